"""The gap to the paper's robots: read the runs of the ``configs/studies/gap/gap_*.yaml`` sweeps and print ours
against the paper row by row (Markdown), and draw one figure of it.

Each gap config sweeps the real loop's non-idealities (tracker latency x tracker noise x servo lag at a 30 Hz
control period; the values and their sources are in each config's header). Per realism level this prints:

* Fig. 2, UR5e: the valid region's bounds (``summary.json``);
* Table I, the UR5e cube: per-axis mean path error, estimated and analytical inverse Jacobian [mm];
* Table II / III, GRABLAB on the Model O and 'E' on the Stewart hand: waypoint error of the estimate [mm] and
  completion;
* peg-in-hole: the UR5e's position error at insertion [mm] and the fraction inserted.

Nothing here is tuned toward the paper's numbers: the rows are what the sweeps gave.

    python scripts/gap_study.py [--runs runs] [--figure docs/gap_study.png]

with the runs made by ``selfid-jax sweep gap_<name>`` (``configs/studies/gap/gap_<name>.yaml``; default run
directories ``runs/gap_<name>``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import pandas as pd

PAPER = {
    "valid_region": (0.33, 1.88),
    "cube_estimated": (1.41, 1.18, 1.73),
    "cube_analytical": (0.35, 0.28, 0.93),
    "grablab": 0.41,
    "stewart_e": 0.28,
    "peg_in_hole": (0.97, 1.54),
}
LEVEL_KEYS = ("latency", "noise_pos", "servo_tau")


def valid_region(run: Path) -> pd.DataFrame:
    """Per realism level: latency, noise, lag, and the valid region's lower / upper bound (NaN: none around 1)."""
    systems = json.loads((run / "summary.json").read_text())["systems"]
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
    d = pd.read_parquet(run / "results.parquet", columns=[*LEVEL_KEYS, "inverse", "arm_pos_mm", "inserted",
                                                            "failed"])
    d["inserted"] = d["inserted"].astype(float)
    return _means(d, ["arm_pos_mm"], "inserted")


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
        f"| latency [steps], noise, lag | UR5e valid region ({_values(vr)}) | UR5e cube x / y / z mm, estimated "
        f"({_values(ce)}) | analytical | GRABLAB mm, completion ({_values(ge)}) | Stewart 'E' mm, completion "
        f"({_values(se)}) | peg-in-hole mm, inserted ({_values(pe)}) |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        f"| **paper (real robots)** | {PAPER['valid_region'][0]}-{PAPER['valid_region'][1]} | "
        f"{' / '.join(map(str, PAPER['cube_estimated']))} | {' / '.join(map(str, PAPER['cube_analytical']))} | "
        f"{PAPER['grablab']} +- 0.16 | {PAPER['stewart_e']} | {PAPER['peg_in_hole'][0]}-{PAPER['peg_in_hole'][1]} |",
    ]

    def axes(r):
        return f"{r['error_x_mm']:.2f} / {r['error_y_mm']:.2f} / {r['error_z_mm']:.2f}"

    def wp(r):
        return f"{r['waypoint_error_mm']:.2f}, {100 * r['completion']:.0f}%"

    for i, label in enumerate(_levels(vr)):
        v = vr.iloc[i]
        region = "none around 1" if np.isnan(v["lower"]) else f"{v['lower']:.1f}-{v['upper']:.1f}"
        p = pe.iloc[i]
        pos = "all failed" if np.isnan(p["arm_pos_mm"]) else f"{p['arm_pos_mm']:.2f}"
        lines.append(f"| {label} | {region} | {axes(ce.iloc[i])} | {axes(ca.iloc[i])} | {wp(ge.iloc[i])} | "
                     f"{wp(se.iloc[i])} | {pos}, {100 * p['inserted']:.0f}% |")
    return "\n".join(lines)


def figure(frames: dict, path: Path) -> None:
    """Four panels, one per table: ours per realism level (x) against the paper's value (a band or a line)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    vr = frames["valid_region"]
    labels = _levels(vr)
    x = np.arange(len(labels))
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), layout="constrained", sharex=True)
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
        ax.semilogy(x, c[["error_x_mm", "error_y_mm", "error_z_mm"]].mean(axis=1), "o-", color=color,
                    label=f"ours, {name} (mean of x/y/z)")
        ax.axhline(np.mean(paper), color=color, ls="--", label=f"paper, {name}: {np.mean(paper):.2f}")
    ax.set(ylabel="mm", title="Table I: UR5e cube, per-axis path error")
    ax.text(0.02, 0.97, _values(frames["cube_est"]), transform=ax.transAxes, va="top", fontsize=7)
    ax.legend(fontsize=7)
    ax = axes[1, 0]
    for key, color, name, paper in (("grablab", "C0", "GRABLAB (Model O)", PAPER["grablab"]),
                                    ("stewart", "C1", "'E' (Stewart hand)", PAPER["stewart_e"])):
        ax.semilogy(x, frames[key]["waypoint_error_mm"], "o-", color=color,
                    label=f"ours, {name} ({_values(frames[key])})")
        ax.axhline(paper, color=color, ls="--", label=f"paper, {name}: {paper}")
    ax.set(ylabel="mm", title="Tables II-III: hands, waypoint error of the estimate")
    ax.legend(fontsize=7)
    ax = axes[1, 1]
    ax.axhspan(*PAPER["peg_in_hole"], color="C2", alpha=0.2, label="paper: 0.97-1.54")
    ax.semilogy(x, frames["peg"]["arm_pos_mm"], "o-", label=f"ours, estimated ({_values(frames['peg'])})")
    ax.set(ylabel="mm", title="Peg-in-hole: UR5e position error at insertion")
    ax.legend(fontsize=7)
    for ax in axes[1]:
        ax.set_xticks(x, labels, rotation=60, ha="right", fontsize=7)
        ax.set_xlabel("realism level: latency [control steps], tracker noise, servo lag")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", default="runs", help="folder holding the gap_* run directories")
    ap.add_argument("--figure", default=None, help="write the figure here (PNG)")
    args = ap.parse_args()
    frames = load(Path(args.runs))
    print(table(frames))
    if args.figure:
        figure(frames, Path(args.figure))
        print(f"\nfigure: {args.figure}")


if __name__ == "__main__":
    main()
