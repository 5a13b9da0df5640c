"""The bounds table of ``docs/results/valid_region.md``, rendered from the run of
``configs/valid_region/valid_region_all.yaml`` (the four systems of the paper's Fig. 2) or from the data file
written from it.

    python scripts/valid_region_page.py [--run runs/valid_region_all] [--json docs/results/data/valid_region.json]
                                        [--page docs/results/valid_region.md]
    python scripts/valid_region_page.py --from-json docs/results/data/valid_region.json \
        --page docs/results/valid_region.md

``--json`` writes what the table is made of (per system: the bounds, the number of rollouts and the protocol
from the run's config); ``--from-json`` renders from such a file; ``--page`` rewrites the page's generated block
(between ``<!-- valid_region:bounds -->`` and ``<!-- /valid_region:bounds -->``), which
``tests/test_results_pages.py`` checks against the JSON: the page cannot drift from the JSON. The JSON
names its runs with their fingerprints (``"provenance"``); with ``--keep-rows`` the runs' rows are copied to
``docs/results/data/runs/`` and the test recomputes every number from them (``from_rows``).
"""

from __future__ import annotations

from pathlib import Path

import yaml
from page_blocks import ROWS, cli, provenance_block, run_summary  # scripts/page_blocks.py (python scripts/NAME.py)

CONFIG = "configs/valid_region/valid_region_all.yaml"
#: Fig. 2's valid regions (Sec. III-C: kinematic simulations; the 2-link arm is its planar example).
PAPER = {"two_link": (0.33, 1.67), "ur5e": (0.33, 1.88), "stewart_hand": (0.12, 2.09), "model_o": (0.22, 1.78)}
SIX_D = {"stewart_hand"}  # 6-D tasks: a position and a rotation step and tolerance
LABELS = {"two_link": "2-link arm", "ur5e": "UR5e (position)", "stewart_hand": "Stewart Hand (6-D)",
          "model_o": "Model O (POM position)"}


NAME = "valid_region_all"


def runs(where: Path) -> dict[str, tuple[Path, str]]:
    """The run behind the page: ``{name: (run directory, config)}``."""
    return {NAME: (where, CONFIG)}


def extract(run: Path) -> dict:
    """Per system of the run (its summary recomputed from its rows, :func:`page_blocks.run_summary`): its bounds
    (None where no valid region contains 1), rollouts and protocol."""
    if not (run / "results.parquet").exists():
        raise SystemExit(f"{run}: no results.parquet; run: selfid-jax sweep {CONFIG}")
    summary = run_summary(run)
    cfg = yaml.safe_load((run / "config.yaml").read_text())
    protocols = {e["system"]: {"path": e["path"], "controller": e["controller"]} for e in cfg["systems"]}
    systems = {}
    for name, e in summary["systems"].items():
        has = bool(e.get("contains_one"))
        systems[name] = {"lower": e["lower"] if has else None, "upper": e["upper"] if has else None,
                         "n_rollouts": e["n_rollouts"], **protocols[name]}
    return {"config": CONFIG, "n_configs": cfg["n_configs"], "n_trials": cfg["n_trials"],
            "eps_limits": cfg["eps_limits"], "completion_threshold": cfg["completion_threshold"],
            "systems": systems}


def _protocol(name: str, p: dict) -> str:
    c = p["controller"]
    rot = name in SIX_D
    step = f"{1e3 * c['max_step']:g} mm" + (f" / {c['max_rot_step']:g} rad" if rot else "")
    tol = f"{1e3 * c['tol']:g} mm" + (f" / {c['rot_tol']:g} rad" if rot else "")
    return (f"star radius {1e3 * p['path']['size']:g} mm{' at constant orientation' if rot else ''}, step {step}, "
            f"tol {tol}, budget {c['steps']} steps")


#: The paper's protocol for Fig. 2 (Sec. III-C): what it states, and what it does not.
PAPER_PROTOCOL = ("10 configurations x 10 tests per eps_limit on a star; star size, step, tolerance, budget and "
                  "eps_limit grid not stated")


def bounds_table(data: dict) -> str:
    """Ours beside Fig. 2's bounds per system, with the paper's protocol in the header and ours per row. Markdown."""
    grid = data["eps_limits"]
    ours = (f"our protocol ({data['n_configs']} starts x {data['n_trials']} trials per eps_limit, {grid['num']} "
            f"eps_limits from {grid['start']:g} to {grid['stop']:g})")
    lines = [f"| system | ours | paper (Fig. 2, kinematic simulation; {PAPER_PROTOCOL}) | rollouts | {ours} |",
             "| --- | --- | --- | --- | --- |"]
    for name, s in data["systems"].items():
        ours = "none around 1" if s["lower"] is None else f"{s['lower']:.2f}x - {s['upper']:.2f}x"
        lo, hi = PAPER[name]
        lines.append(f"| {LABELS.get(name, name)} | {ours} | {lo}x - {hi}x | {s['n_rollouts']} | "
                     f"{_protocol(name, s)} |")
    return "\n".join(lines)


def blocks(data: dict) -> dict[str, str]:
    """The generated blocks of the page: ``{"bounds": ..., "provenance": ...}``."""
    return {"bounds": bounds_table(data), "provenance": provenance_block(data.get("provenance", []))}


def from_rows(rows: Path = ROWS) -> dict:
    """The numbers recomputed from the run's kept rows (``rows/valid_region_all``), without provenance."""
    return extract(rows / NAME)


def main():
    cli(__doc__, "valid_region", extract, blocks, run_flag="--run", run_default="runs/valid_region_all",
        runs=runs, from_rows=from_rows)


if __name__ == "__main__":
    main()
