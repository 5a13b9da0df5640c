"""Settle an MJCF hand (position actuators, a POM site) at a command, in MJX or native MuJoCo.

Generic over any MJCF hand whose actuators are position servos (``ctrl`` = the
target actuator position, m or rad) and whose object carries a POM site. A
hand's pose at command ``q`` is the site pose once the model, started from a
reference state (``qpos0``, zero velocity), stops moving under ``ctrl = q``.
Settled means: the largest ``|qpos_t - qpos_{t-1}|`` over one step (quaternion
components included) stayed below ``tol`` for ``patience`` consecutive steps
(default 3: one small step can be the turning point of an oscillation) within
``max_steps`` steps. MJX keeps a residual velocity ~1e-7, so position change
(not velocity) is the criterion, and its per-step ``qpos`` change at rest has
a float64 noise floor (constraint-solver residual) that native MuJoCo does not:
up to ~9e-10 on the Stewart Hand, ~5e-9 on a Model O probe (native: ~1e-11).
Set ``tol`` above the floor of the hand's MJX model, or nothing settles.
Run everything in float64 (``with jax.enable_x64(True):``, build the
``mjx.Model`` inside it too).

API:

* ``mjx_settle(model, data0, ctrl, *, max_steps, tol, patience=3, loop="while") -> (data, settled)``:
  ``model`` an ``mjx.Model``, ``data0`` an ``mjx.Data`` (start state),
  ``ctrl (nu,)``; returns the settled ``mjx.Data`` (``mjx.forward`` run at
  its final state: ``data.site_xpos``/``site_xmat`` are the settled site
  poses) and a bool scalar. Jit-able, vmappable; ``loop="while"`` exits early
  and is forward-mode differentiable (``jax.jvp``/``jacfwd``);
  ``loop="scan"`` always runs ``max_steps`` (a settled state stays frozen)
  and is reverse-mode differentiable too.
* ``native_settle(mj_model, site, ctrl (B, nu), *, qpos0=None, max_steps, tol, patience=3, chunk=25, nthread=None)
  -> (p (B, 3), R (B, 3, 3), settled (B,))``: the same loop with
  ``mujoco.rollout`` on CPU threads (NumPy in and out, not traceable). ``site``
  is a name or an id; ``qpos0 (nq,)`` the start (default ``mj_model.qpos0``).
* :class:`MjxSettlePose` (``pose_fn`` of a :class:`~selfid_jax.systems.system.System`)
  with ``params`` a :class:`SettleParams` (``mjx.Model``, ``q_low``,
  ``q_high``): ``(params, q (nu,)) -> (p (3,), R (3, 3))``; NaN where ``q`` is
  outside ``[q_low, q_high]`` or the model did not settle.
* :func:`mjx_model` puts an ``MjModel`` for MJX in the current default float dtype, with solver options for
  settling (one Newton iteration and 4 line-search steps per step, a sparse mass matrix on CPU).
* :func:`native_pose_batch` / :class:`NativeSettlePose`: ``native_settle`` with
  the same NaN convention; the latter as a ``pose_fn`` through ``jax.pure_callback``
  (jit/vmap work, no derivatives; ``System.jacobian`` needs finite differences).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.math.checks import warn_if_host_bound
from selfid_jax.systems.kinematics import _mjx

__all__ = [
    "MjxSettlePose",
    "NativeSettlePose",
    "SETTLE_ITERATIONS",
    "SETTLE_LS_ITERATIONS",
    "SettleParams",
    "cast_like",
    "mjx_model",
    "mjx_settle",
    "native_pose_batch",
    "native_settle",
]


#: MJX solver options :func:`mjx_model` sets for settling: Newton iterations per step, line-search steps each.
SETTLE_ITERATIONS = 1
SETTLE_LS_ITERATIONS = 4


def mjx_model(mj, *, iterations: int | None = SETTLE_ITERATIONS, ls_iterations: int | None = SETTLE_LS_ITERATIONS,
              sparse: bool | None = None, impl: str = "jax"):
    """``mjx.put_model`` of ``mj`` (``impl``, JAX's by default) set up for settling, arrays in the default float dtype.

    A settle wants the equilibrium, not each step's exact constraint force, and
    MJX under ``vmap`` pays for solver work native MuJoCo skips
    (``benchmarks/mjx_profile.py`` measures it; on the Stewart Hand at batch
    1,000 on 2 CPU cores, these defaults and the state-only loop of
    :func:`mjx_settle` take MJX settling from 4.8x native's time to 1.9x,
    settled poses unchanged to 1e-16 m):

    Args:
      mj: ``mujoco.MjModel`` (not modified).
      iterations: the MJX model's ``opt.iterations`` (None: the MJCF's). One
        Newton iteration per step: with equality constraints only (both
        hands) the constraint cost is quadratic and one Newton step is exact
        (native MuJoCo stops after one too); where inequalities are active,
        each step warm-starts from the last one's accelerations, so the solve
        carries on across steps and the settle test passes only once nothing
        moves. With 1, MJX runs the Newton step without its ``while_loop``.
      ls_iterations: ``opt.ls_iterations`` (None: the MJCF's). Under ``vmap``
        MJX's line search runs all of them (a batched ``lax.cond`` becomes a
        select); natively it stops after 2 evaluations on these hands.
      sparse: True: sparse mass matrix (``opt.jacobian`` sparse: the hands
        are trees of short chains, so the factorisation is nearly free);
        False: dense; None: sparse on a CPU default backend, else the MJCF's
        setting (MJX's ``auto``: dense below 60 dofs, its advice for GPUs).
      impl: MJX's implementation, ``"jax"`` (default; runs on any JAX backend) or ``"warp"`` (NVIDIA GPUs,
        needs the ``mujoco-warp`` package).

    Returns:
      ``mjx.Model``.
    """
    import copy

    import mujoco

    if sparse is None and jax.default_backend() == "cpu":
        sparse = True
    if sparse is not None:
        mj = copy.copy(mj)
        mj.opt.jacobian = mujoco.mjtJacobian.mjJAC_SPARSE if sparse else mujoco.mjtJacobian.mjJAC_DENSE
    model = _mjx().put_model(mj, impl=impl)
    opt = {}
    if iterations is not None:
        opt["iterations"] = int(iterations)
    if ls_iterations is not None:
        opt["ls_iterations"] = int(ls_iterations)
    return model.replace(opt=model.opt.replace(**opt)) if opt else model


def cast_like(tree, ref):
    """``tree`` with every leaf cast to the dtype of the matching leaf of ``ref`` (arrays or ShapeDtypeStructs)."""
    return jax.tree_util.tree_map(lambda x, r: jnp.asarray(x, r.dtype), tree, ref)


def _max_change(a, b):
    return jnp.max(jnp.abs(a - b))


def mjx_settle(model, data0, ctrl, *, max_steps: int, tol: float, patience: int = 3, loop: str = "while"):
    """Step ``data0`` under ``ctrl`` until ``max|dqpos| < tol`` for ``patience`` steps running: ``(data, settled)``.

    Args:
      model: ``mjx.Model``.
      data0: ``mjx.Data`` start state (e.g. ``mjx.make_data(model)``: ``qpos0``, at rest).
      ctrl: ``(nu,)`` actuator commands (position targets, m or rad).
      max_steps: step budget (static).
      tol: settle tolerance on the per-step ``qpos`` change (qpos units).
      patience: consecutive steps below ``tol`` that count as settled (static).
      loop: ``"while"`` (early exit; forward-mode differentiable) or ``"scan"``
        (fixed ``max_steps``; reverse-mode differentiable).

    Returns:
      ``(data, settled)``: the state at the first settled step (or after
      ``max_steps``) with ``mjx.forward`` run at it (positions, site poses,
      forces and accelerations of that state), and a bool scalar.
    """
    with jax.numpy_rank_promotion("allow"):  # MJX broadcasts implicitly; a caller's "raise" must not break it
        return _mjx_settle(model, data0, ctrl, max_steps=max_steps, tol=tol, patience=patience, loop=loop)


#: The ``mjx.Data`` fields one step reads from the step before it (everything else it recomputes).
_STATE = ("qpos", "qvel", "act", "qacc_warmstart", "time")


def _mjx_settle(model, data0, ctrl, *, max_steps, tol, patience, loop):
    mjx = _mjx()
    d0 = data0.replace(ctrl=jnp.asarray(ctrl, data0.ctrl.dtype))
    max_steps, tol, patience = int(max_steps), float(tol), int(patience)
    # The loops carry the state only (positions, velocities, activations, the solver's warm start, time), not the
    # whole mjx.Data (~40 KB a pose on the Stewart Hand): under vmap a while_loop selects its whole carry per batch
    # element every trip (on the Stewart Hand at batch 1,000 carrying the Data took 24% more time).
    s0 = {k: getattr(d0, k) for k in _STATE}

    def step(s, run):
        """One step from state ``s``; ``run``: consecutive steps below ``tol`` so far (int32)."""
        d1 = mjx.step(model, d0.replace(**s))
        s1 = {k: jnp.asarray(getattr(d1, k), s0[k].dtype) for k in _STATE}
        run1 = jnp.where(_max_change(s1["qpos"], s["qpos"]) < tol, run + 1, 0).astype(jnp.int32)
        return s1, run1

    zero = jnp.zeros((), jnp.int32)
    if loop == "while":
        def cond(c):
            _, k, run = c
            return jnp.logical_and(k < max_steps, run < patience)

        def while_body(c):
            s, k, run = c
            s1, run1 = step(s, run)
            return s1, k + 1, run1

        s, _, run = jax.lax.while_loop(cond, while_body, (s0, zero, zero))
    elif loop == "scan":
        def scan_body(c, _):
            s, run = c
            s1, run1 = step(s, run)
            done = run >= patience
            s1 = jax.tree_util.tree_map(lambda a, b: jnp.where(done, a, b), s, s1)
            return (s1, jnp.where(done, run, run1)), None

        (s, run), _ = jax.lax.scan(scan_body, (s0, zero), None, length=max_steps)
    else:
        raise ValueError(f"loop must be 'while' or 'scan', got {loop!r}")
    return mjx.forward(model, d0.replace(**s)), run >= patience


@dataclasses.dataclass(frozen=True)
class SettleParams:
    """Traced parameters of :class:`MjxSettlePose`.

    ``model`` (``mjx.Model``); ``q_low``, ``q_high`` ``(nu,)`` safe command
    range; ``qpos0`` ``(nq,)`` start configuration (None: ``model.qpos0``).
    """

    model: object
    q_low: jax.Array
    q_high: jax.Array
    qpos0: jax.Array | None = None


jax.tree_util.register_dataclass(SettleParams, data_fields=["model", "q_low", "q_high", "qpos0"], meta_fields=[])


def _nan_unless(ok, p, R):
    nan = jnp.asarray(jnp.nan, p.dtype)
    return jnp.where(ok, p, nan), jnp.where(ok, R, nan)


@dataclasses.dataclass(frozen=True)
class MjxSettlePose:
    """Pose map ``(SettleParams, q (nu,)) -> (p (3,), R (3, 3))``: the POM site after MJX settling at ``ctrl = q``.

    Starts from ``mjx.make_data(model)`` (``params.qpos0`` or the model's, at rest) every call, so the
    pose is a function of ``q`` alone. NaN where ``q`` leaves
    ``[q_low, q_high]`` or the model does not settle within ``max_steps``.
    Hashable by value (static fields only).
    """

    site_id: int
    max_steps: int = 400
    tol: float = 1e-9
    patience: int = 3
    loop: str = "while"

    def __call__(self, params, q):
        model = params.model
        q = jnp.asarray(q)
        with jax.numpy_rank_promotion("allow"):
            data0 = _mjx().make_data(model)
        if params.qpos0 is not None:
            data0 = data0.replace(qpos=jnp.asarray(params.qpos0, data0.qpos.dtype))
        data, settled = mjx_settle(model, data0, q, max_steps=self.max_steps, tol=self.tol,
                                   patience=self.patience, loop=self.loop)
        ok = settled & jnp.all((q >= params.q_low) & (q <= params.q_high))
        p = data.site_xpos[self.site_id].astype(q.dtype)
        R = data.site_xmat[self.site_id].reshape(3, 3).astype(q.dtype)
        return _nan_unless(ok, p, R)


# ---------------------------------------------------------------------- native
_POOLS: dict = {}


def _rollout(nthread):
    from mujoco import rollout

    key = nthread
    if key not in _POOLS:
        _POOLS[key] = rollout.Rollout(nthread=nthread)
    return _POOLS[key]


def native_settle(mj_model, site, ctrl, *, qpos0=None, max_steps: int = 400, tol: float = 1e-9, patience: int = 3,
                  chunk: int = 25, nthread: int | None = None):
    """Settle ``B`` commands with ``mujoco.rollout`` (CPU threads): ``(p (B, 3), R (B, 3, 3), settled (B,))``.

    Each element starts from ``qpos0`` at rest and steps under its ``ctrl``
    until ``max|dqpos| < tol`` for ``patience`` steps running (the test of :func:`mjx_settle`),
    rolled out ``chunk`` steps at a time; settled elements drop out. The pose is
    the site's after ``mj_kinematics`` at the settled ``qpos`` (unsettled: the
    pose after ``max_steps``, with ``settled`` False). NumPy float64, not traceable.

    Args:
      mj_model: ``mujoco.MjModel``.
      site: POM site name or id.
      ctrl: ``(B, nu)`` (or ``(nu,)``) commands.
      qpos0: ``(nq,)`` start configuration (default ``mj_model.qpos0``).
      max_steps, tol, patience: step budget, settle tolerance (qpos units), steps below it in a row.
      chunk: steps per rollout call.
      nthread: rollout threads (default: ``os.cpu_count()``).
    """
    import os

    import mujoco

    ctrl = np.atleast_2d(np.asarray(ctrl, np.float64))
    B = ctrl.shape[0]
    sid = site if isinstance(site, (int, np.integer)) else mujoco.mj_name2id(mj_model, mujoco.mjtObj.mjOBJ_SITE, site)
    if sid < 0:
        raise ValueError(f"site {site!r} not found")
    nthread = int(nthread or os.cpu_count() or 1)
    datas = [mujoco.MjData(mj_model) for _ in range(nthread)]
    d = datas[0]
    if qpos0 is not None:
        d.qpos[:] = qpos0
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    nstate = mujoco.mj_stateSize(mj_model, spec)
    s0 = np.empty(nstate)
    mujoco.mj_getState(mj_model, d, s0, spec)
    q_adr = 1  # FULLPHYSICS = time, qpos, qvel, act, ...
    nq = mj_model.nq
    state = np.tile(s0, (B, 1))
    settled = np.zeros(B, bool)
    run = np.zeros(B, int)  # consecutive steps below tol
    final = state[:, q_adr:q_adr + nq].copy()
    active = np.arange(B)
    pool = _rollout(nthread)
    steps = 0
    while active.size and steps < max_steps:
        n = min(int(chunk), max_steps - steps)
        st, _ = pool.rollout(mj_model, datas, state[active], ctrl[active, None, :], nstep=n)
        qs = np.concatenate([state[active, None, q_adr:q_adr + nq], st[:, :, q_adr:q_adr + nq]], axis=1)
        delta = np.max(np.abs(np.diff(qs, axis=1)), axis=2)  # (b, n)
        small = delta < tol
        r = run[active].copy()
        runs = np.empty_like(delta, dtype=int)
        for t in range(n):  # running count of consecutive small steps
            r = np.where(small[:, t], r + 1, 0)
            runs[:, t] = r
        hit = runs >= patience
        done = hit.any(1)
        first = np.where(done, hit.argmax(1), n - 1)
        final[active] = st[np.arange(active.size), first, q_adr:q_adr + nq]
        run[active] = r
        settled[active[done]] = True
        state[active] = st[:, -1]
        active = active[~done]
        steps += n
    p = np.empty((B, 3))
    R = np.empty((B, 3, 3))
    for i in range(B):
        d.qpos[:] = final[i]
        mujoco.mj_kinematics(mj_model, d)
        p[i] = d.site_xpos[sid]
        R[i] = d.site_xmat[sid].reshape(3, 3)
    return p, R, settled


def native_pose_batch(mj_model, site, q, *, q_low=-np.inf, q_high=np.inf, **kw):
    """:func:`native_settle` with NaN poses where unsettled or ``q`` is outside ``[q_low, q_high]``: ``(p, R, ok)``."""
    q = np.atleast_2d(np.asarray(q, np.float64))
    p, R, settled = native_settle(mj_model, site, q, **kw)
    ok = settled & np.all((q >= q_low) & (q <= q_high), axis=1)
    p[~ok] = np.nan
    R[~ok] = np.nan
    return p, R, ok


@dataclasses.dataclass(frozen=True, eq=False)
class NativeSettlePose:
    """Pose map ``(params, q (nu,)) -> (p (3,), R (3, 3))`` by native settling through ``jax.pure_callback``.

    ``params`` is ``(q_low, q_high)``; the ``MjModel`` (and an optional start
    ``qpos0 (nq,)``) is held here (hashed by identity). jit and vmap work (vmap
    batches the callback into one :func:`native_settle`); no derivatives.
    """

    mj_model: object
    site_id: int
    max_steps: int = 400
    tol: float = 1e-9
    patience: int = 3
    qpos0: object = None

    def __post_init__(self):
        warn_if_host_bound("a hand's native settling (backend='native')",
                           "Use backend='mjx' (MJX's settling, on the device) for batches on an accelerator.")

    def __call__(self, params, q):
        q_low, q_high = params
        q = jnp.asarray(q)
        dt = q.dtype

        def host(qb, lo, hi):
            qb = np.asarray(qb, np.float64)
            nu = qb.shape[-1]
            flat = qb.reshape(-1, nu)
            lo, hi = (np.broadcast_to(np.asarray(x, np.float64), qb.shape).reshape(-1, nu) for x in (lo, hi))
            p, R, _ = native_pose_batch(self.mj_model, self.site_id, flat, q_low=lo, q_high=hi,
                                        max_steps=self.max_steps, tol=self.tol, patience=self.patience,
                                        qpos0=self.qpos0)
            lead = qb.shape[:-1]
            return p.reshape(lead + (3,)).astype(dt), R.reshape(lead + (3, 3)).astype(dt)

        out = (jax.ShapeDtypeStruct(q.shape[:-1] + (3,), dt), jax.ShapeDtypeStruct(q.shape[:-1] + (3, 3), dt))
        return jax.pure_callback(host, out, q, q_low, q_high, vmap_method="expand_dims")
