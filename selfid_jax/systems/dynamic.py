"""Dynamic arms: an MJCF's own position servos stepped in MJX (gravity, inertia, gains), batched.

The kinematic backend (:func:`~selfid_jax.systems.mjcf.from_mjcf`) puts the
actuators exactly where they are commanded. A :class:`DynamicArm` instead
steps the MJCF's physics: each control step sets ``ctrl`` to the commanded
actuator targets and runs ``substeps`` ``mjx.step`` calls, so the joints lag
behind a step command, may overshoot, and (without gravity compensation) sag
under the links' weight, as a servoed robot does.

Physics: the model's own options, solver and integrator, unchanged
(``mjx.put_model(..., impl="jax")``). The shipped UR5e
(:func:`dynamic_ur5e`) uses ``implicitfast`` (velocity-implicit, which MJX
implements as :func:`mujoco.mjx.step`'s ``IMPLICITFAST`` branch; the damping
and the servos' ``kv`` enter the implicit update), dt 0.002 s, Newton solver
(only the +-2 pi joint-limit rows, inactive in normal use), no contacts. In
float64 it agrees with native ``mj_step`` to rounding (about 1e-15 rad over
4 s; ``tests/test_dynamic_arm.py`` holds it to 1e-10 rad). Build and run in
float64 (``jax_enable_x64`` on when the arm is built and when it runs) where
parity with native MuJoCo matters; float32 runs, less exactly (3e-6 rad,
2e-6 m at the flange over the same 4 s step-and-hold rollout).

Actuators must be position servos on hinge or slide joints with unit gear
(``ctrl`` = target joint position, rad or m): fixed gain ``kp``, affine bias
``-kp q - kv qdot``. Actuator ``i``'s coordinate is its joint's ``qpos``.

State: an ``mjx.Data`` (a pytree). API (all pure; jit and vmap over states,
targets and, through :meth:`DynamicArm.with_servo`, over gains):

* ``arm.init(q0, qd0=None) -> state``: at rest (or ``qd0``) at ``q0``, ``ctrl = q0``;
* ``arm.control_step(state, target, substeps=k) -> state``: ``k`` physics steps under ``ctrl = target``;
* ``arm.q(state)``, ``arm.qd(state)`` ``(n,)``; ``arm.observe(state) -> (p (3,), R (3, 3))`` site pose;
* ``arm.step(state, target, substeps=k) -> (state, q, (p, R))`` and its partial
  :meth:`DynamicArm.step_fn` ``(state, target) -> (state, q, (p, R))`` for a control loop;
* ``arm.rollout(state, targets (T, n), substeps=k) -> (state, Trace)``;
* :func:`substeps_for` ``(arm, period)``: physics steps per control period.
"""

from __future__ import annotations

import copy
import dataclasses
import functools
from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.systems.hands.settle import cast_like
from selfid_jax.systems.kinematics import _mjx
from selfid_jax.systems.mjcf import _load_mjmodel
from selfid_jax.systems.ur5e import UR5E_XML

__all__ = ["DynamicArm", "Trace", "dynamic_arm", "dynamic_ur5e", "substeps_for"]

StepFn = Callable[[Any, jax.Array], tuple[Any, jax.Array, tuple[jax.Array, jax.Array]]]
"""``step_fn(state, target (n,)) -> (state, q (n,), (p (3,), R (3, 3)))``: one control step of a dynamic arm."""


class Trace(NamedTuple):
    """Per control step, after the step (leading ``(T,)``; vmapped rollouts add batch axes in front)."""

    q: jax.Array  # (T, n) actuator (joint) positions [rad / m]
    qd: jax.Array  # (T, n) actuator (joint) velocities [rad/s / m/s]
    p: jax.Array  # (T, 3) site position [model length unit, m for the UR5e]
    R: jax.Array  # (T, 3, 3) site orientation (world frame)


@dataclasses.dataclass(frozen=True)
class DynamicArm:
    """An MJCF arm whose position servos are stepped in MJX; see the module docstring.

    Traced attributes:
      model: ``mjx.Model`` (float64 if x64 was on at build). Sweep gains or
        gravity compensation through :meth:`with_servo`.

    Static attributes:
      site_id: index of the POM site.
      qpos_adr: ``(n,)`` ``qpos`` address of each actuator's joint.
      dof_adr: ``(n,)`` ``qvel`` address of each actuator's joint.
      timestep: physics step [s] (the MJCF's ``opt.timestep``).
      name: label.
    """

    model: Any
    site_id: int = dataclasses.field(metadata=dict(static=True))
    qpos_adr: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    dof_adr: tuple[int, ...] = dataclasses.field(metadata=dict(static=True))
    timestep: float = dataclasses.field(metadata=dict(static=True))
    name: str = dataclasses.field(default="dynamic_arm", metadata=dict(static=True))

    @property
    def n_act(self) -> int:
        """Number of actuators ``n``."""
        return len(self.qpos_adr)

    # ------------------------------------------------------------------ state
    def init(self, q0, qd0=None):
        """State at joint positions ``q0 (n,)`` [rad / m], velocities ``qd0 (n,)`` (default 0), ``ctrl = q0``.

        Other joints stay at the model's ``qpos0``, at rest. Returns an
        ``mjx.Data`` (``mjx.make_data``'s dtypes, which :meth:`control_step` keeps).
        """
        mjx = _mjx()
        with jax.numpy_rank_promotion("allow"):
            d = mjx.make_data(self.model)
            f = d.qpos.dtype
            q0 = jnp.asarray(q0, f)
            qpos = d.qpos.at[jnp.asarray(self.qpos_adr)].set(q0)
            qvel = d.qvel if qd0 is None else d.qvel.at[jnp.asarray(self.dof_adr)].set(jnp.asarray(qd0, f))
            return d.replace(qpos=qpos, qvel=qvel, ctrl=q0.astype(d.ctrl.dtype))

    def q(self, state) -> jax.Array:
        """Actuator positions ``(n,)`` [rad / m] of ``state``."""
        return state.qpos[jnp.asarray(self.qpos_adr)]

    def qd(self, state) -> jax.Array:
        """Actuator velocities ``(n,)`` [rad/s / m/s] of ``state``."""
        return state.qvel[jnp.asarray(self.dof_adr)]

    def observe(self, state) -> tuple[jax.Array, jax.Array]:
        """Site pose at ``state.qpos``: ``(p (3,), R (3, 3))`` (``mjx.kinematics``; world frame, m).

        After ``mjx.step`` the data's own ``site_xpos`` belongs to the
        position before the step's integration, so the pose is recomputed.
        """
        mjx = _mjx()
        with jax.numpy_rank_promotion("allow"):
            d = mjx.kinematics(self.model, state)
        return d.site_xpos[self.site_id], d.site_xmat[self.site_id].reshape(3, 3)

    # ------------------------------------------------------------------ stepping
    def control_step(self, state, target, *, substeps: int):
        """``substeps`` (static) physics steps under ``ctrl = target (n,)`` [rad / m]: the next state."""
        mjx = _mjx()
        substeps = _check_substeps(substeps)
        d = state.replace(ctrl=jnp.asarray(target, state.ctrl.dtype))

        def body(_, d):
            # mjx.step may return other index dtypes (int64 under x64) than make_data (int32): keep the carry's
            return cast_like(mjx.step(self.model, d), d)

        with jax.numpy_rank_promotion("allow"):
            return jax.lax.fori_loop(0, substeps, body, d)

    def step(self, state, target, *, substeps: int):
        """One control step and its reading: ``(state, q (n,), (p (3,), R (3, 3)))`` after the step."""
        state = self.control_step(state, target, substeps=substeps)
        return state, self.q(state), self.observe(state)

    def step_fn(self, *, substeps: int) -> StepFn:
        """``step_fn(state, target) -> (state, q, (p, R))``: :meth:`step` with ``substeps`` bound (the loop's hook)."""
        return functools.partial(self.step, substeps=_check_substeps(substeps))

    def rollout(self, state, targets, *, substeps: int):
        """:meth:`step` over ``targets (T, n)`` (one per control step) under ``lax.scan``: ``(state, Trace)``."""

        def body(d, u):
            d, q, (p, R) = self.step(d, u, substeps=substeps)
            return d, Trace(q, self.qd(d), p, R)

        return jax.lax.scan(body, state, jnp.asarray(targets))

    # ------------------------------------------------------------------ sweeps
    def with_servo(self, *, kp=None, kv=None, gravcomp=None) -> DynamicArm:
        """The arm with other servo gains or gravity compensation; traced, so one compilation serves a sweep.

        Args:
          kp: position gain, scalar or ``(n,)`` [N m / rad or N / m]; sets
            ``gainprm[0] = kp`` and ``biasprm[1] = -kp``.
          kv: velocity gain, scalar or ``(n,)`` [N m s / rad or N s / m]; sets ``biasprm[2] = -kv``.
          gravcomp: scalar or ``(nbody,)`` fraction of each body's weight
            cancelled (MuJoCo's ``body_gravcomp``; 1: weightless links). The
            arm must have been built with gravity compensation
            (:func:`dynamic_arm` ``gravcomp=...``, 0.0 included), since MJX
            compiles the term in only then.
        """
        m = self.model
        act = jnp.arange(self.n_act)
        changes: dict[str, Any] = {}
        if kp is not None or kv is not None:
            gain, bias = m.actuator_gainprm, m.actuator_biasprm
            if kp is not None:
                kp = jnp.broadcast_to(jnp.asarray(kp, gain.dtype), (self.n_act,))
                gain, bias = gain.at[act, 0].set(kp), bias.at[act, 1].set(-kp)
            if kv is not None:
                bias = bias.at[act, 2].set(-jnp.broadcast_to(jnp.asarray(kv, bias.dtype), (self.n_act,)))
            changes.update(actuator_gainprm=gain, actuator_biasprm=bias)
        if gravcomp is not None:
            if not m.flg_gravcomp:
                raise ValueError("this arm was built without gravity compensation, which MJX compiles in only "
                                 "when some body has it: build it with dynamic_arm(..., gravcomp=0.0) (or any "
                                 "value) to sweep gravcomp")
            g = m.body_gravcomp
            changes["body_gravcomp"] = jnp.broadcast_to(jnp.asarray(gravcomp, g.dtype), g.shape)
        return dataclasses.replace(self, model=m.replace(**changes)) if changes else self


jax.tree_util.register_dataclass(
    DynamicArm, data_fields=["model"], meta_fields=["site_id", "qpos_adr", "dof_adr", "timestep", "name"]
)


def _check_substeps(substeps) -> int:
    if int(substeps) != substeps or substeps < 1:
        raise ValueError(f"substeps must be a whole number >= 1 (physics steps per control step), got {substeps!r}")
    return int(substeps)


def substeps_for(arm: DynamicArm, period: float) -> int:
    """Physics steps per control period: ``round(period / timestep)`` (>= 1).

    The simulated period is then ``substeps * timestep``, which differs from
    ``period`` when it is not a whole number of physics steps.

    Raises:
      ValueError: ``period`` not positive and finite, or shorter than half a physics step.
    """
    period = float(period)
    if not np.isfinite(period) or period <= 0:
        raise ValueError(f"period must be positive and finite (s), got {period!r}")
    k = int(round(period / arm.timestep))
    if k < 1:
        raise ValueError(f"period {period} s is shorter than half the physics step {arm.timestep} s")
    return k


# ---------------------------------------------------------------------- builders
def _servo_errors(mj, mujoco) -> list[str]:
    """Why each actuator is not a unit-gear position servo on a hinge/slide joint (empty if all are)."""
    bad = []
    for i in range(mj.nu):
        name = mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_ACTUATOR, i) or f"#{i}"
        gain, bias = mj.actuator_gainprm[i], mj.actuator_biasprm[i]
        if int(mj.actuator_trntype[i]) != int(mujoco.mjtTrn.mjTRN_JOINT):
            bad.append(f"{name!r}: transmission is not a joint")
        elif int(mj.jnt_type[mj.actuator_trnid[i, 0]]) not in (int(mujoco.mjtJoint.mjJNT_HINGE),
                                                               int(mujoco.mjtJoint.mjJNT_SLIDE)):
            bad.append(f"{name!r}: joint is not a hinge or slide")
        elif mj.actuator_gear[i, 0] != 1.0:
            bad.append(f"{name!r}: gear {mj.actuator_gear[i, 0]} (must be 1 so that ctrl is the joint target)")
        elif not (int(mj.actuator_gaintype[i]) == int(mujoco.mjtGain.mjGAIN_FIXED)
                  and int(mj.actuator_biastype[i]) == int(mujoco.mjtBias.mjBIAS_AFFINE)
                  and gain[0] > 0 and bias[0] == 0.0 and bias[1] == -gain[0]):
            bad.append(f"{name!r}: not a position servo (fixed gain kp > 0, bias 0 - kp q - kv qdot)")
    return bad


def dynamic_arm(path_or_model, site: str, *, gravcomp: float | None = None, name: str | None = None) -> DynamicArm:
    """A :class:`DynamicArm` from an MJCF model whose actuators are position servos, POM = site ``site``.

    Args:
      path_or_model: MJCF file path, XML string, or a ``mujoco.MjModel``.
      site: name of the POM site.
      gravcomp: None (the model's own ``gravcomp`` values, default) or the
        fraction of every body's weight to cancel (MuJoCo's body
        ``gravcomp``, applied as a passive force: 1.0 gives an arm whose
        controller compensates gravity, as industrial arms' do; 0.0 none).
        Any value (0.0 included) compiles the term in, so that
        :meth:`DynamicArm.with_servo` can sweep it.
      name: label (default ``"dynamic_" + model name``).

    Raises:
      ValueError: the file does not load, the site is missing, there are no
        actuators, an actuator is not a unit-gear position servo on a hinge or
        slide joint, or MJX cannot load the model.
    """
    import mujoco

    mj, label = _load_mjmodel(path_or_model)
    if gravcomp is not None:
        g = float(gravcomp)
        if not np.isfinite(g):
            raise ValueError(f"gravcomp must be finite, got {gravcomp!r}")
        mj = copy.deepcopy(mj)  # the caller's MjModel stays as it was
        mj.body_gravcomp[1:] = g  # not the world
        mj.flg_gravcomp = 1  # compiled in even for 0.0, so that with_servo can sweep it (MuJoCo: "safe")
    sid = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, site)
    if sid < 0:
        raise ValueError(f"site {site!r} not found in MJCF {label}")
    if mj.nu == 0:
        raise ValueError(f"MJCF {label} has no actuators")
    bad = _servo_errors(mj, mujoco)
    if bad:
        raise ValueError(f"MJCF {label}: every actuator must be a position servo on a hinge or slide joint; "
                         + "; ".join(bad))
    jnt = mj.actuator_trnid[:, 0]
    mjx = _mjx()
    try:
        model = mjx.put_model(mj, impl="jax")
    except NotImplementedError as e:
        raise ValueError(f"mjx.put_model cannot load MJCF {label} for simulation: {e}") from e
    return DynamicArm(model, int(sid), tuple(int(a) for a in mj.jnt_qposadr[jnt]),
                      tuple(int(a) for a in mj.jnt_dofadr[jnt]), float(mj.opt.timestep),
                      name or f"dynamic_{mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_MODEL, 0) or 'arm'}")


def dynamic_ur5e(*, gravcomp: float | None = None) -> DynamicArm:
    """The shipped UR5e (:data:`~selfid_jax.systems.ur5e.UR5E_XML`) as a :class:`DynamicArm`, POM = site ``"ee"``.

    Six position servos ``kp = 500 N m/rad``, ``kv = 50 N m s/rad`` (nominal,
    untuned), joint damping 1 N m s/rad, armature 0.1 kg m^2, UR's published
    link masses, dt 0.002 s, ``implicitfast``. Without gravity compensation
    the arm sags under its weight: held at
    :data:`~selfid_jax.systems.ur5e.UR5E_HOME` (``ctrl = q``) it settles
    off it by +0.044 rad (shoulder), +0.040 rad (elbow) and +0.0035 rad
    (wrist 1), 4.3 cm at the flange (``kp`` times the offset balances the
    gravity torque). ``gravcomp=1.0`` removes the sag.
    """
    return dynamic_arm(UR5E_XML, "ee", gravcomp=gravcomp, name="dynamic_ur5e")
