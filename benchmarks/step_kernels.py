"""Where the self-ID step's time goes, kernel by kernel, against the plain RLS of ``rls_floor.py`` (one CPU core).

Both programs are those of ``benchmarks/rls_floor.py``: the steady block step
(:func:`selfid_jax.identify.recursive.run`, ``warmup=0``, one block, the whole
state returned) and the five-line plain RLS, ``--batch`` estimators (n = 6,
m = 3, float32), ``--steps`` samples. Each is compiled once and run
``--reps`` times under ``jax.profiler``; every kernel XLA's CPU runtime
launches (a fusion, a copy, a batched dot) is matched by name to the
compiled program and its time summed, in microseconds per sample. Kernels
are grouped by what they write:

* ``fields``: an ``(n, m)`` or ``(m, m)`` array per estimator (``J``,
  ``sign_net``, ``mag_sum``, ``S_tv``, ``S_vv``, ``P``): the state's matrices;
* ``per-estimator``: anything smaller (the sample's screen, weights and
  reciprocals, the rank-one step's ``P V``, gain and residual, norms, the
  convergence record's scalars and ``mag_count``);
* ``copies``: ``copy`` kernels (the loop carry's buffers).

Then the rate of XLA's CPU code on one elementwise kernel over ``batch x 6``
float32 inside a ``lax.scan``, in nanoseconds per element: a multiply-add, a
multiply-add by a per-estimator value broadcast over the 6 (the form of every
field update under ``vmap``) and a division (``x / (1 + 0 x)``, the form of
:func:`selfid_jax.identify.recursive.once`), each with the batch outermost
(``(batch, 6)``: the layout ``vmap`` gives the step) and innermost
(``(6, batch)``). Which layouts XLA vectorizes depends on its code generator:
run the script under ``XLA_FLAGS=--xla_cpu_use_fusion_emitters=true`` to see
the other one (the flag the user sets wins over selfid_jax's default). The process pins itself to one CPU before JAX
starts (XLA's split of each loop over the cores costs a different amount in
each two-core process; ``rls_floor.py --one-core``).

The last lines: the field kernels alone as a multiple of plain RLS's whole
time, and the per-estimator time that would leave the step at 0.5x plain RLS.

    python benchmarks/step_kernels.py [--batch 10000] [--steps 50] [--reps 5] [--json out.json]
"""

from __future__ import annotations

import argparse
import collections
import glob
import gzip
import json
import os
import re
import tempfile

from timing import pin_one_core, time_call, usable_cpus

FIELD_DIMS = ("6,3", "3,3")


def instructions(hlo: str) -> dict[str, tuple[str, str]]:
    """``name: (opcode, result shape)`` of every instruction of a compiled program's text."""
    out = {}
    for line in hlo.splitlines():
        m = re.match(r"\s*(?:ROOT )?%(\S+) = (\S+?)(?:\{[^}]*\})? (\S+?)\(", line)
        if m:
            out[m.group(1)] = (m.group(3), m.group(2))
    return out


def group_of(opcode: str, shape: str, batch: int) -> str | None:
    """The group a launched kernel is counted in, None for what is not a kernel of its own."""
    if opcode in ("while", "conditional", "call", "tuple", "get-tuple-element", "parameter", "bitcast", "constant"):
        return None
    if opcode == "copy":
        return "copies"
    return "fields" if any(shape.startswith(f"f32[{batch},{d}]") for d in FIELD_DIMS) else "per-estimator"


def kernel_times(compiled, args: tuple, batch: int, steps: int, reps: int) -> dict:
    """Microseconds per sample of each kernel of ``compiled(*args)`` (``reps`` profiled calls), with its group."""
    import jax

    ins = instructions(compiled.as_text())
    for _ in range(2):
        jax.block_until_ready(compiled(*args))
    with tempfile.TemporaryDirectory() as tmp:
        with jax.profiler.trace(tmp):
            for _ in range(reps):
                jax.block_until_ready(compiled(*args))
        (path,) = glob.glob(os.path.join(tmp, "**", "*.trace.json.gz"), recursive=True)
        with gzip.open(path) as f:
            events = json.load(f)["traceEvents"]
    total: collections.Counter = collections.Counter()
    for e in events:
        if e.get("ph") == "X" and e.get("name") in ins:
            total[e["name"]] += e["dur"]
    rows = []
    for name, us in total.most_common():
        opcode, shape = ins[name]
        group = group_of(opcode, shape, batch)
        if group is not None:
            rows.append({"kernel": name, "shape": shape, "group": group, "us_per_sample": us / reps / steps})
    return {"kernels": rows, "groups": {g: sum(r["us_per_sample"] for r in rows if r["group"] == g)
                                        for g in ("fields", "per-estimator", "copies")}}


def element_rates(batch: int, steps: int, reps: int) -> dict:
    """Nanoseconds per element of a multiply-add, a multiply-add by a per-estimator value and a division over
    ``batch x 6`` float32 in a ``lax.scan``, batch-major ``(batch, 6)`` and batch-minor ``(6, batch)``."""
    import jax
    import jax.numpy as jnp

    ops = {"multiply-add": lambda c, y, ax: c * 1.0001 + 1.0,
           "multiply-add by a per-estimator value": lambda c, y, ax: c * jnp.expand_dims(y, ax) + 1.0,
           "division x / (1 + 0 x)": lambda c, y, ax: c / (1.0 + 0.0 * c) + 1.0}
    y = jnp.full((batch,), 0.9999, jnp.float32)
    out = {}
    for layout, shape, ax in (("(batch, 6)", (batch, 6), 1), ("(6, batch)", (6, batch), 0)):
        x = jnp.ones(shape, jnp.float32)
        for name, op in ops.items():
            fn = jax.jit(lambda x, y, op=op, ax=ax: jax.lax.scan(lambda c, _: (op(c, y, ax), None), x, None,
                                                                 length=steps)[0])
            out[f"{name}, {layout}"] = 1e9 * time_call(fn, x, y, reps=reps, per=steps).run_s / x.size
    return out


def run(batch: int = 10_000, steps: int = 50, reps: int = 5) -> dict:
    import jax
    import jax.numpy as jnp
    from rls_floor import F32, make_data, scan_fn, scan_rows, steady_program

    n, m = 6, 3
    d64, V64 = make_data(batch, 2 * steps, n, m)
    d0, V0 = jnp.asarray(d64[:steps], F32), jnp.asarray(V64[:steps], F32)
    d, V = jnp.asarray(d64[steps:], F32), jnp.asarray(V64[steps:], F32)
    fn, s0, r0 = steady_program(n, m, d0, V0, full_state=True)
    step = fn.lower(s0, r0, d, V).compile()
    plain = scan_fn(batch, *scan_rows(n, m)["plain RLS"]).lower(d, V).compile()
    prog = {"self-ID step, steady, full state out": kernel_times(step, (s0, r0, d, V), batch, steps, reps),
            "plain RLS": kernel_times(plain, (d, V), batch, steps, reps)}
    return {"batch": batch, "steps": steps, "reps": reps, "n": n, "m": m, "dtype": "float32",
            "device": f"1 {jax.devices()[0].platform}, {usable_cpus()} CPU core(s) usable",
            "xla_flags": os.environ.get("XLA_FLAGS", ""),
            "programs": prog, "element_ns": element_rates(batch, steps, reps)}


def report(res: dict, top: int = 12) -> str:
    lines = [f"kernels of the self-ID step and of plain RLS: {res['batch']} estimators (n=6, m=3, float32), "
             f"{res['steps']} samples, {res['reps']} profiled calls, {res['device']}; XLA_FLAGS {res['xla_flags']}"]
    for name, p in res["programs"].items():
        g = p["groups"]
        lines.append(f"{name}: {len(p['kernels'])} kernels, {sum(g.values()):.0f} us per sample: "
                     + ", ".join(f"{k} {v:.0f} us" for k, v in g.items()))
        for r in p["kernels"][:top]:
            lines.append(f"  {r['us_per_sample']:7.1f} us  {r['group']:13s} {r['shape']:24s} {r['kernel']}")
    lines.append("elementwise over batch x 6 in a scan, ns per element: " + "; ".join(
        f"{k} {v:.2f}" for k, v in res["element_ns"].items()))
    step, plain = res["programs"].values()
    whole = sum(plain["groups"].values())
    fields = step["groups"]["fields"]
    budget = 2 * whole - fields - step["groups"]["copies"]
    left = (f"would have {budget:.0f} us" if budget > 0 else
            "would have no time left (the field kernels and copies alone take twice plain RLS's time)")
    lines.append(f"the step's field kernels alone: {fields:.0f} us = {fields / whole:.2f}x plain RLS's whole "
                 f"{whole:.0f} us; at 0.5x plain RLS the rest of the step (per-estimator kernels) {left}, "
                 f"against {step['groups']['per-estimator']:.0f} us now")
    return "\n".join(lines)


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=10_000)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--json", default=None, help="write the results here")
    a = ap.parse_args()
    if a.batch < 1 or a.steps < 1 or a.reps < 1:
        ap.error("--batch, --steps and --reps must be >= 1")
    pin_one_core(ap)
    from emit import emit

    res = run(a.batch, a.steps, a.reps)
    emit(res, report(res), a.json)


if __name__ == "__main__":
    main()
