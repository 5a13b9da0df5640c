"""Every benchmark at a small size, one table of ratios and goals, written as JSON.

Runs each benchmark script in a fresh Python process (so each import and
compile is cold and none shares memory with another) with ``--json``, then
prints one table: the measured value, the issue-14 goal and whether this run
met it, and writes everything (the table and each script's full record) to
``--out``. Timings are medians of a few repetitions but still move with the
load of the machine; ratios measured in one process (``x RLS``, ``x SLSQP``)
are the robust numbers. About 22 minutes on 2 CPU cores at load 1.5, most of it ``compile_time`` and
``test_suite`` (suite_time.py: the test suite's two tiers, and its fast tier at the shipped LLVM level, as the
README runs them).

    python benchmarks/run_all.py [--out benchmarks/results.json] [--markdown] [--skip ablation ...] [--resume]

The record is rewritten after each benchmark (so a stopped or failed run keeps what finished; a failed script
is a row of its own and the others still run); ``--resume`` runs only those the record lacks.

On a machine with a GPU the same command measures there (the scripts use
JAX's default device, and each row names it); ``--gpu-scale`` raises the sizes
to 1,000,000 estimators (and the step against the device's bandwidth bound),
100,000 rollouts, the paper-protocol UR5e valid-region map and the whole
``_full`` map and ablation as whole processes, the hands' MJX settling at batch
10,000 (with ``impl="warp"`` beside it where ``mujoco-warp`` imports) and 200
articulated objects, and skips the rows that measure the CPU itself (each with
its reason, :data:`CPU_ONLY`). ``--budget S`` starts no script after ``S``
seconds and gives each the time left (``benchmarks/gpu.sh`` runs it with 420).
``--plan`` prints what would run, with which arguments, and exits.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from timing import run_process

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BENCHMARKS = ("estimator", "estimator_2dev", "bandwidth", "rls_floor", "rollouts", "refine", "valid_region",
              "ablation", "articulated", "scaling", "demo_cold", "compile_time", "mjx_profile", "test_suite")

#: The GPU plan's order: the short rows first, the whole ``_full`` sweeps (the longest) last.
GPU_ORDER = ("estimator", "bandwidth", "rollouts", "refine", "articulated", "mjx_profile", "scaling", "valid_region",
             "ablation")

#: Rows ``--gpu-scale`` skips, and why: each measures the CPU itself, not the programs users scale.
CPU_ONLY = {
    "estimator_2dev": "splits the batch over two forced host devices (the CPU's two cores)",
    "rls_floor": "the 2-core CPU's RLS floor and host-dispatch latency (issue 27); the bandwidth row measures the "
                 "step's bound on the device instead",
    "demo_cold": "the demo's 20 s cold start is a goal for a 2-core CPU without a GPU",
    "compile_time": "XLA CPU compile-time goals (the CPU backend's LLVM level)",
    "test_suite": "the test suite runs on the CPU, in CI",
}


def _script(name: str, args: list[str], env: dict | None = None, timeout: int = 900) -> tuple[dict, float]:
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "out.json"
        cmd = [sys.executable, str(HERE / f"{name}.py"), *args, "--json", str(out)]
        proc, wall = run_process(cmd, cwd=ROOT, env={**os.environ, **(env or {})}, capture_output=True, text=True,
                                 timeout=timeout)
        if proc.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed:\n{proc.stderr[-3000:]}")
        print(proc.stdout.rstrip(), flush=True)
        return json.loads(out.read_text()), wall


def plans(gpu_scale: bool = False) -> dict[str, tuple[str, list[str], dict | None]]:
    """``{benchmark: (script, arguments, extra environment)}`` at the small (CPU) or the GPU scale; the GPU plan
    lacks the :data:`CPU_ONLY` rows."""
    batch_est, batch_roll = (1_000_000, 100_000) if gpu_scale else (10_000, 10_000)
    whole = "1000000"  # chunks: more than any _full config has, so the whole config runs
    plans: dict[str, tuple[str, list[str], dict | None]] = {
        "estimator": ("estimator", ["--batch", str(batch_est), "--steps", "50", "--reps", "3", "--rounds", "2"], None),
        "estimator_2dev": ("estimator", ["--batch", str(batch_est), "--steps", "50", "--reps", "3", "--rounds", "2",
                                         "--shard"],
                           {"XLA_FLAGS": (os.environ.get("XLA_FLAGS", "") +
                                          " --xla_force_host_platform_device_count=2").strip()}),
        "rls_floor": ("rls_floor", ["--batch", str(batch_est), "--steps", "50", "--reps", "3", "--rounds", "2",
                                    "--long", "10000", "--long-batch", "20", "--calls", "1000"], None),
        "rollouts": ("rollouts", ["--batches", str(batch_roll), "--loops", "20"], None),
        "scaling": ("scaling", [] if gpu_scale else ["--quick"], None),
        "demo_cold": ("demo_cold", ["--runs", "3"], None),
        "compile_time": ("compile_time", ["--configs", "valid_region_two_link", "valid_region_ur5e",
                                          "tracking_ur5e_cube", "tracking_peg_in_hole", "design_all"], None),
        "refine": ("refine", ["--batch", "2000", "--slsqp", "20"], None),
        "valid_region": ("valid_region", ["--full-chunks", whole, "--no-warm-full"] if gpu_scale
                         else ["--full-chunks", "1"], None),
        "ablation": ("ablation", ["--full-chunks", whole if gpu_scale else "1"], None),
        "articulated": ("articulated", ["--batch", "200" if gpu_scale else "8", "--steps", "100"], None),
        "mjx_profile": ("mjx_profile", ["--scenes", "stewart", "--no-stages", "--native", "16", "--native-steps", "10",
                                        "--batch", "10000" if gpu_scale else "500"] + (["--warp"] if gpu_scale else []),
                        None),
        "test_suite": ("suite_time", ["--tiers", "fast", "whole", "--shipped"], None),
        "bandwidth": ("bandwidth", ["--batch", str(batch_est), "--copy-mib", "2048" if gpu_scale else "256"], None),
    }
    order = GPU_ORDER if gpu_scale else [k for k in BENCHMARKS if k in plans]
    return {k: plans[k] for k in order}


def collect(skip=(), gpu_scale=False, done: dict | None = None, save=None, budget_s: float | None = None) -> dict:
    """Run each benchmark not in ``skip`` nor already in ``done`` (a previous run's records, kept); ``save(res)``
    after each, so an interrupted or failed run keeps what finished. A script that fails is recorded with its
    error and the rest still run. ``budget_s``: start no script after that many seconds and give each at most
    the time left (a script stopped at it is a failed row); those not started are recorded as skipped."""
    t_start = time.perf_counter()
    res = dict(done or {})
    if gpu_scale:
        for key, why in CPU_ONLY.items():
            res.setdefault(key, {"skipped": f"a CPU row: {why}"})
    device = _default_device()
    for key in plans(gpu_scale):
        if key in skip and key not in res:
            res[key] = {"skipped": "--skip", "device": device}
    for key, (script, args, env) in plans(gpu_scale).items():
        if key in skip or key in res:
            continue
        timeout = 3600 if key in ("compile_time", "test_suite") else 900
        if budget_s is not None:
            left = budget_s - (time.perf_counter() - t_start)
            if left < 10:
                res[key] = {"skipped": f"the time budget of {budget_s:.0f} s was spent", "device": device}
                print(f"== {key} skipped: budget spent", flush=True)
                continue
            timeout = int(min(timeout, left))
        print(f"== {key} ({device})", flush=True)
        t0 = time.perf_counter()
        try:
            data, wall = _script(script, args, env, timeout=timeout)
            res[key] = {"result": data, "script_wall_s": wall, "device": device}
        except (RuntimeError, subprocess.TimeoutExpired) as err:
            print(f"== {key} FAILED: {str(err)[-2000:]}", flush=True)
            res[key] = {"error": str(err)[-4000:], "script_wall_s": time.perf_counter() - t0, "device": device}
        if save is not None:
            save(res)
    return res


def _default_device() -> str:
    """JAX's default device here, as ``"platform (kind)"``: what each script's computations run on."""
    import jax

    import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)

    d = jax.devices()[0]
    return f"{d.platform} ({d.device_kind})"


def _row(rows, what, value, unit, goal, met, note=""):
    rows.append({"benchmark": what, "value": value, "unit": unit, "goal": goal, "met": met, "note": note})


def table(res: dict) -> list[dict]:
    """One row per figure, benchmark by benchmark in :data:`BENCHMARKS` order, each with the ``device`` its
    script ran on (a failed or skipped benchmark is one row saying so)."""
    rows: list[dict] = []
    for key in [k for k in BENCHMARKS if k in res] + [k for k in res if k not in BENCHMARKS]:
        r = res[key]
        if "skipped" in r:
            part = [{"benchmark": f"{key}: skipped", "value": None, "unit": "", "goal": "", "met": None,
                     "note": r["skipped"]}]
        elif "error" in r:
            part = [{"benchmark": f"{key}: the script failed", "value": None, "unit": "", "goal": "", "met": False,
                     "note": r["error"].strip().splitlines()[-1][:200]}]
        else:
            part = _rows({key: r})
        rows += [{**row, "device": r.get("device", "")} for row in part]
    return rows


def _rows(res: dict) -> list[dict]:
    rows: list[dict] = []
    for key in ("estimator", "estimator_2dev"):
        if key not in res:
            continue
        r = res[key]["result"]
        ours, rls = r["rows"]["ours"], r["rows"]["rls"]
        where = f"{r['batch']} estimators, n=6, m=3, float32, {r['device']}"
        _row(rows, f"self-ID step ({where})", ours["steps_per_s"], "steps/s", ">= 1000", ours["steps_per_s"] >= 1000)
        _row(rows, "  ... against RLS in the same run", ours["ratio_to_rls"], "x RLS", ">= 0.5",
             ours["ratio_to_rls"] >= 0.5, f"RLS {rls['steps_per_s']:.0f} steps/s")
        _row(rows, "  ... error vs float64 least squares", ours["rel_err_vs_float64_lstsq"], "relative", "<= 1e-4",
             ours["rel_err_vs_float64_lstsq"] <= 1e-4)
        full, full_rls = r["rows"].get("ours, full state out"), r["rows"].get("plain RLS, full state out")
        if full and full_rls:
            goal = 2000 if key == "estimator_2dev" else None
            _row(rows, "  ... full state out", full["steps_per_s"], "steps/s", ">= 2000" if goal else "",
                 full["steps_per_s"] >= goal if goal else None)
            _row(rows, "  ... full state out, against plain RLS's full state", full["ratio_to_rls"], "x plain RLS",
                 ">= 0.5", full["ratio_to_rls"] >= 0.5, f"plain RLS {full_rls['steps_per_s']:.0f} steps/s")
        before = r["rows"].get("ours, 64-sample buffer (before)")
        if before:
            _row(rows, "  ... against the 64-sample buffer (before)", ours["steps_per_s"] / before["steps_per_s"],
                 "x before", "", None,
                 f"before {before['steps_per_s']:.1f} steps/s = {before['ratio_to_rls']:.3f}x RLS")
    if "bandwidth" in res:
        r = res["bandwidth"]["result"]
        t = r["traffic"]
        frac = r["fraction_of_bound"]  # NaN: above 100 % of the bound, a measurement error (bandwidth.py says so)
        flagged = frac != frac
        _row(rows, f"self-ID step against the bandwidth bound ({r['batch']} estimators, {r['device']})",
             frac, "x bound", ">= 0.25", None if flagged else frac >= 0.25,
             ("MEASUREMENT ERROR: above 100 % of the bound, not a figure; " if flagged else "")
             + f"{r['estimator_steps_per_s']:.3g} estimator-steps/s; {t['bytes_per_step']} B per estimator and sample "
             f"({r['xla_bytes_per_step'] or 0:.0f} B as XLA counts); copy {r['copy_bandwidth_gb_s']:.0f} GB/s")
    if "rls_floor" in res:
        r = res["rls_floor"]["result"]
        new, old = r["rows"]["new step, block"], r["rows"]["old full step"]
        plain, brls = r["rows"]["plain RLS"], r["rows"]["baselines.rls"]
        _row(rows, f"self-ID step at the RLS floor ({r['batch']} estimators, blocked)", new["steps_per_s"], "steps/s",
             ">= 2000", new["steps_per_s"] >= 2000, f"old full step {old['steps_per_s']:.0f} steps/s")
        _row(rows, "  ... against a plain five-line RLS in the same run", new["x_plain_rls"], "x plain RLS", ">= 0.5",
             new["x_plain_rls"] >= 0.5, f"plain RLS {plain['steps_per_s']:.0f} steps/s")
        _row(rows, "  ... against baselines.rls in the same run", new["x_baselines_rls"], "x baselines.rls", ">= 1",
             new["x_baselines_rls"] >= 1.0, f"baselines.rls {brls['steps_per_s']:.0f} steps/s")
        steady = r["rows"]["new step, block, steady"]
        _row(rows, "  ... past the start (warm-up done), against plain RLS", steady["x_plain_rls"], "x plain RLS",
             ">= 0.5", steady["x_plain_rls"] >= 0.5,
             f"{steady['steps_per_s']:.0f} steps/s = {steady['x_baselines_rls']:.2f}x baselines.rls")
        full = r["rows"].get("... steady, full state out")
        if full:
            _row(rows, "  ... past the start, whole state returned (a fleet), against plain RLS", full["x_plain_rls"],
                 "x plain RLS", ">= 0.5", full["x_plain_rls"] >= 0.5,
                 f"{full['steps_per_s']:.0f} steps/s = {full['x_baselines_rls']:.2f}x baselines.rls; the rows above "
                 "return only the estimates, so XLA drops the statistics the rank-one loop does not read")
        err = max(r["long"]["rel_err"].values())
        _row(rows, f"  ... float32 over {r['long']['samples']} samples vs float64 least squares", err, "relative",
             "<= 1e-4", err <= 1e-4)
        lat = r["latency"]["n=6,m=3"]
        _row(rows, "  ... batch-1 latency p99 (n=6, m=3, one sample per call)", lat["new step"]["p99_ms"], "ms",
             "<= 0.1", lat["new step"]["p99_ms"] <= 0.1,
             f"p50 {lat['new step']['p50_ms']:.3f} ms; packed state p99 {lat['new step, packed state']['p99_ms']:.3f}"
             f" ms; blocked p99 {[v for k, v in lat.items() if 'per call' in k][0]['p99_ms']:.3f} ms per sample")
        sync = lat.get("new step, packed, donated, sync")
        if sync:
            _row(rows, "  ... the same, packed state, donated, synchronous CPU dispatch", sync["p99_ms"], "ms",
                 "<= 0.1", sync["p99_ms"] <= 0.1, f"p50 {sync['p50_ms']:.3f} ms (jax_cpu_enable_async_dispatch=False)")
    if "scaling" in res:
        r = res["scaling"]["result"]
        est = r["estimator"]
        ratio = max(e["peak_bytes_per_less_data"] / e["state_bytes"] for e in est if e["batch"] >= 100
                    and e["peak_bytes_per_less_data"] is not None)
        rec = r.get("recursive_memory", {}).get("peak_over_state", {})
        _row(rows, "self-ID step peak memory per estimator (batch >= 100, state donated), over the state's size",
             ratio, "x state", "<= 2", ratio <= 2, f"state {est[0]['state_bytes']} B; rank-one forms "
             + ", ".join(f"{k} {v:.2f}x" for k, v in rec.items() if v is not None)
             + "; stops paying after batch " + ", ".join(
                 f"{v:,} ({k})" if v is not None else f"not up to the largest measured ({k})"
                 for k, v in r["stops_paying"].items()))
    if "demo_cold" in res:
        r = res["demo_cold"]["result"]
        _row(rows, f"selfid-jax demo, empty cache, whole process (median of {len(r['runs'])})", r["wall_median_s"],
             "s", "<= 20", r["wall_median_s"] <= 20,
             f"min {r['wall_min_s']:.1f}, max {r['wall_max_s']:.1f} s; CPU {r['cpu_median_s']:.1f} s; peak RSS "
             f"{r['peak_rss_mib']:.0f} MiB; load {r['load_before'][0]:.1f} before")
    if "compile_time" in res:
        for c in res["compile_time"]["result"]["rows"]:
            if "error" in c:
                _row(rows, f"compile: {c['config']}", None, "", "", False, c["error"])
                continue
            _row(rows, f"compile: {c['config']}, longest XLA program", c["xla_max_s"], "s", "<= 30",
                 c["xla_max_s"] <= 30, f"cold {c['cold_wall_s']:.1f} s, warm {c['warm_wall_s']:.1f} s whole process; "
                 f"trace {c['trace_s']:.1f}, lower {c['lower_s']:.1f}, XLA {c['xla_s']:.1f} s; warm compiles "
                 f"{c['warm_programs']}")
            first = c.get("first_result_s", c["cold_wall_s"])
            _row(rows, "  ... first result (first chunk on disk), cold", first, "s", "<= 60", first <= 60,
                 f"whole run {c['cold_wall_s']:.1f} s, of which the sweep (its compile and compute) {c['run_s']:.1f} s")
    if "rollouts" in res:
        r = res["rollouts"]["result"]
        jax_rows = {k: v for k, v in r.items() if k.startswith("JAX")}
        name, best = max(jax_rows.items(), key=lambda kv: int(kv[0].split()[-1]))
        _row(rows, f"UR5e 200-step rollout, {name}", best["ms_per_rollout"], "ms/rollout", "<= 0.1",
             best["ms_per_rollout"] <= 0.1,
             f"{best['vs_numpy']:.0f}x the numpy loop, compile {best['compile_s']:.1f} s")
    if "refine" in res:
        r = res["refine"]["result"]["rows"]
        _row(rows, "closed-form refinement vs SLSQP (analytic grad)", r["closed_form"]["vs_slsqp_analytic"], "x SLSQP",
             ">= 100", r["closed_form"]["vs_slsqp_analytic"] >= 100)
        _row(rows, "optax refinement vs SLSQP (analytic grad)", r["optax"]["vs_slsqp_analytic"], "x SLSQP", ">= 10",
             r["optax"]["vs_slsqp_analytic"] >= 10)
    if "valid_region" in res:
        r = res["valid_region"]["result"]
        paper, full = r.get("valid_region_ur5e.yaml"), r.get("valid_region_ur5e_full.yaml")
        if paper:
            _row(rows, f"UR5e valid-region map, paper protocol ({paper['cold']['rows']} rollouts), cold",
                 paper["cold"]["wall_s"], "s whole process", "<= 8", paper["cold"]["wall_s"] <= 8,
                 f"warm {paper['warm']['wall_s']:.1f} s; import {paper['cold']['import_s']:.1f}, build "
                 f"{paper['cold']['build_s']:.1f}, run {paper['cold']['run_s']:.1f}")
        if full:
            _row(rows, f"UR5e valid-region map, full ({full['rows_full']} rollouts), peak RSS",
                 full["cold"]["peak_rss_mib"], "MiB", "< 4096", full["cold"]["peak_rss_mib"] < 4096,
                 f"measured on {full['cold']['rows']} rows; projected run {full['projected_full_run_s']:.0f} s")
    if "ablation" in res:
        r = res["ablation"]["result"]
        if "cold" in r:
            _row(rows, "ablation, paper protocol (configs/ablation/ablation_ur5e.yaml), cold", r["cold"]["wall_s"],
                 "s whole process", "<= 30", r["cold"]["wall_s"] <= 30,
                 f"warm {r['warm']['wall_s']:.1f} s; peak RSS {r['cold']['peak_rss_mib']:.0f} MiB")
        if "full" in r:
            f = r["full"]
            _row(rows, "ablation, full (configs/ablation/ablation_ur5e_full.yaml), peak RSS", f["peak_rss_mib"], "MiB",
                 "< 4096", f["peak_rss_mib"] < 4096,
                 f"{f['streams']} of {f['streams_full']} streams; projected run {f['projected_full_run_s']:.0f} s")
        if "updates_per_s" in r:
            slow = min(r["updates_per_s"].items(), key=lambda kv: kv[1]["rate"])
            ours = r["updates_per_s"].get("ours", {"rate": float("nan")})
            _row(rows, "ablation estimator updates/s: ours", ours["rate"], "updates/s", "", None,
                 f"slowest: {slow[0]} {slow[1]['rate']:.0f}/s ({slow[1]['vs_ours']:.2f}x ours)")
    if "articulated" in res:
        r = res["articulated"]["result"]
        nat = r["rows"]["native"]
        note = f"{r['batch']} {r['kind']} objects x {r['steps']} steps, compile+first {nat['first_call_s']:.1f} s"
        _row(rows, "articulated rollouts, native MuJoCo", nat["sim_s_per_wall_s"], "sim s / wall s", "", None, note)
        if "mjx" in r["rows"]:
            mjx = r["rows"]["mjx"]
            _row(rows, "  ... MJX against native in the same run", r["mjx_vs_native"], "x native", "", None,
                 f"compile+first {mjx['first_call_s']:.1f} s; handle paths differ by up to "
                 f"{1e3 * r['max_handle_diff_m']:.2g} mm (friction loss {r['frictionloss']} N)")
    if "mjx_profile" in res:
        for s in res["mjx_profile"]["result"]["scenes"]:
            if "settle" in s:
                st = s["settle"]
                _row(rows, f"MJX settling ({s['scene']}, batch {s['batch']}), time against native",
                     st["mjx_time_x_native"], "x native", "<= 3", st["mjx_time_x_native"] <= 3,
                     f"mjx {st['mjx_poses_per_s']:.0f}, native {st['native_poses_per_s']:.0f} poses/s; one step "
                     f"{s['mjx_step_us']:.0f} us/pose, native rollout {s['native_rollout_us']:.0f}")
    if "test_suite" in res:
        r = res["test_suite"]["result"]
        ratio = r.get("fast_vs_shipped_level")
        for t in r["rows"]:
            if t["level"] is not None:
                continue
            note = f"{t['passed']} passed, wall {t['wall_s']:.0f} s, load {t['load_before']:.1f} before"
            if t["tier"] == "fast" and ratio is not None:
                note += f"; {ratio:.2f}x the same tier at LLVM level 3 in this run"
            _row(rows, f"test suite, {t['tier']} tier (pytest -n 2, LLVM level 0)", t["pytest_s"], "s pytest",
                 f"<= {r['goals_s'][t['tier']]:g}", t["pytest_s"] <= r["goals_s"][t["tier"]], note)
    return rows


def _fmt(v):
    if v is None:
        return "-"
    if isinstance(v, float):
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.3e}"
    return str(v)


def render(rows: list[dict], markdown: bool = False) -> str:
    status = {True: "met", False: "NOT met", None: ""}
    if markdown:
        lines = ["| benchmark | device | value | unit | goal | status | note |", "|---|---|---|---|---|---|---|"]
        lines += [f"| {r['benchmark']} | {r.get('device', '')} | {_fmt(r['value'])} | {r['unit']} | {r['goal']} | "
                  f"{status[r['met']]} | {r['note']} |" for r in rows]
        return "\n".join(lines)
    lines = [f"{'benchmark':64s} {'device':14s} {'value':>10s} {'unit':16s} {'goal':9s} {'status':8s} note"]
    lines += [f"{r['benchmark'][:64]:64s} {r.get('device', '')[:14]:14s} {_fmt(r['value']):>10s} {r['unit']:16s} "
              f"{r['goal']:9s} {status[r['met']]:8s} {r['note']}" for r in rows]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(HERE / "results.json"))
    ap.add_argument("--skip", nargs="*", default=[], choices=BENCHMARKS)
    ap.add_argument("--markdown", action="store_true", help="also print the table as Markdown (the README table)")
    ap.add_argument("--gpu-scale", action="store_true",
                    help="the GPU plan: 1,000,000 estimators, 100,000 rollouts, whole _full sweeps; no CPU rows")
    ap.add_argument("--budget", type=float, default=None, help="seconds: start no benchmark after this")
    ap.add_argument("--plan", action="store_true", help="print the benchmarks that would run, and exit")
    ap.add_argument("--resume", action="store_true",
                    help="keep the benchmarks --out already holds (those that did not fail) and run the others")
    args = ap.parse_args()
    if args.plan:
        for key, (script, script_args, env) in plans(args.gpu_scale).items():
            if key not in args.skip:
                extra = " ".join(f"{k}={v!r}" for k, v in (env or {}).items())
                print(f"{key:15s} {extra + ' ' if extra else ''}python benchmarks/{script}.py {' '.join(script_args)}")
        for key, why in (CPU_ONLY.items() if args.gpu_scale else ()):
            print(f"{key:15s} skipped: {why}")
        return
    t0 = time.perf_counter()
    out = Path(args.out)
    done = {}
    if args.resume and out.exists():
        done = {k: r for k, r in json.loads(out.read_text())["benchmarks"].items()
                if "error" not in r and "skipped" not in r}
        print(f"resuming: {', '.join(done) or 'nothing'} kept from {out}", flush=True)
    started = time.strftime("%Y-%m-%d %H:%M:%S")

    def save(res):
        import jax

        record = {
            "machine": {"platform": platform.platform(), "processor": platform.processor(), "cpus": os.cpu_count(),
                        "python": platform.python_version(), "jax": jax.__version__,
                        "device": str(jax.devices()[0]), "load_avg_at_end": os.getloadavg()},
            "started": started, "date": time.strftime("%Y-%m-%d %H:%M:%S"), "total_s": time.perf_counter() - t0,
            "table": table(res), "benchmarks": res,
        }
        tmp = out.with_name(out.name + ".tmp")
        tmp.write_text(json.dumps(record, indent=2, default=str))
        os.replace(tmp, out)  # whole or not at all

    res = collect(set(args.skip), args.gpu_scale, done, save, args.budget)
    save(res)
    rows = table(res)
    print()
    print(render(rows))
    if args.markdown:
        print()
        print(render(rows, markdown=True))
    print(f"\nall benchmarks: {time.perf_counter() - t0:.0f} s")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
