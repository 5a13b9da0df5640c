"""The self-ID step against the bandwidth bound of the memory level its state lives in.

Two steps, n = 6, m = 3, float32, no sample buffer, ``--batch`` vmapped
estimators, ``--steps`` samples in one ``lax.scan``, the whole state returned:

* ``closed form``: ``benchmarks/estimator.py``'s ``ours``, the per-sample
  step :func:`selfid_jax.identify.step.sample_step` (``update``,
  ``initial_guess``, the closed form of Eq. 14, ``record``; one native kernel
  on CPU where the kernels are built);
* ``rank-one block``: :func:`selfid_jax.identify.recursive.run` past the start
  (``warmup=0``, ``history=False``), the state and its ``Recursion`` returned
  (the fleet form, ``benchmarks/rls_floor.py``'s ``... steady, full state out``).

For each it states the traffic per estimator and sample two ways:

* **the state's minimum**: ``2 x`` the bytes of the leaves a step changes
  (read and written), plus the leaves it only reads and the sample
  ``(dtheta, V)``: what a step must move at least;
* **as XLA counts it**: ``cost_analysis()["bytes accessed"]`` of the compiled
  scan, divided by the batch (XLA counts a loop body once, whatever its trip
  count: every fusion's operands and outputs, and the copies of the carry),
  plus the arguments and results of its custom calls (the native kernels of
  :mod:`selfid_jax.math.native`), which XLA's cost analysis leaves out: read
  off the compiled HLO, each counted once as read and once as written.

**The bound** is a copy at the memory level the state lives in: a ``lax.scan``
of ``--steps`` jitted ``x * a + b`` over an array of the state's own size
(bytes read plus written), timed interleaved with the step. A batch whose
state fits the last-level cache (``--cache-mib``, default the largest CPU
cache in ``/sys``; 0 on another device) is copied at that size, in cache; a
batch that cannot fit is copied at ``max(state, --copy-mib)``, streaming
through main memory. The fraction of the bound is
``rate x bytes per step / copy bandwidth``, for each traffic count; a copy
that moves its bytes is the fastest a step can move them, so a figure above
100 % is a measurement error (load that hit the copy and not the step, a
copy at another memory level), flagged and not printed.

    python benchmarks/bandwidth.py [--batch 10000] [--steps 50] [--reps 5] [--rounds 3] [--json out.json]
    JAX_PLATFORMS=cpu taskset -c 0,1 python benchmarks/bandwidth.py   # the 2-core CPU row on a bigger machine

The step's native CPU kernels run on one thread here (``SELFID_JAX_NATIVE_THREADS=1``
unless the environment sets it), as the copy that sets the bound does.

On a GPU run it with ``--batch 1000000 --copy-mib 2048`` (``benchmarks/gpu.sh`` does).
"""

from __future__ import annotations

import argparse
import datetime
import functools
import glob
import math
import os
import re
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))
# the bound is one thread's copy: the step's native kernels (selfid_jax.math.native) run on one thread too
os.environ.setdefault("SELFID_JAX_NATIVE_THREADS", "1")
import jax
import jax.numpy as jnp
import numpy as np
from emit import emit
from estimator import F32, E, M, N, make_data, ours_step, scan_fn
from timing import first_call, interleaved, usable_cpus

from selfid_jax.identify import recursive as R
from selfid_jax.math import native

EPS = 1e-3


def last_level_cache_mib() -> float:
    """The largest CPU cache in ``/sys`` (MiB; 0 where none is listed)."""
    sizes = []
    for path in glob.glob("/sys/devices/system/cpu/cpu0/cache/index*/size"):
        text = Path(path).read_text().strip()
        scale = {"K": 1 / 1024, "M": 1.0, "G": 1024.0}.get(text[-1:], 1 / (1 << 20))
        sizes.append(float(text.rstrip("KMG")) * scale)
    return max(sizes, default=0.0)


def closed_form_program(batch: int):
    """``(fn, carry0)``: ``fn(d, V)`` scans the closed-form step from empty estimators, the whole state returned."""
    init = lambda: E.init(N, M, capacity=0, dtype=F32)
    fn = scan_fn(batch, init, ours_step, lambda s: s)
    carry0 = jax.vmap(lambda _: init())(jnp.arange(batch))
    return fn, carry0


def rank_one_program(batch: int, d0, V0):
    """``(jitted, carry0)``: ``jitted(*carry0, d, V)`` runs :func:`recursive.run` past the start, from the state after
    ``d0, V0``; the whole ``(state, rec)`` is returned."""
    def first(d, V):
        return R.run(E.init(N, M, capacity=0, dtype=F32), R.init(M, F32), d, V, EPS, warmup=M + 5, history=False)[:2]

    s0, r0 = jax.block_until_ready(jax.jit(jax.vmap(first, in_axes=(1, 1)))(d0, V0))
    more = jax.jit(jax.vmap(lambda s, r, d, V: R.run(s, r, d, V, EPS, warmup=0, history=False)[:2],
                            in_axes=(0, 0, 1, 1)))
    return more, (s0, r0)


def fast_scan():
    """``jit(fn)``: ``fn(state, rec, d, V)`` scans :func:`recursive.fast_step` (the rank-one step that
    :func:`recursive.run` takes after its warm-up) under ``vmap``: the loop whose body XLA's count is of (``run`` also
    compiles the batch form's loop, for a block that needs it, which XLA counts too)."""
    def fn(s, r, d, V):
        step = jax.vmap(lambda s, r, d, V: R.fast_step(s, r, d, V, EPS))
        return jax.lax.scan(lambda c, x: (step(*c, *x), None), (s, r), (d, V))[0]

    return jax.jit(fn)


def state_traffic(before, after, batch: int) -> dict:
    """Bytes per estimator and sample a step must move, from which leaves of the carry ``before -> after`` changed."""
    names = [jax.tree_util.keystr(p) for p, _ in jax.tree_util.tree_flatten_with_path(before)[0]]
    changed, size = {}, {}
    for name, a, b in zip(names, jax.tree.leaves(before), jax.tree.leaves(after)):
        a, b = np.asarray(a), np.asarray(b)
        size[name] = int(a.nbytes // batch)
        changed[name] = bool(a.size) and not np.array_equal(a, b, equal_nan=True)
    written = sum(size[k] for k, c in changed.items() if c)
    read_only = sum(size[k] for k, c in changed.items() if not c)
    sample = (N + M) * np.dtype(np.float32).itemsize
    return {"state_bytes": sum(size.values()), "written_bytes": written, "read_only_bytes": read_only,
            "sample_bytes": sample, "bytes_per_step": 2 * written + read_only + sample,
            "written_leaves": [k for k, c in changed.items() if c],
            "read_only_leaves": [k for k, c in changed.items() if not c and size[k]]}


def xla_bytes(compiled) -> float | None:
    """XLA's ``bytes accessed`` of a compiled program (None if the backend does not say)."""
    cost = compiled.cost_analysis()
    if isinstance(cost, list):  # older jax: one dict per program
        cost = cost[0] if cost else None
    if not cost or "bytes accessed" not in cost:
        return None
    return float(cost["bytes accessed"])


def xla_body_bytes(jitted, lead, d, V, batch: int, compiled=None) -> float | None:
    """XLA's count for one pass of the scan's body, per estimator: the program's ``bytes accessed`` over ``d, V``
    (``compiled``, if given, is it) less that of the same program over no samples (XLA counts a loop body once,
    whatever its trip count), plus its custom calls' arguments and results (:func:`custom_call_bytes`)."""
    compiled = jitted.lower(*lead, d, V).compile() if compiled is None else compiled
    full, empty = xla_bytes(compiled), xla_bytes(jitted.lower(*lead, d[:0], V[:0]).compile())
    return None if full is None or empty is None else (full - empty + custom_call_bytes(compiled)) / batch


_SHAPE = re.compile(r"\b(pred|[suf](?:8|16|32|64)|bf16)\[([\d,]*)\]")
_DEF = re.compile(r"^\s*(?:ROOT\s+)?(%[\w.-]+)\s*=\s*(.*?)\s+([\w-]+)\((.*)$")


def shape_bytes(text: str) -> int:
    """Bytes of every array shape written in ``text`` (an HLO shape or tuple of shapes, ``f32[10000,6,3]{2,1,0}``)."""
    total = 0
    for dtype, dims in _SHAPE.findall(text):
        width = 1 if dtype in ("pred", "s8", "u8") else (2 if dtype == "bf16" else int(dtype[1:]) // 8)
        total += width * math.prod(int(x) for x in dims.split(",") if x)
    return total


def custom_call_bytes(compiled) -> int:
    """Bytes of the arguments and results of every custom call in ``compiled``'s HLO (each call once)."""
    shapes: dict[str, str] = {}
    calls: list[tuple[str, str]] = []
    for line in compiled.as_text().splitlines():
        m = _DEF.match(line)
        if m is None:
            continue
        name, shape, op, rest = m.groups()
        shapes[name] = shape
        if op == "custom-call":
            calls.append((shape, rest[: rest.find(")")]))
    return sum(shape_bytes(shape) + sum(shape_bytes(shapes.get(a, "")) for a in re.findall(r"%[\w.-]+", args))
               for shape, args in calls)


def copy_program(nbytes: int, steps: int):
    """``(fn, x)``: ``fn(x)`` runs ``steps`` iterations of ``x * a + b`` over ``x`` (float32, ``nbytes`` bytes) in one
    ``lax.scan`` (the step's harness, a copy per iteration)."""
    x = jnp.ones((max(nbytes // 4, 1),), F32)

    def run(x):
        return jax.lax.scan(lambda x, _: (x * jnp.float32(1.0001) + jnp.float32(1e-7), None), x, None,
                            length=steps)[0]

    return jax.jit(run), x


def run(batch: int = 10_000, steps: int = 50, reps: int = 5, rounds: int = 3, copy_mib: int = 256,
        cache_mib: float | None = None) -> dict:
    cpu = jax.devices()[0].platform == "cpu"
    cache_mib = (last_level_cache_mib() if cpu else 0.0) if cache_mib is None else cache_mib
    start = max(steps, 4 * (M + 5))  # samples that take the rank-one block past its start
    d, V, _ = make_data(batch, start + steps)
    d0, V0, d1, V1 = d[:start], V[:start], d[start:], V[start:]
    cf, cf_carry0 = closed_form_program(batch)
    ro, ro_carry0 = rank_one_program(batch, d0, V0)
    # name: (fn, leading arguments, the carry the scan starts from, the program whose loop body XLA counts)
    programs = {"closed form": (cf, (), cf_carry0, cf), "rank-one block": (ro, ro_carry0, ro_carry0, fast_scan())}
    out: dict[str, dict[str, Any]] = {}
    calls: dict[str, tuple[Callable[[], Any], int]] = {}
    for name, (fn, lead, before, counted) in programs.items():
        t0 = time.perf_counter()
        compiled = fn.lower(*lead, d1, V1).compile()
        compile_s = time.perf_counter() - t0
        first_call(compiled, *lead, d1, V1)
        # the leaves one sample changes: the carry before and after a one-sample scan
        traffic = state_traffic(before, fn(*lead, d1[:1], V1[:1]), batch)
        xla = xla_body_bytes(counted, lead, d1, V1, batch, compiled if counted is fn else None)
        out[name] = {"traffic": traffic, "xla_bytes_per_step": xla, "compile_s": compile_s}
        calls[name] = (functools.partial(compiled, *lead, d1, V1), 1)
    state_bytes = max(r["traffic"]["state_bytes"] for r in out.values()) * batch
    resident = state_bytes <= cache_mib * (1 << 20)
    copy_bytes = state_bytes if resident else max(state_bytes, copy_mib << 20)
    copy_fn, x = copy_program(copy_bytes, steps)
    first_call(copy_fn, x)
    calls["copy"] = (lambda: copy_fn(x), 1)
    times = interleaved(calls, reps, rounds)
    bw = 2 * x.nbytes * steps / statistics.median(times["copy"])
    for name, r in out.items():
        rate = batch * steps / statistics.median(times[name])
        r.update({"estimator_steps_per_s": rate, "steps_per_s": rate / batch})
        for key, per in (("state", r["traffic"]["bytes_per_step"]), ("xla", r["xla_bytes_per_step"])):
            frac = None if per is None else rate * per / bw
            r[f"fraction_of_bound_{key}"] = frac
            r[f"measurement_error_{key}"] = frac is not None and frac > 1.0
    main = out["closed form"]
    return {"batch": batch, "steps": steps, "n": N, "m": M, "dtype": "float32",
            "device": f"1 {jax.devices()[0].platform} ({jax.devices()[0].device_kind})",
            "cpus_visible": usable_cpus(),
            "date": datetime.datetime.now(datetime.UTC).strftime("%Y-%m-%d %H:%M UTC"),
            "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
            "memory_level": "cache" if resident else "main memory", "cache_mib": cache_mib,
            "state_mib": state_bytes / (1 << 20), "copy_mib": copy_bytes / (1 << 20),
            "copy_bandwidth_gb_s": bw / 1e9, "reps": reps * rounds, "steps_rows": out,
            "native": f"{native.status()}, SELFID_JAX_NATIVE_THREADS={os.environ.get('SELFID_JAX_NATIVE_THREADS', '')}",
            # the closed-form row under the names benchmarks/run_all.py reads (NaN where it is a measurement error)
            "traffic": main["traffic"], "xla_bytes_per_step": main["xla_bytes_per_step"],
            "estimator_steps_per_s": main["estimator_steps_per_s"], "steps_per_s": main["steps_per_s"],
            "fraction_of_bound": (float("nan") if main["measurement_error_state"]
                                  else main["fraction_of_bound_state"]),
            "bound_estimator_steps_per_s": bw / main["traffic"]["bytes_per_step"]}


def percent(frac: float | None, error: bool) -> str:
    """A fraction of the bound as a percentage; above 100 % it is a measurement error, not a figure."""
    if frac is None:
        return "- (backend gives no count)"
    return "MEASUREMENT ERROR (above 100 %: not a figure)" if error else f"{100 * frac:.0f} %"


def report(r: dict) -> str:
    load = "-" if r["load_average"] is None else ", ".join(f"{x:.1f}" for x in r["load_average"])
    lines = [f"self-ID step against the bandwidth bound, {r['device']}, {r['cpus_visible']} CPUs visible, "
             f"{r['date']}, load average {load}",
             f"state {r['state_mib']:.1f} MiB at batch {r['batch']:,} ({r['memory_level']}; last-level cache "
             f"{r['cache_mib']:.0f} MiB): bound = a copy of {r['copy_mib']:.1f} MiB, {r['steps']} iterations in one "
             f"scan, {r['copy_bandwidth_gb_s']:.1f} GB/s (read + written), medians of {r['reps']} interleaved calls",
             f"native kernels {r['native']}"]
    for name, s in r["steps_rows"].items():
        t = s["traffic"]
        xla = "-" if s["xla_bytes_per_step"] is None else f"{s['xla_bytes_per_step']:.0f} B"
        ratio = "" if s["xla_bytes_per_step"] is None else f" ({s['xla_bytes_per_step'] / t['bytes_per_step']:.1f}x)"
        lines += [
            f"{name}: {s['steps_per_s']:.0f} steps/s = {s['estimator_steps_per_s']:.3g} estimator-steps/s "
            f"(compiled in {s['compile_s']:.1f} s)",
            f"  traffic per estimator and sample: state minimum {t['bytes_per_step']} B = 2 x {t['written_bytes']} B "
            f"written + {t['read_only_bytes']} B read only + {t['sample_bytes']} B sample; as XLA counts it {xla}"
            f"{ratio}",
            f"  of the bound: state minimum {percent(s['fraction_of_bound_state'], s['measurement_error_state'])}; "
            f"XLA's count {percent(s['fraction_of_bound_xla'], s['measurement_error_xla'])}",
        ]
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--copy-mib", type=int, default=256,
                    help="MiB of the streaming copy, for a state that does not fit the cache (at least the state's)")
    ap.add_argument("--cache-mib", type=float, default=None,
                    help="last-level cache, MiB (default: the largest CPU cache in /sys; 0 on another device)")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res = run(args.batch, args.steps, args.reps, args.rounds, args.copy_mib, args.cache_mib)
    emit(res, report(res), args.json)


if __name__ == "__main__":
    main()
