"""Where one MJX physics step spends its time, stage by stage, against native MuJoCo's own stage timers (float64, CPU).

For each scene (``stewart``: the Stewart Hand; ``model_o``: the Model O;
``articulated``: one prismatic drawer of ``benchmarks/articulated.py``, weld
grasp, its per-object model fields vmapped) a batch of ``--batch`` states is
prepared by stepping MJX ``--warm`` steps from the scene's start under random
commands (the hands: commands from the sampling box; the drawer: the mocap
target pulled 5 mm along x), so the states are mid-motion. Then:

* MJX: the stages of ``mjx.step`` (``fwd_position`` = kinematics + com_pos,
  crb + factor_m, collision, make_constraint, transmission; ``fwd_velocity``;
  ``fwd_actuation``; ``fwd_acceleration``; ``solve``; the integrator) are
  chained in jitted, vmapped prefixes (stages 1..k, the whole ``mjx.Data`` out)
  timed in interleaved rounds (fastest of each); a stage's row is what it adds to the
  prefix before it (so XLA fuses across stages as in ``mjx.step``, and the
  dispatch of a call, the identity row, is in no stage). The solver is split
  the same way: warm start (two cost evaluations), the initial context (cost,
  gradient, Newton Hessian and its factor), one line search, one constraint
  update and gradient; the rest of ``solve`` is its ``while_loop``. Times are
  wall microseconds per pose (call time / batch) on all cores XLA uses.
* native: ``mj_step`` on ``--native`` of the same states (their state fields copied),
  ``--native-steps`` steps each, one thread; per-stage microseconds (median over steps) from
  ``mjData.timer`` (``mjTIMER_POS_KINEMATICS``, ``_POS_INERTIA``,
  ``_POS_COLLISION``, ``_POS_MAKE``, ``_POS_PROJECT``, ``_VELOCITY``,
  ``_ACTUATION``, ``_CONSTRAINT`` = the solver, ``_ADVANCE``, ``_STEP``), and the
  whole machine's rate: ``mujoco.rollout`` over the batch on every core
  (what ``benchmarks/hands.py``'s native backend uses), in us per pose-step.
* solver iterations per step: MJX's Newton ``while_loop`` under vmap runs until
  its slowest batch element stops, so the table gives the trips of the loop
  (the batch maximum) and the mean per element (a copy of ``mjx.solve``'s loop
  that counts), and the line-search evaluations: under vmap the batched
  ``lax.cond`` in MJX's line search becomes a select, so every solver
  iteration pays ``opt.ls_iterations`` line-search steps; natively
  ``mjData.solver_niter`` and the summed ``mjSolverStat.neval``.

The hands' MJX model is the one the library settles with
(:func:`selfid_jax.systems.hands.settle.mjx_model`: one Newton iteration, 4
line-search steps, a sparse mass matrix on CPU); ``--mjcf-options`` profiles
the MJCF's own options (Newton up to 100 iterations, 50 line-search steps,
dense), the options the library settled with before (with today's loop). ``--iterations`` / ``--ls-iterations``
override any scene's MJX solver options (the drawer's MJX model runs 4
line-search steps, as ``selfid_jax.articulated.sim`` sets; ``--ls-iterations
50`` is the MJCF's), ``--jacobian`` the hands' mass matrix layout (never the
native model's).

    python benchmarks/mjx_profile.py                      # batch 1,000, all three scenes (~3 minutes on 2 cores)
    python benchmarks/mjx_profile.py --batch 100 --scenes stewart
    python benchmarks/mjx_profile.py --batch 10000        # on a CUDA jax install: the GPU side
"""

from __future__ import annotations

import argparse
import copy
import os
import time

import jax
import jax.numpy as jnp
import mujoco
import numpy as np
from emit import emit
from mujoco import mjx
from timing import time_call

import selfid_jax  # noqa: F401  (XLA flags before JAX initialises)
from selfid_jax.systems.hands.settle import cast_like

#: native mjData timers, in the order of the MJX stages they match (None: no native timer of its own).
NATIVE_TIMERS = {
    "kinematics+com_pos": "mjTIMER_POS_KINEMATICS",
    "crb+factor_m": "mjTIMER_POS_INERTIA",
    "collision": "mjTIMER_POS_COLLISION",
    "make_constraint": "mjTIMER_POS_MAKE",
    "project (native only)": "mjTIMER_POS_PROJECT",
    "transmission": None,
    "fwd_velocity": "mjTIMER_VELOCITY",
    "fwd_actuation": "mjTIMER_ACTUATION",
    "fwd_acceleration": None,
    "solve": "mjTIMER_CONSTRAINT",
    "integrator": "mjTIMER_ADVANCE",
}


def _stages(m):
    """``[(name, fn(model, data) -> data)]``: the stages of ``mjx.step`` in order (MJX 3.x, impl "jax")."""
    integ = {mujoco.mjtIntegrator.mjINT_EULER: mjx.euler, mujoco.mjtIntegrator.mjINT_IMPLICITFAST: mjx.implicit,
             mujoco.mjtIntegrator.mjINT_RK4: mjx.rungekutta4}[int(m.opt.integrator)]
    return [
        ("kinematics+com_pos", lambda m, d: mjx.com_pos(m, mjx.kinematics(m, d))),
        ("crb+factor_m", lambda m, d: mjx.factor_m(m, mjx.crb(m, d))),
        ("collision", mjx.collision),
        ("make_constraint", mjx.make_constraint),
        ("transmission", mjx.transmission),
        ("fwd_velocity", mjx.fwd_velocity),
        ("fwd_actuation", mjx.fwd_actuation),
        ("fwd_acceleration", mjx.fwd_acceleration),
        ("solve", mjx.solve),
        ("integrator", integ),
    ]


def _counting_solve(m, d):
    """``mjx.solve``'s loop (warm start, Newton/CG while_loop) returning ``solver_niter`` (int scalar) too."""
    from mujoco.mjx._src import math as mmath
    from mujoco.mjx._src import solver as S

    def cond(ctx):
        improvement = S._rescale(m, d, ctx.prev_cost - ctx.cost)
        gradient = S._rescale(m, d, mmath.norm(ctx.grad))
        return ~((ctx.solver_niter >= m.opt.iterations) | (improvement < m.opt.tolerance)
                 | (gradient < m.opt.tolerance))

    def body(ctx):
        ctx = S._linesearch(m, d, ctx)
        pg, pmg = ctx.grad, ctx.Mgrad
        ctx = S._update_constraint(m, d, ctx)
        ctx = S._update_gradient(m, d, ctx)
        if m.opt.solver == mujoco.mjtSolver.mjSOL_NEWTON:
            search = -ctx.Mgrad
        else:
            beta = jnp.maximum(0, jnp.dot(ctx.grad, ctx.Mgrad - pmg) / jnp.maximum(mujoco.mjMINVAL, jnp.dot(pg, pmg)))
            search = -ctx.Mgrad + beta * ctx.search
        return ctx.replace(search=search, solver_niter=ctx.solver_niter + 1)

    warm = S.Context.create(m, d.replace(qacc=d.qacc_warmstart), grad=False)
    smth = S.Context.create(m, d.replace(qacc=d.qacc_smooth), grad=False)
    d = d.replace(qacc=jnp.where(warm.cost < smth.cost, d.qacc_warmstart, d.qacc_smooth))
    ctx = S.Context.create(m, d)
    ctx = body(ctx) if m.opt.iterations == 1 else jax.lax.while_loop(cond, body, ctx)
    return ctx.solver_niter


# ------------------------------------------------------------------ scenes
class Scene:
    """A batch of MJX states of one model: ``mj`` (``MjModel``), ``model_of(obj) -> mjx.Model``, ``obj`` (batched
    pytree or a dummy ``(B,)``), ``d0`` (batched ``mjx.Data``), ``mj_of(i) -> MjModel`` of element i (native)."""

    def __init__(self, name, mj, model_of, obj, d0, mj_of=None, systems=None, q=None):
        self.name, self.mj, self.model_of, self.obj, self.d0 = name, mj, model_of, obj, d0
        self.mj_of = mj_of or (lambda i: mj)
        self.systems, self.q = systems, q  # hands: {"mjx": System, "native": System}, commands (B, nu)


def _opts(model, iterations, ls_iterations):
    o = {}
    if iterations:
        o["iterations"] = int(iterations)
    if ls_iterations:
        o["ls_iterations"] = int(ls_iterations)
    return model.replace(opt=model.opt.replace(**o)) if o else model


def _hand_scene(name, B, seed, it, ls, jacobian=None, mjcf_options=False, warp=False):
    from selfid_jax.systems.hands import settle

    if name == "stewart":
        from selfid_jax.systems.hands.stewart import STEWART_HALF_WIDTH, _mjmodel, stewart_home

        mj = _mjmodel()
        home = stewart_home()
        lo, hi = home - STEWART_HALF_WIDTH, home + STEWART_HALF_WIDTH
        qpos0 = mj.qpos0
    else:
        from selfid_jax.systems.hands.model_o_hand import model_o_keyframe, model_o_mjmodel

        mj = model_o_mjmodel()
        qpos0, home = model_o_keyframe()
        lo, hi = home - 0.001, home + 0.001
    kw = {"iterations": None, "ls_iterations": None, "sparse": False} if mjcf_options else {}
    if jacobian:
        kw["sparse"] = jacobian == "sparse"
    model = _opts(settle.mjx_model(mj, **kw), it, ls)
    ctrl = np.random.default_rng(seed).uniform(lo, hi, (B, mj.nu))

    def make(c):
        with jax.numpy_rank_promotion("allow"):
            d = mjx.make_data(model)
        return d.replace(qpos=jnp.asarray(qpos0, d.qpos.dtype), ctrl=c.astype(d.ctrl.dtype))

    d0 = jax.jit(jax.vmap(make))(jnp.asarray(ctrl))
    return Scene(name, mj, lambda _: model, jnp.zeros(B), d0, systems=_hand_systems(name, model, mj if warp else None),
                 q=ctrl)


def _hand_systems(name, model, warp_mj=None):
    """``{"mjx": System, "native": System}`` of the hand, the mjx one settling with ``model`` (``mjx.Model``);
    with ``warp_mj`` (the ``MjModel``) also ``"mjx_warp"``, MJX's ``impl="warp"`` (or why it cannot run here)."""
    import dataclasses

    from selfid_jax.systems.hands import settle

    if name == "stewart":
        from selfid_jax.systems.hands.stewart import stewart_hand as factory
    else:
        from selfid_jax.systems.hands.model_o_hand import model_o as factory
    mjx_sys, native = factory(backend="mjx"), factory(backend="native")

    def with_model(model):
        prm = mjx_sys.params
        if isinstance(prm, settle.SettleParams):
            prm = dataclasses.replace(prm, model=model)
        else:  # Model O: (SettleParams, max_tilt)
            prm = (dataclasses.replace(prm[0], model=model), prm[1])
        return dataclasses.replace(mjx_sys, params=prm)

    systems = {"mjx": with_model(model), "native": native}
    if warp_mj is not None:
        try:
            import mujoco_warp  # noqa: F401

            systems["mjx_warp"] = with_model(settle.mjx_model(warp_mj, sparse=False, impl="warp"))
        except Exception as err:  # noqa: BLE001  (not installed, no CUDA device...: the row says why)
            systems["mjx_warp"] = f"{type(err).__name__}: {err}"[:300]
    return systems


def settle_rates(scene: Scene, reps: int = 2) -> dict:
    """Settled poses/s of ``jit(vmap(system.pose))`` per backend on ``scene.q`` (best of ``reps`` calls after the
    compiling one), the MJX / native time ratio and the largest position difference between them (m)."""
    out, poses = {}, {}
    q = jnp.asarray(scene.q)
    for backend, system in scene.systems.items():
        if isinstance(system, str):
            out[f"{backend}_error"] = system
            continue
        fn = jax.jit(jax.vmap(system.pose))
        try:
            t = time_call(fn, q, reps=reps, stat=min)
        except Exception as err:
            if backend != "mjx_warp":
                raise
            out[f"{backend}_error"] = f"{type(err).__name__}: {err}"[:300]
            continue
        poses[backend] = np.asarray(t.out[0])
        out[f"{backend}_poses_per_s"] = q.shape[0] / t.run_s
    out["mjx_time_x_native"] = out["native_poses_per_s"] / out["mjx_poses_per_s"]
    if "mjx_warp_poses_per_s" in out:
        out["mjx_warp_time_x_native"] = out["native_poses_per_s"] / out["mjx_warp_poses_per_s"]
    out["max_pose_diff_m"] = float(np.nanmax(np.abs(poses["mjx"] - poses["native"])))
    if "mjx_warp" in poses:
        out["warp_max_pose_diff_m"] = float(np.nanmax(np.abs(poses["mjx_warp"] - poses["native"])))
    out["nan_fraction"] = {k: float(np.mean(np.isnan(v[:, 0]))) for k, v in poses.items()}
    return out


def _articulated_scene(B, seed, it, ls):
    import sys

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from articulated import _part

    from selfid_jax.articulated import scenes

    part, _ = _part("mjx", "prismatic", B, 10, "turbo_u0", (0.5, 3.0), seed)
    st = part.static.sim
    lay, mj = st.layout, st.mj_model
    obj = jax.tree.map(jnp.asarray, part.params.rollout.obj)

    def model_of(o):
        return _opts(scenes.apply_mjx(st.mjx_model, lay, o), it, ls)

    def make(o):
        m = model_of(o)
        with jax.numpy_rank_promotion("allow"):
            d = mjx.kinematics(m, mjx.make_data(m))
        return d.replace(mocap_pos=d.mocap_pos + jnp.asarray([0.005, 0.0, 0.0], d.mocap_pos.dtype))

    d0 = jax.jit(jax.vmap(make))(obj)
    objn = jax.tree.map(np.asarray, part.params.rollout.obj)

    def mj_of(i):
        mi = copy.copy(mj)
        scenes.apply_native(mi, lay, jax.tree.map(lambda a: a[i], objn))
        return mi

    return Scene("articulated", mj, model_of, obj, d0, mj_of)


# ------------------------------------------------------------------ measurement
def profile(scene: Scene, warm: int, n_native: int, native_steps: int, min_time: float, rounds: int = 20,
            stages_table: bool = True) -> dict:
    """Per-stage MJX and native microseconds per pose-step, solver iterations and rates for one scene
    (``stages_table`` False: the whole step only, no MJX stage rows)."""
    B = scene.d0.qpos.shape[0]
    model_of = scene.model_of

    def advance(obj, d):
        m = model_of(obj)
        with jax.numpy_rank_promotion("allow"):
            return jax.lax.fori_loop(0, warm, lambda _, x: cast_like(mjx.step(m, x), x), d)

    with jax.numpy_rank_promotion("allow"):
        d = jax.jit(jax.vmap(advance))(scene.obj, scene.d0)
    d = jax.block_until_ready(d)
    m_host = model_of(jax.tree.map(lambda a: a[0], scene.obj))
    stages = _stages(m_host)

    def prefix(k):
        def f(o, x):
            m = model_of(o)
            for _, fn in stages[:k]:
                x = fn(m, x)
            return x
        return jax.jit(jax.vmap(f))

    # the solver's parts, on the solver's input state (the output of fwd_acceleration)
    def solver_part(k):
        from mujoco.mjx._src import solver as S

        def f(o, x):
            m = model_of(o)
            for _, fn in stages[:8]:
                x = fn(m, x)
            if k == 0:
                return x
            warm = S.Context.create(m, x.replace(qacc=x.qacc_warmstart), grad=False)
            smth = S.Context.create(m, x.replace(qacc=x.qacc_smooth), grad=False)
            x = x.replace(qacc=jnp.where(warm.cost < smth.cost, x.qacc_warmstart, x.qacc_smooth))
            if k == 1:
                return x
            ctx = S.Context.create(m, x)
            if k == 2:
                return ctx
            ctx = S._linesearch(m, x, ctx)
            if k == 3:
                return ctx
            ctx = S._update_constraint(m, x, ctx)
            return S._update_gradient(m, x, ctx)
        return jax.jit(jax.vmap(f))

    nst = len(stages) if stages_table else 0
    fns = [jax.jit(jax.vmap(lambda o, x: x))] + [prefix(k) for k in range(1, nst + 1)]
    sfns = [solver_part(k) for k in range(5)] if stages_table else []
    step = jax.jit(jax.vmap(lambda o, x: mjx.step(model_of(o), x)))
    allf = fns + sfns + [step]
    with jax.numpy_rank_promotion("allow"):
        for f in allf:
            jax.block_until_ready(f(scene.obj, d))
        ts = [[] for _ in allf]
        t_end = time.perf_counter() + min_time
        while len(ts[0]) < rounds or (time.perf_counter() < t_end and len(ts[0]) < 50):
            for i, f in enumerate(allf):  # interleaved rounds: load drift hits every entry alike
                t0 = time.perf_counter()
                jax.block_until_ready(f(scene.obj, d))
                ts[i].append(time.perf_counter() - t0)
        T = [1e6 * float(np.min(t)) / B for t in ts]  # the least-disturbed call: other jobs only ever add time
        niter = np.asarray(jax.jit(jax.vmap(lambda o, x: _counting_solve(model_of(o), x)))(scene.obj, prefix(8)(
            scene.obj, d)))
    rows = [{"stage": name, "mjx_us": T[k + 1] - T[k]} for k, (name, _) in enumerate(stages[:nst])]
    S0 = T[nst + 1] if stages_table else 0.0
    solver_rows = [] if not stages_table else [{"stage": "  warm start (2 costs)", "mjx_us": T[nst + 2] - S0},
                   {"stage": "  context (cost, grad, H)", "mjx_us": T[nst + 3] - T[nst + 2]},
                   {"stage": "  1st line search", "mjx_us": T[nst + 4] - T[nst + 3]},
                   {"stage": "  1st update+gradient", "mjx_us": T[nst + 5] - T[nst + 4]}]
    if stages_table:
        solve_us = next(r["mjx_us"] for r in rows if r["stage"] == "solve")
        solver_rows.append({"stage": "  rest (while_loop)", "mjx_us": solve_us - (T[nst + 5] - S0)})
    step_us, ident_us, prefix_us = T[-1], T[0], T[nst]

    # native: the same states, one thread, stage timers
    n = min(n_native, B)
    datas = _native_datas(scene, d, n)
    names = [*[t for t in NATIVE_TIMERS.values() if t], "mjTIMER_STEP"]
    per_step = {t: [] for t in names}  # one duration per step: the median ignores steps another job preempted
    nat_iter, nat_eval = [], []
    for i, di in enumerate(datas):
        mi = scene.mj_of(i)
        for _ in range(native_steps):
            for t in names:
                di.timer[getattr(mujoco.mjtTimer, t)].duration = 0.0
            mujoco.mj_step(mi, di)
            for t in names:
                per_step[t].append(di.timer[getattr(mujoco.mjtTimer, t)].duration)
            nat_iter.append(int(di.solver_niter[0]))
            nat_eval.append(int(sum(di.solver[k].neval for k in range(min(int(di.solver_niter[0]), 20)))))
    native_us = {t: 1e6 * float(np.median(v)) for t, v in per_step.items()}
    for r in rows:
        t = NATIVE_TIMERS.get(r["stage"])
        r["native_us"] = native_us[t] if t else None
    if stages_table:
        rows.insert(5, {"stage": "project (native only)", "mjx_us": None,
                        "native_us": native_us["mjTIMER_POS_PROJECT"]})
        i = [r["stage"] for r in rows].index("solve") + 1
        rows[i:i] = [{**r, "native_us": None} for r in solver_rows]

    # native on every core: mujoco.rollout over the batch (as benchmarks/hands.py's native backend)
    from mujoco import rollout

    nthread = os.cpu_count() or 1
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    all_datas = _native_datas(scene, d, min(B, 20_000))
    models = [scene.mj_of(i) for i in range(len(all_datas))]
    state = np.stack([_state(models[i], x, spec) for i, x in enumerate(all_datas)])
    ctrl = np.stack([x.ctrl.copy() for x in all_datas])[:, None, :]
    pool = rollout.Rollout(nthread=nthread)
    work = [mujoco.MjData(scene.mj) for _ in range(nthread)]
    nstep = 20
    pool.rollout(models, work, state, ctrl, nstep=nstep)
    t0 = time.perf_counter()
    pool.rollout(models, work, state, ctrl, nstep=nstep)
    rollout_us = 1e6 * (time.perf_counter() - t0) / (len(models) * nstep)
    pool.close()

    opt = m_host.opt
    return {"scene": scene.name, "batch": B, "nv": int(scene.mj.nv), "nefc": int(d._impl.efc_J.shape[-2]),
            "ls_iterations": int(opt.ls_iterations), "iterations": int(opt.iterations),
            "rows": rows, "mjx_step_us": step_us, "mjx_forward_euler_us": prefix_us if stages_table else None,
            "mjx_identity_us": ident_us,
            "native_step_us": native_us["mjTIMER_STEP"], "native_rollout_us": rollout_us, "native_threads": nthread,
            "mjx_solver_trips": int(niter.max()), "mjx_solver_iter_mean": float(niter.mean()),
            "native_solver_iter_mean": float(np.mean(nat_iter)), "native_ls_evals_mean": float(np.mean(nat_eval))}


_FIELDS = ("qpos", "qvel", "act", "qacc_warmstart", "ctrl", "mocap_pos", "mocap_quat", "time")


def _native_datas(scene, d, n):
    """``mujoco.MjData`` of the first ``n`` states of the batched ``mjx.Data`` ``d`` (the fields a step reads)."""
    host = {k: np.asarray(getattr(d, k)) for k in _FIELDS}
    out = []
    for i in range(n):
        di = mujoco.MjData(scene.mj_of(i))
        for k in _FIELDS:
            if k == "time":
                di.time = float(host[k][i])
            else:
                getattr(di, k)[:] = host[k][i]
        out.append(di)
    return out


def _state(m, d, spec):
    s = np.empty(mujoco.mj_stateSize(m, spec))
    mujoco.mj_getState(m, d, s, spec)
    return s


def report(res: dict) -> str:
    lines = []
    for s in res["scenes"]:
        lines.append(f"\n{s['scene']}: batch {s['batch']}, nv {s['nv']}, nefc {s['nefc']}, solver iterations "
                     f"{s['iterations']}, ls_iterations {s['ls_iterations']}, {res['device']}, load {res['load']}")
        lines.append(f"{'stage':24s} {'mjx us/pose':>12s} {'native us':>10s} {'x native':>9s}")
        for r in s["rows"]:
            mu, nu = r["mjx_us"], r["native_us"]
            ratio = f"{mu / nu:9.1f}" if mu is not None and nu else f"{'-':>9s}"
            mus = f"{mu:12.2f}" if mu is not None else f"{'-':>12s}"
            nus = f"{nu:10.2f}" if nu is not None else f"{'-':>10s}"
            lines.append(f"{r['stage']:24s} {mus} {nus} {ratio}")
        if s["mjx_forward_euler_us"] is not None:
            lines.append(f"{'all stages (chained)':24s} {s['mjx_forward_euler_us']:12.2f}")
        lines.append(f"{'mjx.step / mj_step':24s} {s['mjx_step_us']:12.2f} {s['native_step_us']:10.2f} "
                     f"{s['mjx_step_us'] / s['native_step_us']:9.1f}")
        lines.append(f"{'(identity jit, in row 1)':24s} {s['mjx_identity_us']:12.2f}")
        lines.append(f"native mujoco.rollout, {s['native_threads']} threads: {s['native_rollout_us']:.2f} us per "
                     f"pose-step; mjx.step / that: {s['mjx_step_us'] / s['native_rollout_us']:.1f}x")
        lines.append(f"solver iterations per step: mjx loop trips {s['mjx_solver_trips']} (batch max), mean "
                     f"{s['mjx_solver_iter_mean']:.2f} per pose, each with {s['ls_iterations']} line-search steps "
                     f"under vmap; native {s['native_solver_iter_mean']:.2f}, line-search evaluations "
                     f"{s['native_ls_evals_mean']:.2f}")
        if "settle" in s:
            st = s["settle"]
            lines.append(f"settling (jit(vmap(system.pose)), batch {s['batch']}): mjx {st['mjx_poses_per_s']:.1f}, "
                         f"native {st['native_poses_per_s']:.1f} poses/s: MJX takes {st['mjx_time_x_native']:.2f}x "
                         f"native's time (goal <= 3x); poses differ by <= {st['max_pose_diff_m']:.1e} m; NaN "
                         f"{st['nan_fraction']}")
            if "mjx_warp_poses_per_s" in st:
                lines.append(f"  impl='warp': {st['mjx_warp_poses_per_s']:.1f} poses/s, "
                             f"{st['mjx_warp_time_x_native']:.2f}x native's time; poses differ from native by <= "
                             f"{st['warp_max_pose_diff_m']:.1e} m")
            elif "mjx_warp_error" in st:
                lines.append(f"  impl='warp': not measured: {st['mjx_warp_error']}")
    return "\n".join(lines)


def run(scenes=("stewart", "model_o", "articulated"), batch=1000, warm=20, n_native=64, native_steps=20,
        min_time=0.3, iterations=None, ls_iterations=None, jacobian=None, mjcf_options=False, settle=True,
        stages_table=True, seed=0, warp=False) -> dict:
    out = {"device": str(jax.devices()[0].platform), "load": " ".join(f"{x:.2f}" for x in os.getloadavg()),
           "scenes": []}
    with jax.enable_x64(True):
        for name in scenes:
            if name == "articulated":
                sc = _articulated_scene(batch, seed, iterations, ls_iterations)
            else:
                sc = _hand_scene(name, batch, seed, iterations, ls_iterations, jacobian, mjcf_options, warp)
            rec = profile(sc, warm, n_native, native_steps, min_time, stages_table=stages_table)
            if sc.systems is not None and settle:
                rec["settle"] = settle_rates(sc)
            out["scenes"].append(rec)
            print(report({**out, "scenes": out["scenes"][-1:]}), flush=True)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--batch", type=int, default=1000)
    ap.add_argument("--scenes", nargs="+", default=["stewart", "model_o", "articulated"],
                    choices=("stewart", "model_o", "articulated"))
    ap.add_argument("--warm", type=int, default=20, help="MJX steps from the start before profiling")
    ap.add_argument("--native", type=int, default=64, help="states timed natively (one thread)")
    ap.add_argument("--native-steps", type=int, default=20)
    ap.add_argument("--min-time", type=float, default=0.3)
    ap.add_argument("--iterations", type=int, default=None, help="override the MJX model's opt.iterations")
    ap.add_argument("--ls-iterations", type=int, default=None, help="override the MJX model's opt.ls_iterations")
    ap.add_argument("--jacobian", choices=("sparse", "dense"), default=None, help="MJX hands: mass matrix layout")
    ap.add_argument("--mjcf-options", action="store_true",
                    help="MJX hands: the MJCF's solver options and a dense mass matrix, not settle.mjx_model's")
    ap.add_argument("--no-settle", action="store_true", help="hands: skip the settled-poses/s comparison")
    ap.add_argument("--no-stages", action="store_true", help="whole steps only, no MJX stage rows (a quick run)")
    ap.add_argument("--warp", action="store_true",
                    help="hands: also settle with MJX's impl='warp' (mujoco-warp, an NVIDIA GPU), side by side")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    res = run(args.scenes, args.batch, args.warm, args.native, args.native_steps, args.min_time, args.iterations,
              args.ls_iterations, args.jacobian, args.mjcf_options, not args.no_settle, not args.no_stages,
              warp=args.warp)
    emit(res, "", args.json)


if __name__ == "__main__":
    main()
