"""selfid-jax online through trossen-arm against trossen-arm-sim's WidowX AI: the table of docs/drivers.md.

    python benchmarks/trossen_sim.py [--seeds 0 1 2] [--out runs/trossen_sim]

Starts ``trossen-arm-sim --host 127.0.0.1`` (the controller's ports TCP 50001 and UDP 50000 must be free), runs the
shipped ``configs/robot/online_trossen_sim.yaml`` for the tasks x,y,z and x,y,z,rx,ry,rz once per seed (each
session starts at the config's ``start`` pose, where the driver moves the arm when it connects), and prints per
session: where it converged, the estimate's ||J Ĵ - I||_F against MuJoCo's Jacobian of the simulator's own MJCF at
the session's first joint reading (tests/trossen_reference.py) and against the driver's model from the controller's
kinematic parameters (``summary.json`` ``reference_error``), the star, the path distance, and the wall times.
About a minute a session on 2 cores. Needs ``pip install ".[test]"`` (trossen-arm, trossen-arm-sim).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import trossen_reference as tr  # noqa: E402

TASKS = {"x,y,z": [], "6-D": ["--set", "selfid.task=x,y,z,rx,ry,rz"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--out", type=Path, default=Path("runs/trossen_sim"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print("| task (seed) | converged at | ||J Ĵ - I||_F (MuJoCo) | reference_error (the controller's parameters) | "
          "star | path distance mean / max | self-ID / following |")
    with tr.trossen_sim(args.out / "trossen-arm-sim.log"):
        for task, extra in TASKS.items():
            for seed in args.seeds:
                out = args.out / f"{task.replace(',', '')}_{seed}"
                cmd = ["selfid-jax", "online", str(ROOT / "configs/robot/online_trossen_sim.yaml"), "--out",
                       str(out), "--set", f"selfid.seed={seed}", "--quiet", *extra]
                code = subprocess.run(cmd, cwd=ROOT, check=False, stderr=subprocess.DEVNULL).returncode
                s = json.loads((out / "summary.json").read_text())
                if not s["converged"]:
                    print(f"| {task} ({seed}) | not converged: {s['status']}, exit {code} | | | | | |")
                    continue
                error = tr.session_error(out)[0]
                ref = s.get("reference_error")
                track = "" if s["track_mean_m"] is None else \
                    f"{1e3 * s['track_mean_m']:.2f} / {1e3 * s['track_max_m']:.2f} mm"
                print(f"| {task} ({seed}) | {s['converged_at']} | {error:.3f} | "
                      f"{'-' if ref is None else f'{ref:.3f}'} | {s['waypoints']}/{s['waypoints_total']} in "
                      f"{s['follow_steps']} moves | {track} | {s['selfid_s']:.1f} s / {s['follow_s']:.1f} s |",
                      flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
