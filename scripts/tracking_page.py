"""The tables of ``docs/results/tracking.md``, rendered from the runs of the shipped tracking and peg-in-hole
configs or from the data file written from them.

    python scripts/tracking_page.py [--runs runs] [--json docs/results/data/tracking.json] [--page PAGE]
    python scripts/tracking_page.py --from-json docs/results/data/tracking.json --page docs/results/tracking.md

with the runs made by ``selfid-jax sweep CONFIG`` for each config in :data:`RUNS` (default run directories
``runs/<config name>``). ``--json`` writes the numbers the tables are made of (each run's summary, less its
per-letter entries, and the size of its protocol); ``--from-json`` renders from such a file instead of the runs;
``--page`` rewrites the page's generated blocks (between ``<!-- tracking:NAME -->`` and
``<!-- /tracking:NAME -->``), which ``tests/test_results_pages.py`` checks against the JSON: the page cannot drift
from the JSON. The JSON names its runs with their fingerprints (``"provenance"``); with ``--keep-rows`` the runs'
rows are copied to ``docs/results/data/runs/`` and the test recomputes every number from them (``from_rows``).

Every row is one tracker-noise level and inverse Jacobian of a run: nothing is picked out. The paper's numbers
(:data:`PAPER`) sit on the noise-free rows, as the paper gives no tracker noise.
"""

from __future__ import annotations

from pathlib import Path

import yaml
from page_blocks import ROWS, cli, provenance_block, run_summary  # scripts/page_blocks.py (python scripts/NAME.py)

#: Run directory name -> the config that makes it.
RUNS = {
    "tracking_ur5e_cube": "configs/tracking/tracking_ur5e_cube.yaml",
    "tracking_stewart_e": "configs/tracking/tracking_stewart_e.yaml",
    "tracking_model_o_grablab": "configs/tracking/tracking_model_o_grablab.yaml",
    "tracking_model_o_rotation_full": "configs/tracking/tracking_model_o_rotation_full.yaml",
    "tracking_peg_in_hole_full": "configs/peg_in_hole/tracking_peg_in_hole_full.yaml",
}
#: The paper's numbers per (run, inverse) on the noise-free rows (Tables I-III, Sec. V-B, V-C).
PAPER = {
    ("tracking_ur5e_cube", "estimated"): "Table I: 1.41 / 1.18 / 1.73 mm; Table II: 3.58 / 4.07 +- 1.95 deg; "
                                         "8 iterations",
    ("tracking_ur5e_cube", "analytical"): "Table I: 0.35 / 0.28 / 0.93 mm; Table II: 2.28 / 2.82 +- 1.74 deg",
    ("tracking_stewart_e", "estimated"): "Sec. V-C: 0.28 +- 0.22 mm waypoint error ('E' of unstated size), 10 "
                                         "iterations; Table I: 0.27 / 0.25 / 0.18 mm",
    ("tracking_model_o_grablab", "estimated"): "Sec. V-B: 0.41 +- 0.16 mm on 12 mm letters, 5.7 +- 1.0 iterations",
    ("tracking_model_o_rotation_full", "estimated"): "Table II (Green Octagon): X 0.37 / 0.56 +- 0.39 deg, "
                                                     "Y 0.74 / 0.57 +- 0.30 deg; 5.0 +- 0.0 iterations",
}
PEG_PAPER = ("| paper (real robots, 5 objects) | 0.97-1.54 per object (sd 0.61-0.72) | - | 0.10-0.41 | 0.39-1.28 "
             "| - | 8.2 +- 0.4 / 5.6 +- 1.0 |")
PAPER_SIZES = {"tracking_model_o_grablab": "2 mm letters", "tracking_stewart_e": "12 mm"}


def runs(where: Path) -> dict[str, tuple[Path, str]]:
    """The runs behind the page: ``{name: (run directory, config)}``."""
    return {name: (where / name, config) for name, config in RUNS.items()}


def from_rows(rows: Path = ROWS) -> dict:
    """The numbers recomputed from the runs' kept rows (``rows/<run>``), without provenance."""
    return extract(rows)


def extract(runs: Path) -> dict:
    """Per run in :data:`RUNS`: its protocol's size and its summary's numbers (recomputed from its rows,
    :func:`page_blocks.run_summary`) (tracking: per system, noise level
    and inverse, and per rotation axis; peg-in-hole: per noise level, inverse and layout)."""
    out = {}
    for name in RUNS:
        run = runs / name
        if not (run / "results.parquet").exists():
            raise SystemExit(f"{run}: no results.parquet; run: selfid-jax sweep {RUNS[name]}")
        summary = run_summary(run)
        cfg = yaml.safe_load((run / "config.yaml").read_text())
        size = {k: cfg[k] for k in ("n_configs", "n_trials") if k in cfg}
        if "layouts" in cfg:
            size["layouts"] = len(cfg["layouts"])
        if "path" in cfg and "height" in cfg["path"]:
            size["height_mm"] = 1e3 * cfg["path"]["height"]
        if "systems" in summary:
            numbers = {s: {k: v for k, v in e.items() if k in ("pose_noise_mm", "rotations")}
                       for s, e in summary["systems"].items()}
        else:
            numbers = {"pose_noise_mm": summary["pose_noise_mm"]}
        out[name] = {"config": RUNS[name], "size": size, "numbers": numbers}
    return out


def _ms(m: dict | None, digits: int = 2) -> str:
    if m is None or m.get("mean") is None:
        return "-"
    return f"{m['mean']:.{digits}f} +- {m['sd']:.{digits}f}"


def _mean(m: dict | None, digits: int = 2) -> str:
    return "-" if m is None or m.get("mean") is None else f"{m['mean']:.{digits}f}"


def _size(size: dict) -> str:
    parts = []
    if "layouts" in size:
        parts.append(f"{size['layouts']} layouts")
    if "n_configs" in size:
        parts.append(f"{size['n_configs']} starts")
    if size.get("n_trials", 1) > 1:
        parts.append(f"{size['n_trials']} trials")
    return " x ".join(parts)


def _row(label: str, noise: str, inverse: str, m: dict, paper: str) -> str:
    xyz = " / ".join(_mean(m.get(f"error_{a}_mm")) for a in "xyz")
    rot = f"{_mean(m.get('rot_final_deg'))} / {_mean(m.get('rot_step_deg'))}"
    conv = _mean(m.get("converged_at"), 1) if inverse == "estimated" else ""
    if conv == "-1.0" or (inverse == "estimated" and m.get("converged_at", {}).get("mean") is None):
        conv = "never"
    return (f"| {label} | {noise} | {inverse} | {100 * m['completion']['mean']:.0f}% | "
            f"{_ms(m.get('waypoint_error_mm'))} | {xyz} | {rot} | {conv} | {paper} |")


def tracking_table(data: dict) -> str:
    """One row per run, system, noise level and inverse (per rotation axis for rotation paths), Markdown."""
    lines = ["| experiment (config, size) | tracker noise mm, deg | inverse | completed | waypoint error mm | "
             "x / y / z mm | rotation end / per step deg | converged at | paper (noise-free rows) |",
             "| --- | --- | --- | --- | --- | --- | --- | --- | --- |"]
    for name in RUNS:
        if name == "tracking_peg_in_hole_full":
            continue
        run = data[name]
        height = PAPER_SIZES.get(name)
        label = f"`{Path(run['config']).name}` ({_size(run['size'])}{', ' + height if height else ''})"
        for entry in run["numbers"].values():
            per = entry.get("rotations") or {"": entry["pose_noise_mm"]}
            for axis, levels in per.items():
                for noise, inverses in levels.items():
                    for inverse, m in inverses.items():
                        what = label + (f", about {axis.split(':')[1][1:].upper()}" if axis else "")
                        paper = PAPER.get((name, inverse), "") if float(noise) == 0 and not (
                            axis and axis.split(":")[1] != "rx") else ""
                        lines.append(_row(what, noise, inverse, m, paper))
    return "\n".join(lines)


def peg_table(data: dict) -> str:
    """Table III: per noise level and inverse, over all layouts and trials, with the range of the layouts'
    means. Markdown."""
    run = data["tracking_peg_in_hole_full"]
    lines = [f"| `{Path(run['config']).name}` ({_size(run['size'])}) | UR5e waypoint error mm (layouts' means) | "
             "UR5e position at insertion mm | UR5e rotation deg | Model O rotation deg | inserted | "
             "self-ID iterations arm / hand |",
             "| --- | --- | --- | --- | --- | --- | --- |", PEG_PAPER]
    for noise, inverses in run["numbers"]["pose_noise_mm"].items():
        for inverse, level in inverses.items():
            a = level["all"]
            means = [lo["arm_wp_mm"]["mean"] for lo in level["layouts"].values() if lo["arm_wp_mm"]["mean"] is not None]
            spread = f" ({min(means):.2f}-{max(means):.2f})" if means else ""
            conv = (f"{_ms(a['arm_converged_at'], 1)} / {_ms(a['hand_converged_at'], 1)}"
                    if inverse == "estimated" else "")
            lines.append(f"| {inverse}, {noise} mm / {noise} deg noise | {_ms(a['arm_wp_mm'])}{spread} | "
                         f"{_ms(a['arm_pos_mm'])} | {_ms(a['arm_rot_deg'])} | {_ms(a['hand_rot_deg'])} | "
                         f"{100 * a['inserted']:.0f}% | {conv} |")
    return "\n".join(lines)


def blocks(data: dict) -> dict[str, str]:
    """The generated blocks of the page: ``{"tracking": ..., "peg": ..., "provenance": ...}``."""
    return {"tracking": tracking_table(data), "peg": peg_table(data),
            "provenance": provenance_block(data["provenance"])}


def main():
    cli(__doc__, "tracking", extract, blocks, run_flag="--runs", run_default="runs", runs=runs, from_rows=from_rows)


if __name__ == "__main__":
    main()
