"""selfid-jax online through libfranka against franky-sim's FR3: the table of docs/drivers.md.

    python benchmarks/franka_sim.py [--seeds 0 1 2] [--out runs/franka_sim]

Starts ``franky-sim -s mujoco`` (127.0.0.1:1337, which must be free), runs the shipped
``configs/robot/online_franka_sim.yaml`` for the tasks x,y,z and x,y,z,rx,ry,rz once per seed (each session
starts where the previous one left the arm, as on a real arm), and prints per session: where it converged, the
estimate's ||J Ĵ - I||_F against MuJoCo's Jacobian of the simulator's own fr3.xml at the session's first joint
reading (tests/franka_reference.py) and against libfranka's model (``summary.json`` ``reference_error``), the
star, the path distance, and the wall times. About a minute a session on 2 cores. Needs ``pip install
".[test]"`` (franky-control, franky-sim).
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))
import franka_reference as fr  # noqa: E402

TASKS = {"x,y,z": [], "6-D": ["--set", "selfid.task=x,y,z,rx,ry,rz"]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    p.add_argument("--out", type=Path, default=Path("runs/franka_sim"))
    args = p.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    print("| task (seed) | converged at | ||J Ĵ - I||_F (MuJoCo) | reference_error (libfranka's model) | star | "
          "path distance mean / max | self-ID / following |")
    with fr.franky_sim(args.out / "franky-sim.log"):
        for task, extra in TASKS.items():
            for seed in args.seeds:
                out = args.out / f"{task.replace(',', '')}_{seed}"
                cmd = ["selfid-jax", "online", str(ROOT / "configs/robot/online_franka_sim.yaml"), "--out", str(out),
                       "--set", f"selfid.seed={seed}", "--quiet", *extra]
                code = subprocess.run(cmd, cwd=ROOT, check=False).returncode
                s = json.loads((out / "summary.json").read_text())
                if not s["converged"]:
                    print(f"| {task} ({seed}) | not converged: {s['status']}, exit {code} | | | | | |")
                    continue
                error = fr.session_error(out)[0]
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
