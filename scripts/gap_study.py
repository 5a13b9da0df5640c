"""The gap to the paper's robots: read the runs of the ``configs/studies/gap/gap_*.yaml`` sweeps and print ours
against the paper row by row (Markdown), and draw one figure of it.

Each gap config sweeps the real loop's non-idealities (tracker latency x tracker noise x servo lag at a 30 Hz
control period; the values and their sources are in each config's header). Per realism level this prints:

* Fig. 2, UR5e: the valid region's bounds (``summary.json``);
* Table I, the UR5e cube: per-axis mean path error, estimated and analytical inverse Jacobian [mm];
* Sec. V-B / V-C, GRABLAB on the Model O and 'E' on the Stewart hand: waypoint error of the estimate [mm] and
  completion;
* Table III, peg-in-hole: the UR5e's waypoint error (mean +- sd over its four waypoints) [mm] and the fraction
  inserted.

Nothing here is tuned toward the paper's numbers: the rows are what the sweeps gave. Each robot's realism
profile (:data:`PROFILE`) is one level of each sweep; :func:`profile_table` sets that level beside the paper, column
by column, with completion beside every error and the paper's protocol beside ours (:data:`PAPER_SOURCE`,
:data:`PROTOCOL`). The other levels are a sensitivity study. The order, as it happened: the values the sweeps take
were committed in the configs before any of their results (04f84b7; the tracker noise then from a stereo camera's
manual), the 12-level results were published first (9ca7c31, 2026-12-02), and the profile, which level stands for
each robot, was picked three days later (393447c, 2026-12-05), with those results read. On 2026-12-06 (issue 53)
the tracker noise became a measurement: ``scripts/gap_camera_noise.py`` tracks a tag on rendered frames of a
simulated camera per robot's scale (assumptions stated there and in each config's header) and the configs' noise
level is its result (:data:`gap_camera_noise.NOISE_POS`); the sweeps were rerun with it. The choice of level
(latency 0 with noise and lag) was not revisited.

    python scripts/gap_study.py [--runs runs] [--figure docs/figures/gap_study.png] [--json F]
                                [--keep-rows] [--page PAGE]
    python scripts/gap_study.py --from-json docs/results/data/gap_study.json --page docs/results/gap.md

with the runs made by ``selfid-jax sweep gap_<name>`` (``configs/studies/gap/gap_<name>.yaml``; default run
directories ``runs/gap_<name>``). ``--json`` writes the per-level numbers the tables are made of;
``--from-json`` renders from such a file instead of the runs; ``--page`` rewrites the generated blocks of a
results page (between ``<!-- gap_study:NAME -->`` and ``<!-- /gap_study:NAME -->``), which
``tests/test_results_pages.py`` checks against the JSON: the page cannot drift from the JSON. The JSON names its
runs with their fingerprints (``"provenance"``, :func:`page_blocks.provenance`); ``--keep-rows`` copies the runs'
rows into ``docs/results/data/runs/``, from which the test recomputes every number (:func:`from_rows`), so the JSON
cannot drift from the runs either.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd
from gap_camera_noise import NOISE_POS, camera_table  # scripts/gap_camera_noise.py: the measured noise
from page_blocks import ROWS, from_runs, provenance_block, run_summary, write_blocks  # scripts/page_blocks.py

PAPER = {
    "valid_region": (0.33, 1.88),
    "cube_estimated": (1.41, 1.18, 1.73),
    "cube_analytical": (0.35, 0.28, 0.93),
    "grablab": 0.41,
    "stewart_e": 0.28,
    "peg_in_hole": (0.97, 1.54),
}
#: Where each paper number comes from: only Fig. 2 is a simulation (kinematic); the tables are the real robots.
PAPER_SOURCE = {
    "valid_region": "Fig. 2 (kinematic simulation of a UR5e)",
    "cube": "Table I (real UR5e, AprilTag)",
    "grablab": "Sec. V-B text (real Model O, 12 mm letters, waypoint error)",
    "stewart_e": "Sec. V-C text (real Stewart Hand, waypoint error)",
    "peg_in_hole": "Table III (real UR5e, waypoint error, 5 objects)",
}
#: Each column's protocol: the paper's (what it states, and what it leaves unstated) beside ours.
PROTOCOL = {
    "valid_region": "paper: 10 configurations x 10 tests per eps_limit (Sec. III-C, stated for its 2-link arm and "
                    "repeated for the UR5e); its path size, step, tolerance and eps_limit grid are not stated. Ours: "
                    "3 starts x 3 trials per eps_limit on a 16-point grid from 0 to 3 (steps of 0.2), a 50 mm star, "
                    "2.5 mm steps, 0.5 mm tolerance; the 10 x 10 run on a 61-point grid (steps of 0.05) gives "
                    "0.20-2.05 ideal (docs/results/valid_region.md)",
    "cube": "paper: a 150 mm cube at constant orientation (Sec. V-E), Table I's 'absolute error at each control "
            "step' per axis (Sec. V-B); what the error is measured against (the path, the current waypoint or the "
            "goal) and the start configuration are not stated. Ours: the mean distance to the commanded path per "
            "axis over the control steps, 150 mm cube, 1 start per level drawn around the UR5e's home pose",
    "grablab": "paper: waypoint error over GRABLAB in 12 mm letters, one object per letter (Sec. V-B, Fig. 6); its "
               "waypoint tolerance is not stated. Ours: 2 mm letters, not 12 mm: the model reaches a 4.9 mm radius "
               "about its start and no start completes a letter above 6 mm (docs/results/hands.md); one object, "
               "1 start per level; waypoint tolerance 0.05 mm",
    "stewart_e": "paper: waypoint error writing 'E' (Sec. V-C); the letter's size and the waypoint tolerance are not "
                 "stated (its 12 mm height is given for the Model O letters only). Ours: a 12 mm 'E' (our choice: "
                 "the Model O letters' height), 1 start per level, waypoint tolerance 0.1 mm",
    "peg_in_hole": "paper: Table III's 'UR5e waypoint errors' per object, 5 objects with holes in different places; "
                   "the arm grasps the peg, the hand turns it to perpendicular, the arm moves it to the hole and "
                   "releases it (Sec. V-F); which waypoints the error averages is not stated. Ours: the waypoint "
                   "error over the arm's grasp, lift, over-the-hole and insertion waypoints (tolerance 0.5 mm), 5 "
                   "layouts; the grasp is not simulated (the peg is in the hand from the start), the hand tilts the "
                   "peg 0.15 rad instead of turning it perpendicular (our Model O's tilt guard is 15 deg), no "
                   "contact between peg and hole",
}
#: One realism profile per robot (a level of each gap sweep): latency 0 (a loop that waits for the next frame after
#: each move; the paper states neither its loop's latency nor its camera's rate: latency 0 is our inference from
#: this sweep's latency rows, where one step of latency puts our full-gain step at its stability limit), tracker
#: noise measured on a simulated camera per robot's scale (:data:`gap_camera_noise.NOISE_POS`: 0.37 mm per axis for
#: the arm's camera, 0.15 mm for the hands'; until 2026-12-06 it was 0.5 and 0.2 mm, taken from a stereo camera's
#: manual), servo lag by actuator (UR5e joints, Dynamixel tendon servos, the Stewart Hand's geared linear
#: actuators). The lag values were committed in the configs before any result (04f84b7); this choice of level,
#: latency 0 with noise and lag, was made after the 12-level results had been read (9ca7c31, then 393447c).
PROFILE = {
    "valid_region": dict(latency=0, noise_pos=NOISE_POS["ur5e"], servo_tau=0.02),
    "cube": dict(latency=0, noise_pos=NOISE_POS["ur5e"], servo_tau=0.02),
    "grablab": dict(latency=0, noise_pos=NOISE_POS["hand"], servo_tau=0.05),
    "stewart_e": dict(latency=0, noise_pos=NOISE_POS["hand"], servo_tau=0.1),
    "peg_in_hole": dict(latency=0, noise_pos=NOISE_POS["ur5e"], servo_tau=0.05),
}
#: Run directory name -> the config that makes it.
RUNS = {name: f"configs/studies/gap/{name}.yaml" for name in (
    "gap_valid_region_ur5e", "gap_tracking_ur5e_cube", "gap_tracking_model_o_grablab", "gap_tracking_stewart_e",
    "gap_peg_in_hole")}
LEVEL_KEYS = ("latency", "noise_pos", "servo_tau")


def valid_region(run: Path) -> pd.DataFrame:
    """Per realism level: latency, noise, lag, and the valid region's lower / upper bound (NaN: none around 1), from
    the run's summary recomputed from its rows (:func:`page_blocks.run_summary`)."""
    systems = run_summary(run)["systems"]
    rows = []
    for entry in systems.values():
        r = entry["realism"]
        has = bool(entry.get("contains_one"))
        rows.append(dict(latency=r["latency"], noise_pos=r["noise_pos"], servo_tau=r["servo_tau"],
                         lower=entry["lower"] if has else np.nan, upper=entry["upper"] if has else np.nan))
    return pd.DataFrame(rows).sort_values(list(LEVEL_KEYS)).reset_index(drop=True)


def tracking(run: Path) -> pd.DataFrame:
    """Per realism level and inverse: mean per-axis path error and waypoint error [mm] of the rollouts that did not
    fail, and the mean completion."""
    errors = ["waypoint_error_mm", "error_x_mm", "error_y_mm", "error_z_mm"]
    d = pd.read_parquet(run / "results.parquet", columns=[*LEVEL_KEYS, "inverse", "completion", "failed", *errors])
    return _means(d, errors, "completion")


def _means(d: pd.DataFrame, errors: list[str], fraction: str) -> pd.DataFrame:
    """Per level and inverse: the mean of ``fraction`` over every rollout, the errors' means over those that did
    not fail (as the experiments' reports count them)."""
    keys = [*LEVEL_KEYS, "inverse"]
    out = d.groupby(keys, sort=True)[[fraction]].mean()
    ok = d[~d["failed"].astype(bool)].groupby(keys, sort=True)[errors].mean()
    return out.join(ok).reset_index()


def peg(run: Path) -> pd.DataFrame:
    """Per realism level and inverse: the arm's waypoint error (Table III's metric: mean and sd pooled over the
    four waypoints of the rollouts that did not fail) and its final distance at insertion [mm], and the fraction
    inserted."""
    d = pd.read_parquet(run / "results.parquet", columns=[*LEVEL_KEYS, "inverse", "arm_wp_mm", "arm_pos_mm",
                                                            "inserted", "failed"])
    d["inserted"] = d["inserted"].astype(float)
    out = _means(d.drop(columns="arm_wp_mm"), ["arm_pos_mm"], "inserted")
    ok = d[~d["failed"].astype(bool)]
    pooled = {k: np.concatenate([np.asarray(v, float) for v in g["arm_wp_mm"]])
              for k, g in ok.groupby([*LEVEL_KEYS, "inverse"], sort=True)}
    keys = list(zip(*(out[c] for c in [*LEVEL_KEYS, "inverse"])))
    out["arm_wp_mm"] = [pooled[k].mean() if k in pooled else np.nan for k in keys]
    out["arm_wp_sd_mm"] = [pooled[k].std() if k in pooled else np.nan for k in keys]
    return out


def _pick(df: pd.DataFrame, inverse: str) -> pd.DataFrame:
    """The rows of one inverse, in level order (latency, then noise, then lag, each ascending), indexed 0..L-1."""
    return df[df["inverse"] == inverse].sort_values(list(LEVEL_KEYS)).reset_index(drop=True)


def _levels(frame: pd.DataFrame) -> list[str]:
    """Each level as 'latency, noise on/off, lag on/off' (the configs share the grid; the values differ)."""
    return [f"{int(r['latency'])}, {'noise' if r['noise_pos'] > 0 else '-'}, {'lag' if r['servo_tau'] > 0 else '-'}"
            for _, r in frame.iterrows()]


def _values(frame: pd.DataFrame) -> str:
    return (f"noise {1e3 * frame['noise_pos'].max():g} mm, lag {1e3 * frame['servo_tau'].max():g} ms")


def load(runs: Path) -> dict:
    """Every gap run's per-level frame, each in level order."""
    vr = valid_region(runs / "gap_valid_region_ur5e")
    cube = tracking(runs / "gap_tracking_ur5e_cube")
    return dict(valid_region=vr, cube_est=_pick(cube, "estimated"), cube_ana=_pick(cube, "analytical"),
                grablab=_pick(tracking(runs / "gap_tracking_model_o_grablab"), "estimated"),
                stewart=_pick(tracking(runs / "gap_tracking_stewart_e"), "estimated"),
                peg=_pick(peg(runs / "gap_peg_in_hole"), "estimated"))


def table(frames: dict) -> str:
    """Ours per realism level against the paper's real robots, Markdown."""
    vr, ce, ca, ge, se, pe = (frames[k] for k in ("valid_region", "cube_est", "cube_ana", "grablab", "stewart",
                                                  "peg"))
    n = {len(f) for f in (vr, ce, ca, ge, se, pe)}
    if len(n) != 1:
        raise SystemExit(f"the gap runs have different numbers of realism levels: {sorted(n)}")
    lines = [
        f"| latency [steps], noise, lag | UR5e valid region ({_values(vr)}) | UR5e cube x / y / z mm, completion, "
        f"estimated ({_values(ce)}) | analytical | GRABLAB mm, completion ({_values(ge)}) | Stewart 'E' mm, completion "
        f"({_values(se)}) | peg-in-hole waypoint mm, inserted ({_values(pe)}) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        "| **paper** (Fig. 2: simulation; the rest: real robots) | "
        f"{PAPER['valid_region'][0]}-{PAPER['valid_region'][1]} | "
        f"{' / '.join(map(str, PAPER['cube_estimated']))} | {' / '.join(map(str, PAPER['cube_analytical']))} | "
        f"{PAPER['grablab']} +- 0.16 | {PAPER['stewart_e']} | {PAPER['peg_in_hole'][0]}-{PAPER['peg_in_hole'][1]} |",
    ]

    def axes(r):
        return f"{r['error_x_mm']:.2f} / {r['error_y_mm']:.2f} / {r['error_z_mm']:.2f}, {100 * r['completion']:.0f}%"

    def wp(r):
        return f"{r['waypoint_error_mm']:.2f}, {100 * r['completion']:.0f}%"

    for i, label in enumerate(_levels(vr)):
        v = vr.iloc[i]
        region = "none around 1" if np.isnan(v["lower"]) else f"{v['lower']:.1f}-{v['upper']:.1f}"
        p = pe.iloc[i]
        pos = "all failed" if np.isnan(p["arm_wp_mm"]) else f"{p['arm_wp_mm']:.2f} +- {p['arm_wp_sd_mm']:.2f}"
        lines.append(f"| {label} | {region} | {axes(ce.iloc[i])} | {axes(ca.iloc[i])} | {wp(ge.iloc[i])} | "
                     f"{wp(se.iloc[i])} | {pos}, {100 * p['inserted']:.0f}% |")
    return "\n".join(lines)


def _level(frame: pd.DataFrame, level: dict) -> pd.Series:
    """The row of ``frame`` at ``level`` (its latency, noise and lag)."""
    hit = frame[np.logical_and.reduce([np.isclose(frame[k], v) for k, v in level.items()])]
    if len(hit) != 1:
        raise SystemExit(f"the runs have {len(hit)} rows at the profile level {level}")
    return hit.iloc[0]


def profile_table(frames: dict) -> str:
    """Each column's paper number (with its source) beside ours under that robot's realism profile and ideal,
    completion beside every error, and the paper's protocol beside ours. Markdown."""
    def wp(r):
        return f"{r['waypoint_error_mm']:.2f} mm, {100 * r['completion']:.0f}% completed"

    def axes(r):
        return (f"{r['error_x_mm']:.2f} / {r['error_y_mm']:.2f} / {r['error_z_mm']:.2f} mm, "
                f"{100 * r['completion']:.0f}% completed")

    def region(r):
        return "none around 1" if np.isnan(r["lower"]) else f"{r['lower']:.1f}-{r['upper']:.1f}"

    def peg(r):
        pos = "all failed" if np.isnan(r["arm_wp_mm"]) else f"{r['arm_wp_mm']:.2f} +- {r['arm_wp_sd_mm']:.2f} mm"
        return f"{pos}, {100 * r['inserted']:.0f}% inserted"

    ideal = dict(latency=0, noise_pos=0.0, servo_tau=0.0)
    cols = [
        ("UR5e valid region", "valid_region", f"{PAPER['valid_region'][0]}-{PAPER['valid_region'][1]}",
         frames["valid_region"], region),
        ("UR5e cube, estimated", "cube", " / ".join(map(str, PAPER["cube_estimated"])) + " mm", frames["cube_est"],
         axes),
        ("UR5e cube, analytical", "cube", " / ".join(map(str, PAPER["cube_analytical"])) + " mm",
         frames["cube_ana"], axes),
        ("GRABLAB, Model O", "grablab", f"{PAPER['grablab']} +- 0.16 mm", frames["grablab"], wp),
        ("'E', Stewart Hand", "stewart_e", f"{PAPER['stewart_e']} +- 0.22 mm", frames["stewart"], wp),
        ("peg-in-hole, UR5e", "peg_in_hole",
         f"{PAPER['peg_in_hole'][0]}-{PAPER['peg_in_hole'][1]} mm per object, sd 0.61-0.72",
         frames["peg"], peg),
    ]
    lines = ["| column | paper (source) | ours, profile (latency, noise, lag) | ours, ideal | protocol: the paper's, "
             "ours |",
             "| --- | --- | --- | --- | --- |"]
    for name, key, paper, frame, fmt in cols:
        prof = PROFILE[key]
        label = (f"{prof['latency']}, {1e3 * prof['noise_pos']:g} mm, {1e3 * prof['servo_tau']:g} ms")
        lines.append(f"| {name} | {paper} ({PAPER_SOURCE[key]}) | {fmt(_level(frame, prof))} ({label}) | "
                     f"{fmt(_level(frame, ideal))} | {PROTOCOL[key]} |")
    return "\n".join(lines)


FRAMES = ("valid_region", "cube_est", "cube_ana", "grablab", "stewart", "peg")


def to_json(frames: dict) -> dict:
    """The frames as ``{name: [row records]}`` (NaN as null), what ``--json`` writes and ``from_json`` reads."""
    return {k: json.loads(frames[k].to_json(orient="records")) for k in FRAMES}


def from_json(data: dict) -> dict:
    """Inverse of :func:`to_json`."""
    frames = {}
    for k in FRAMES:
        f = pd.DataFrame.from_records(data[k])
        frames[k] = f.astype({c: float for c in f.columns if c != "inverse"})
    return frames


def blocks(frames: dict) -> dict[str, str]:
    """The generated blocks of the results page: ``{"profile": ..., "levels": ...}``."""
    return {"profile": profile_table(frames), "levels": table(frames)}


def runs(where: Path) -> dict[str, tuple[Path, str]]:
    """The runs behind the page: ``{name: (run directory, config)}``."""
    return {name: (where / name, config) for name, config in RUNS.items()}


def from_rows(rows: Path = ROWS) -> dict:
    """The per-level numbers recomputed from the runs' kept rows (``rows/<run>``), as :func:`to_json` writes them,
    without provenance."""
    return to_json(load(rows))


def page_blocks_of(data: dict) -> dict[str, str]:
    """Every generated block of the page from a data file's contents: the tables and the provenance."""
    return {**blocks(from_json(data)), "camera": camera_table(), "provenance": provenance_block(data["provenance"])}


def write_page(page: Path, data: dict) -> None:
    """Replace each ``<!-- gap_study:NAME -->`` ... ``<!-- /gap_study:NAME -->`` block of ``page``."""
    write_blocks(page, "gap_study", page_blocks_of(data))


def figure(frames: dict, path: Path) -> None:
    """Four panels, one per table: ours per realism level (x) against the paper's value (a band or a line). The
    profile's level is shaded grey in each panel (every robot's profile is its config's "0, noise, lag" level);
    hollow markers are levels that did not complete their path (or insert every peg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vr = frames["valid_region"]
    labels = _levels(vr)
    x = np.arange(len(labels))
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), layout="constrained", sharex=True)
    for ax, (key, frame) in zip(axes.flat, (("valid_region", vr), ("cube", frames["cube_est"]),
                                            ("grablab", frames["grablab"]), ("peg_in_hole", frames["peg"]))):
        at = [i for i in range(len(frame)) if all(np.isclose(frame.iloc[i][k], v) for k, v in PROFILE[key].items())]
        for i in at:
            ax.axvspan(i - 0.4, i + 0.4, color="0.85", zorder=0, label="the profile's level")

    def line(ax, frame, y, done, color, label):
        """Ours per level: filled markers where ``done`` (the path completed), hollow where not."""
        y, done = np.asarray(y, float), np.asarray(done, bool)
        ax.plot(x, y, "-", color=color, label=label)
        ax.plot(x[done], y[done], "o", color=color)
        ax.plot(x[~done], y[~done], "o", mfc="white", color=color)
    ax = axes[0, 0]
    ax.axhspan(*PAPER["valid_region"], color="C2", alpha=0.2, label="paper's UR5e: 0.33-1.88")
    none = np.isnan(vr["lower"].to_numpy())
    ax.vlines(x[~none], vr["lower"].to_numpy()[~none], vr["upper"].to_numpy()[~none], color="C0", lw=4,
              label=f"ours ({_values(vr)})")
    ax.plot(x[none], np.ones(none.sum()), "x", color="C3", ms=8, label="ours: none around 1")
    ax.set(ylabel="eps_limit", title="Fig. 2: UR5e valid region")
    ax.legend(fontsize=7, loc="upper right")
    ax = axes[0, 1]
    for key, color, paper in (("cube_est", "C0", PAPER["cube_estimated"]), ("cube_ana", "C1",
                                                                            PAPER["cube_analytical"])):
        c = frames[key]
        name = "estimated" if key == "cube_est" else "analytical"
        ax.set_yscale("log")
        line(ax, c, c[["error_x_mm", "error_y_mm", "error_z_mm"]].mean(axis=1), c["completion"] >= 1.0, color,
             f"ours, {name} (mean of x/y/z)")
        ax.axhline(np.mean(paper), color=color, ls="--", label=f"paper, {name}: {np.mean(paper):.2f}")
    ax.set(ylabel="mm", title="Table I: UR5e cube, per-axis path error")
    ax.text(0.02, 0.97, _values(frames["cube_est"]), transform=ax.transAxes, va="top", fontsize=7)
    ax.legend(fontsize=7)
    ax = axes[1, 0]
    for key, color, name, paper in (("grablab", "C0", "GRABLAB (Model O)", PAPER["grablab"]),
                                    ("stewart", "C1", "'E' (Stewart hand)", PAPER["stewart_e"])):
        ax.set_yscale("log")
        line(ax, frames[key], frames[key]["waypoint_error_mm"], frames[key]["completion"] >= 1.0, color,
             f"ours, {name} ({_values(frames[key])})")
        ax.axhline(paper, color=color, ls="--", label=f"paper, {name}: {paper}")
    ax.set(ylabel="mm", title="Sec. V-B, V-C: hands, waypoint error of the estimate")
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    ax.axhspan(*PAPER["peg_in_hole"], color="C2", alpha=0.2, label="paper: 0.97-1.54")
    ax.set_yscale("log")
    line(ax, frames["peg"], frames["peg"]["arm_wp_mm"], frames["peg"]["inserted"] >= 1.0, "C0",
         f"ours, estimated ({_values(frames['peg'])})")
    ax.set(ylabel="mm", title="Table III: peg-in-hole, UR5e waypoint error")
    ax.legend(fontsize=7)
    for ax in axes[1]:
        ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
        ax.set_xlabel("realism level: latency [control steps], tracker noise, servo lag\n"
                      "(grey: the profile's level; hollow: not completed / not every peg inserted)")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", default="runs", help="folder holding the gap_* run directories")
    ap.add_argument("--figure", default=None, help="write the figure here (PNG)")
    ap.add_argument("--json", default=None, help="write the per-level numbers here")
    ap.add_argument("--keep-rows", action="store_true", help="copy the runs' rows to docs/results/data/runs")
    ap.add_argument("--from-json", default=None, help="read the per-level numbers from here, not from the runs")
    ap.add_argument("--page", default=None, help="rewrite this page's generated blocks")
    args = ap.parse_args()
    if args.from_json:
        data = json.loads(Path(args.from_json).read_text())
    else:
        data = from_runs(lambda where: to_json(load(where)), runs, Path(args.runs),
                         keep=from_rows if args.keep_rows else None)
    frames = from_json(data)
    if args.json:
        Path(args.json).parent.mkdir(parents=True, exist_ok=True)
        Path(args.json).write_text(json.dumps(data, indent=1) + "\n")
    print(profile_table(frames))
    print()
    print(table(frames))
    if args.page:
        write_page(Path(args.page), data)
        print(f"\nrewrote the generated blocks of {args.page}")
    if args.figure:
        figure(frames, Path(args.figure))
        print(f"\nfigure: {args.figure}")


if __name__ == "__main__":
    main()
