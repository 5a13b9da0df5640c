"""Closed-loop rollout: tactile controller -> gripper twist -> arm inverse Jacobian -> mocap -> MuJoCo or MJX.

One rollout (:func:`rollout`) is a ``lax.scan`` over control steps (pure JAX,
jit + vmap), after a first reading at the grasp that fixes the initial contact
set ``C_1`` and the Eq. 2 threshold (:func:`~.tactile.initial_contact`: fixed,
or the seed's Sec. 5.1 rule). Each step: read the gripper pose and the markers (:mod:`.tactile`),
run the controller (Tac-Man stop-and-go as its papers describe it, Tac-Man
re-aiming after each recovery, TacMan-Turbo literal, TacMan-Turbo keeping
``u0``, or TacMan-Turbo with an integral lead; a traced :class:`Controller`), map
the gripper twist (gripper frame) to the world frame and through the arm's
inverse Jacobian (the true one at the current joints, or a fixed
self-identified estimate), scale by ``alpha``
(Eq. 25-26) on the arm's joint-velocity limits, stretch a scaled step over
``dt / alpha`` (Eq. 27: the controller waits until it is done), integrate the
joints, and move the mocap along the arm's forward kinematics over
``substeps`` physics steps. The arm is kinematic (its joints follow the
command exactly) and the controllers read the gripper pose from it (where
the step is applied); under the ``"weld"`` grasp the gripper is a dynamic
body welded to the mocap, under ``"spring"`` the mocap itself, pulling the
handle through :func:`spring_wrench` (native backend only).

Backends (static): ``"native"`` steps ``mujoco.MjModel`` on the host through
``jax.pure_callback`` (a vmapped batch is one callback that loops over it,
skipping finished rollouts); ``"mjx"`` steps ``mjx.Model`` with per-object
fields set by :func:`~.scenes.apply_mjx` (compiled; worth it on a GPU).

Size: about 540 lines, one rollout: its carry, the physics step on both backends and the sensor model are
private helpers of a single ``lax.scan`` body.
"""

from __future__ import annotations

import enum
from typing import Any, Literal, NamedTuple, get_args

import jax
import jax.numpy as jnp
import jaxlie
import numpy as np

from selfid_jax.articulated import scenes, tacman, tactile
from selfid_jax.math.checks import warn_if_host_bound

__all__ = ["CONTROLLERS", "Controller", "ControllerLabel", "RolloutParams", "RolloutResult", "Static", "rollout",
           "make_static", "spring_wrench", "time_weighted_jerk"]


class Controller(enum.IntEnum):
    """The tactile controller of a rollout; its value is the traced ``RolloutParams.controller``.

    Configs and result tables name it by :attr:`label` (the lower-case member
    name, e.g. ``"turbo_u0"``); :meth:`parse` maps a label back.
    """

    TACMAN = 0  # Tac-Man stop-and-go as its papers describe it: fixed direction, no re-aim (tacman.tacman_step)
    TURBO = 1  # literal TacMan-Turbo, Eq. 14-18 (tacman.turbo_step)
    TURBO_U0 = 2  # TacMan-Turbo keeping the base speed u0 in the prediction (tacman.keep_speed)
    TURBO_LEAD = 3  # TacMan-Turbo with an integral lead on a smoothed screw (tacman.lead_step)
    TACMAN_REAIM = 4  # Tac-Man re-aiming its exploration after each recovery (our departure; tacman.tacman_step)

    @property
    def label(self) -> str:
        return self.name.lower()

    @classmethod
    def parse(cls, label: str) -> Controller:
        """The member whose :attr:`label` is ``label``; ``ValueError`` naming the allowed labels otherwise."""
        try:
            return cls[label.upper()]
        except KeyError:
            raise ValueError(f"unknown controller {label!r}; allowed: {', '.join(CONTROLLERS)}") from None


# a Controller's label, as a type (configs)
ControllerLabel = Literal["tacman", "turbo", "turbo_u0", "turbo_lead", "tacman_reaim"]
CONTROLLERS: tuple[ControllerLabel, ...] = get_args(ControllerLabel)  # the labels, in value order
if CONTROLLERS != tuple(c.label for c in Controller):  # a Literal cannot be built from the enum: keep them in step
    raise AssertionError(f"ControllerLabel {CONTROLLERS} != Controller labels {tuple(c.label for c in Controller)}")


class Static(NamedTuple):
    """Closed over by :func:`rollout` (hashable pieces and arrays; no config objects)."""

    backend: str  # "native" | "mjx"
    layout: scenes.Layout
    mj_model: Any  # mujoco.MjModel template (native); also the source of the MJX model
    mjx_model: Any  # mjx.Model template (mjx backend) or None
    pads: tactile.Pads
    arm: Any  # selfid_jax System (6-D task), POM = gripper frame
    q0: np.ndarray  # (n,) arm start joints [rad]
    steps: int  # control steps
    substeps: int  # physics steps per control step
    stride: int  # trace subsampling
    level: float  # success progress
    scene_id: int  # crc32 of the template and settings (see RolloutResult.scene_id)


class RolloutParams(NamedTuple):
    """Traced, one row (vmap adds a leading axis); hosts build the rows of a sweep as numpy arrays."""

    obj: scenes.ObjectParams
    controller: scenes.ParamArray  # () int32 Controller value
    use_estimate: scenes.ParamArray  # () bool: fixed self-ID estimate instead of the true inverse Jacobian
    jinv_est: scenes.ParamArray  # (n, 6) self-identified inverse Jacobian
    key: scenes.ParamArray  # (2,) uint32 key data (marker noise)
    speed: scenes.ParamArray  # () |u0| [m/s] along the gripper's x axis
    marker_noise: scenes.ParamArray  # () marker reading noise sd [m] (tactile.read)
    contact_eps: scenes.ParamArray  # () Eq. 2 threshold [m] when contact_points is 0
    contact_points: scenes.ParamArray  # () int32: 0 = the fixed contact_eps; n > 0 = the seed's rule (Sec. 5.1), the
    # smallest threshold leaving exactly n markers in the initial reading (tactile.initial_contact; the paper: 9)
    qdot_max: scenes.ParamArray  # (n,) joint-velocity limits [rad/s]
    beta: scenes.ParamArray  # () Eq. 25 safety factor
    dev_high: scenes.ParamArray  # () Tac-Man exploration -> recovery [m]
    dev_low: scenes.ParamArray  # () Tac-Man recovery -> exploration [m]
    recovery_gain: scenes.ParamArray  # () Tac-Man: fraction of the in-hand pose removed per recovery step
    slip: scenes.ParamArray  # () in-hand translation declared a slip [m]
    slip_rot: scenes.ParamArray  # () in-hand rotation declared a slip [rad]
    lead_max: scenes.ParamArray  # () turbo_lead: cap of the integral lead [m]
    twist_tau: scenes.ParamArray  # () turbo_lead: handle-twist smoothing time constant [s] (0: none)
    grasp: scenes.ParamArray  # (4,) spring grasp [k N/m, c N s/m, kr N m/rad, cr N m s/rad] (unused by "weld")


class RolloutResult(NamedTuple):
    success: jax.Array  # () bool
    failed: jax.Array  # () bool: slipped or non-finite
    slipped: jax.Array  # () bool
    nonfinite: jax.Array  # () bool: the physics state went non-finite (rollout frozen there)
    steps_used: jax.Array  # () int32 control steps until success (or all)
    progress: jax.Array  # () final normalised progress
    efficiency: jax.Array  # () % of the path per control step (100 min(progress, level) / level / steps_used)
    efficiency_60hz: jax.Array  # () % of the path per 1/60 s (the paper's step): 100 min(p, level) / level / (60 T)
    jerk: jax.Array  # () mean ||d^3 q / dt^3|| over the steps used [rad/s^3]
    jerk_tw: jax.Array  # () time average of |d^3 q_1 / dt^3| of the base joint over the task [s^-3]
    path_dev: jax.Array  # () mean distance gripper (arm) to handle over the steps used [m]
    dev_mean: jax.Array  # () mean contact deviation over the steps used [m]
    dev_max: jax.Array  # () max contact deviation [m]
    invalid_steps: jax.Array  # () int32 steps whose contact set failed Eq. 11-12
    alpha_min: jax.Array  # () smallest alpha applied
    recovery_steps: jax.Array  # () int32 Tac-Man steps spent in recovery (0 for the Turbo controllers)
    contact_eps: jax.Array  # () the Eq. 2 threshold used [m] (fixed, or set by the seed's rule on the first reading)
    contact_n: jax.Array  # () int32 markers in the initial contact set C_1
    contact_ok: jax.Array  # () bool: the seed's rule found a threshold with exactly contact_points markers (True if
    # the threshold is fixed)
    handle_trace: jax.Array  # (S, 3) handle positions in G1 frame [m], every stride-th step
    gripper_trace: jax.Array  # (S, 3) gripper positions in G1 frame [m]
    progress_trace: jax.Array  # (S,) progress
    dev_trace: jax.Array  # (S,) contact deviation [m]
    recovery_trace: jax.Array  # (S,) bool: the step's command was a Tac-Man recovery
    scene_id: jax.Array  # () int32 constant identifying the scene template: the host callback is invisible in the
    # lowered program text, and selfid_jax.runner.sweep shares compiled programs by that text, so without it two kinds
    # with equal shapes (prismatic, revolute) would share one callback


#: Line-search steps per Newton iteration of the MJX backend (at most the MJCF's ``ls_iterations``).
MJX_LS_ITERATIONS = 4


def make_static(backend, layout, mj_model, pads, arm, q0, *, steps, substeps, stride) -> Static:
    if backend not in ("native", "mjx"):
        raise ValueError(f"backend must be 'native' or 'mjx', got {backend!r}")
    mjx_model = None
    if backend == "mjx" and layout.grasp == "spring":
        raise ValueError("grasp model 'spring' runs on the native backend only (its wrench is applied between "
                         "MuJoCo's position and velocity stages, mj_step1 / mj_step2); use backend: native")
    if backend == "native":
        warn_if_host_bound("the articulated rollout's backend 'native'",
                           "Use backend: mjx for the rigid and soft grasps (the spring grasp runs on native only).")
    if backend == "mjx":
        from mujoco import mjx

        mjx_model = mjx.put_model(mj_model, impl="jax")
        # Under vmap MJX's line search runs all opt.ls_iterations steps (its batched lax.cond becomes a select; native
        # MuJoCo stops after ~2.4 evaluations here): 4 instead of 50 cut a step from 62 to 20 us a pose at batch
        # 1,000 on CPU (benchmarks/mjx_profile.py), the same 1.15 Newton iterations a step, handle paths unchanged.
        ls = min(int(mj_model.opt.ls_iterations), MJX_LS_ITERATIONS)
        mjx_model = mjx_model.replace(opt=mjx_model.opt.replace(ls_iterations=ls))
    import zlib

    m = mj_model
    blob = repr((backend, layout, substeps)).encode() + b"".join(
        np.ascontiguousarray(a, np.float64).tobytes() for a in (m.opt.timestep, m.body_pos, m.jnt_stiffness,
                                                               m.dof_damping, m.eq_solref, m.body_mass))
    return Static(backend, layout, mj_model, mjx_model, pads, arm, np.asarray(q0, float), int(steps), int(substeps),
                  int(stride), scenes.success_level(layout.kind), int(zlib.crc32(blob) & 0x7FFFFFFF))


# ----------------------------------------------------------------------------- physics backends


def spring_wrench(p_t, q_t, v_t, w_t, p_h, q_h, v_h, w_h, grasp, out=None):
    """Spring-damper wrench ``(6,) = [force N, torque N m]`` (world frame) on the handle from the gripper.

    ``F = -k (p_h - p_t) - c (v_h - v_t)``, ``tau = -kr R_t log(R_t^T R_h) -
    cr (w_h - w_t)``: positions ``p (3,)`` [m], unit quaternions ``q (4,)``
    (w, x, y, z), linear ``v (3,)`` [m/s] and angular ``w (3,)`` [rad/s]
    velocities of the gripper (``_t``) and the handle (``_h``), world frame;
    ``grasp (4,) = [k, c, kr, cr]``. numpy float64 (MuJoCo's quaternion
    helpers), one call per physics step on the host; written into ``out``
    when given.
    """
    f64 = lambda a: np.asarray(a, np.float64)
    out = np.empty(6) if out is None else out
    _Wrench()(f64(p_t), f64(q_t), f64(v_t).tolist(), f64(w_t).tolist(), f64(p_h), f64(q_h), f64(v_h), f64(w_h),
              f64(grasp).tolist(), out)
    return out


class _Wrench:
    """:func:`spring_wrench` with its work arrays kept between calls: the host loop calls it once per physics step.

    Positions, quaternions and the handle's velocities are float64 arrays (MuJoCo's views), the gripper's
    velocities ``v_t``, ``w_t`` sequences of 3 floats, ``gains = (k, c, kr, cr)`` floats; the same float64
    operations, in the same order, as numpy's on the arrays, written into ``out (6,)``.
    """

    def __init__(self):
        import mujoco

        self.mj = mujoco
        self.qi, self.qr, self.rv, self.rot = np.empty(4), np.empty(4), np.empty(3), np.empty(3)

    def __call__(self, p_t, q_t, v_t, w_t, p_h, q_h, v_h, w_h, gains, out):
        mj, qi, qr, rv, rot = self.mj, self.qi, self.qr, self.rv, self.rot
        k, c, kr, cr = gains
        mj.mju_negQuat(qi, q_t)
        mj.mju_mulQuat(qr, qi, q_h)  # R_t^T R_h
        mj.mju_quat2Vel(rv, qr, 1.0)  # its rotation vector (gripper frame)
        mj.mju_rotVecQuat(rot, rv, q_t)  # in the world frame
        (a0, a1, a2), (b0, b1, b2) = p_h.tolist(), p_t.tolist()
        (c0, c1, c2), (d0, d1, d2) = v_h.tolist(), v_t
        (e0, e1, e2), (f0, f1, f2) = w_h.tolist(), w_t
        r0, r1, r2 = rot.tolist()
        nk, nkr = -k, -kr
        out[:] = (nk * (a0 - b0) - c * (c0 - d0), nk * (a1 - b1) - c * (c1 - d1), nk * (a2 - b2) - c * (c2 - d2),
                  nkr * r0 - cr * (e0 - f0), nkr * r1 - cr * (e1 - f1), nkr * r2 - cr * (e2 - f2))


def _target_velocity(mpos, mquat, h):
    """Linear and angular velocity ``((K, 3), (K, 3))`` of the mocap between ``K + 1`` poses ``h`` s apart (world)."""
    from scipy.spatial.transform import Rotation

    v = np.diff(mpos, axis=0) / h
    r = Rotation.from_quat(mquat[:, [1, 2, 3, 0]])
    w = (r[1:] * r[:-1].inv()).as_rotvec() / h  # world-frame increment R_{k+1} R_k^T
    return v, w


def _sensors(xpos_g, xquat_g, xpos_h, xquat_h):
    return jnp.concatenate([xpos_g, xquat_g, xpos_h, xquat_h])


_NATIVE: dict = {}


def _native_host(static: Static):
    """Host stepping function for ``static`` (one MjModel copy and MjData per static)."""
    import copy

    import mujoco

    key = id(static.mj_model), static.layout
    if key in _NATIVE:
        return _NATIVE[key]
    m = copy.deepcopy(static.mj_model)
    d = mujoco.MjData(m)
    lay, K = static.layout, static.substeps
    spring = lay.grasp == "spring"
    h = float(m.opt.timestep)
    vel = np.zeros(6)
    # views into MjData's buffers, bound once: the loop below runs once per physics step
    vel_ang, vel_lin = vel[:3], vel[3:]
    mocap_p, mocap_q = d.mocap_pos[0], d.mocap_quat[0]
    grip_p, grip_q, handle_p, handle_q = (d.xpos[lay.gripper], d.xquat[lay.gripper], d.xpos[lay.handle],
                                          d.xquat[lay.handle])
    handle_f = d.xfrc_applied[lay.handle]
    step1, step2, object_velocity = mujoco.mj_step1, mujoco.mj_step2, mujoco.mj_objectVelocity
    body = mujoco.mjtObj.mjOBJ_BODY
    wrench = _Wrench()

    def host(qpos, qvel, warm, mpos, mquat, active, grasp, *obj):
        lead = np.broadcast_shapes(qpos.shape[:-1], active.shape, *(o.shape[: o.ndim - f] for o, f in
                                                                    zip(obj, _OBJ_NDIM)))
        B = int(np.prod(lead))
        qpos = np.broadcast_to(qpos, lead + qpos.shape[-1:]).reshape(B, -1).astype(np.float64).copy()
        qvel = np.broadcast_to(qvel, lead + qvel.shape[-1:]).reshape(B, -1).astype(np.float64).copy()
        warm = np.broadcast_to(warm, lead + warm.shape[-1:]).reshape(B, -1).astype(np.float64).copy()
        mpos = np.broadcast_to(mpos, lead + mpos.shape[-2:]).reshape(B, K + 1, 3)
        mquat = np.broadcast_to(mquat, lead + mquat.shape[-2:]).reshape(B, K + 1, 4)
        active = np.broadcast_to(active, lead).reshape(B)
        grasp = np.broadcast_to(grasp, lead + grasp.shape[-1:]).reshape(B, 4)
        obj = tuple(np.broadcast_to(o, lead + o.shape[o.ndim - f:]).reshape((B,) + o.shape[o.ndim - f:])
                    for o, f in zip(obj, _OBJ_NDIM))
        sens = np.zeros((B, 14))
        for b in range(B):
            scenes.apply_native(m, lay, scenes.ObjectParams(*(o[b] for o in obj)))
            d.qpos[:], d.qvel[:], d.qacc_warmstart[:] = qpos[b], qvel[b], warm[b]
            pos_b, quat_b = mpos[b], mquat[b]
            if active[b] and spring:
                v_t, w_t = _target_velocity(pos_b, quat_b, h)
                v_t, w_t, gains = v_t.tolist(), w_t.tolist(), grasp[b].tolist()
                for k in range(K):  # the wrench from the gripper and handle states at the same instant t_k
                    mocap_p[:], mocap_q[:] = pos_b[k], quat_b[k]
                    step1(m, d)
                    object_velocity(m, d, body, lay.handle, vel, 0)
                    wrench(grip_p, grip_q, v_t[k], w_t[k], handle_p, handle_q, vel_lin, vel_ang, gains, handle_f)
                    step2(m, d)
            elif active[b]:
                for k in range(K):
                    mocap_p[:], mocap_q[:] = pos_b[k + 1], quat_b[k + 1]
                    mujoco.mj_step(m, d)
            if spring:
                mocap_p[:], mocap_q[:] = pos_b[-1], quat_b[-1]
            mujoco.mj_kinematics(m, d)
            qpos[b], qvel[b], warm[b] = d.qpos, d.qvel, d.qacc_warmstart
            sens[b] = np.concatenate([grip_p, grip_q, handle_p, handle_q])
        # float64 travels as uint32 pairs: the callback's return check canonicalises float64 to float32
        # when x64 is enabled by a (thread-local) context rather than globally.
        out = lambda a: np.ascontiguousarray(a, np.float64).view(np.uint32).reshape(lead + a.shape[1:] + (2,))
        return out(qpos), out(qvel), out(warm), out(sens)

    _NATIVE[key] = host
    return host


_OBJ_NDIM = tuple(len(s) for s in ((3,), (3,), (), (), (2, 5), (), (), ()))  # per-field core ndim


class _Phys(NamedTuple):
    qpos: jax.Array
    qvel: jax.Array
    warm: jax.Array
    data: Any  # mjx.Data (mjx backend) or None


def _phys_init(static: Static, obj):
    m = static.mj_model
    f = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32  # type: ignore[attr-defined]
    qpos, qvel, warm = (jnp.asarray(a, f) for a in (m.qpos0, np.zeros(m.nv), np.zeros(m.nv)))
    data = None
    if static.backend == "mjx":
        from mujoco import mjx

        model = scenes.apply_mjx(static.mjx_model, static.layout, obj)
        with jax.numpy_rank_promotion("allow"):
            data = mjx.kinematics(model, mjx.make_data(model))
    return _Phys(qpos, qvel, warm, data)


def _phys_step(static: Static, obj, phys: _Phys, mpos, mquat, active, grasp):
    """``substeps`` physics steps with the mocap along ``mpos (K + 1, 3)``, ``mquat (K + 1, 4)`` (index 0: the pose
    at the start of the control step): ``(phys, sensors (14,))``; ``grasp (4,)`` the spring grasp's gains."""
    lay = static.layout
    if static.backend == "native":
        host = _native_host(static)
        f = phys.qpos.dtype
        u = lambda n: jax.ShapeDtypeStruct((n, 2), jnp.uint32)
        shapes = (u(phys.qpos.shape[0]), u(phys.qvel.shape[0]), u(phys.warm.shape[0]), u(14))
        outs = jax.pure_callback(host, shapes, phys.qpos, phys.qvel, phys.warm, mpos, mquat, active, grasp, *obj,
                                 vmap_method="expand_dims")
        qpos, qvel, warm, sens = (jax.lax.bitcast_convert_type(o, jnp.float64).astype(f) for o in outs)
        return _Phys(qpos, qvel, warm, None), sens
    from mujoco import mjx

    model = scenes.apply_mjx(static.mjx_model, lay, obj)

    def sub(d, mq):
        p, q = mq
        d1 = d.replace(mocap_pos=p[None].astype(d.mocap_pos.dtype), mocap_quat=q[None].astype(d.mocap_quat.dtype))
        d1 = mjx.step(model, d1)
        return jax.tree_util.tree_map(lambda a, b: jnp.where(active, a, b), d1, d), None

    with jax.numpy_rank_promotion("allow"):
        d, _ = jax.lax.scan(sub, phys.data, (mpos[1:], mquat[1:]))
        d = mjx.kinematics(model, d)
    sens = _sensors(d.xpos[lay.gripper], d.xquat[lay.gripper], d.xpos[lay.handle], d.xquat[lay.handle])
    return _Phys(d.qpos, d.qvel, d.qacc_warmstart, d), sens


# ----------------------------------------------------------------------------- the loop


class _Carry(NamedTuple):
    phys: _Phys
    sens: jax.Array  # (14,)
    q: jax.Array  # (n,) arm joints
    turbo: tacman.TurboState
    tac: tacman.TacManState
    X1: jaxlie.SE3  # in-hand pose at the start (reference of the markers)
    done: jax.Array  # () bool
    success: jax.Array
    slipped: jax.Array
    nonfinite: jax.Array
    steps_used: jax.Array  # () int32
    invalid: jax.Array  # () int32
    alpha_min: jax.Array
    key: jax.Array
    hold_k: jax.Array  # () int32 Eq. 27: interval of the stretched step now running (0: a new command)
    hold_qdot: jax.Array  # (n,) the unscaled joint velocity of the stretched step [rad/s]
    hold_alpha: jax.Array  # () its alpha


def _poses(sens):
    T_g = jaxlie.SE3(jnp.concatenate([sens[3:7], sens[0:3]]))
    T_h = jaxlie.SE3(jnp.concatenate([sens[10:14], sens[7:10]]))
    return T_g, T_h


def _arm_pose(arm, q) -> jaxlie.SE3:
    pos, R = arm.pose(q)
    return tacman.se3(pos, R)


def rollout(static: Static, p: RolloutParams) -> RolloutResult:
    """One closed-loop rollout of ``static.steps`` control steps (see the module docstring)."""
    arm, lay = static.arm, static.layout
    f = jnp.float64 if jax.config.jax_enable_x64 else jnp.float32  # type: ignore[attr-defined]
    dt = jnp.asarray(static.mj_model.opt.timestep * static.substeps, f)
    q0 = jnp.asarray(static.q0, f)
    ref = jnp.asarray(static.pads.ref, f)
    p1, R1 = jnp.asarray(lay.p1, f), jnp.asarray(lay.R1, f)
    G1 = tacman.se3(p1, R1)
    u0 = jnp.concatenate([jnp.stack([p.speed, 0.0, 0.0]).astype(f), jnp.zeros(3, f)])
    turbo_p = tacman.TurboParams(u0, dt, p.controller == Controller.TURBO_U0, p.lead_max, p.twist_tau)
    tac_p = tacman.TacManParams(p.speed, dt, p.dev_high, p.dev_low, p.recovery_gain, 2.0 * p.speed,
                                p.controller == Controller.TACMAN_REAIM)
    n = q0.shape[0]

    phys = _phys_init(static, p.obj)
    # C_1 and the Eq. 2 threshold from the reading at the grasp (its own key: the scan's noise stream is unchanged)
    eps, start, eps_ok = tactile.initial_contact(static.pads, jax.random.fold_in(jax.random.wrap_key_data(
        jnp.asarray(p.key)), 0x0C1), p.marker_noise, p.contact_eps, p.contact_points)
    eps = eps.astype(f)
    sens0 = jnp.concatenate([p1, jaxlie.SO3.from_matrix(R1).wxyz, p1, jaxlie.SO3.from_matrix(R1).wxyz])
    T_g0, T_h0 = _poses(sens0)
    zero_i = jnp.zeros((), jnp.int32)
    carry = _Carry(phys, sens0, q0, tacman.turbo_init(T_g0), tacman.tacman_init(T_g0, jnp.array([1.0, 0, 0], f)),
                   T_g0.inverse() @ T_h0, jnp.zeros((), bool), jnp.zeros((), bool), jnp.zeros((), bool),
                   jnp.zeros((), bool), zero_i, zero_i, jnp.ones((), f), jax.random.wrap_key_data(jnp.asarray(p.key)),
                   zero_i, jnp.zeros(n, f), jnp.ones((), f))
    keep = lambda new, a, b: jax.tree_util.tree_map(lambda x, y: jnp.where(new, x, y), a, b)

    def body(c: _Carry, _):
        T_s, T_h = _poses(c.sens)  # the gripper body carrying the sensor, and the handle (physics)
        X_rel = (T_s.inverse() @ T_h) @ c.X1.inverse()
        key, k_read = jax.random.split(c.key)
        cur, mask, _ = tactile.read(static.pads, X_rel, k_read, p.marker_noise, eps, start)
        T_g = _arm_pose(arm, c.q)  # the gripper pose where the step is applied: the arm's (tracker / encoders)
        reading = tacman.Reading(T_g, ref, cur, mask)
        turbo, u_turbo, (valid_t, _) = tacman.turbo_step(c.turbo, reading, turbo_p)
        lead, u_lead, _ = tacman.lead_step(c.turbo, reading, turbo_p)
        is_lead = p.controller == Controller.TURBO_LEAD
        turbo = keep(is_lead, lead, turbo)
        u_turbo = jnp.where(is_lead, u_lead, u_turbo)  # the validity flag is the same Kabsch's
        tac, u_tac, (valid_r, _) = tacman.tacman_step(c.tac, reading, tac_p)
        is_tac = (p.controller == Controller.TACMAN) | (p.controller == Controller.TACMAN_REAIM)
        u = jnp.where(is_tac, u_tac, u_turbo)
        valid = jnp.where(is_tac, valid_r, valid_t)
        R_g = T_g.rotation().as_matrix()
        V = jnp.concatenate([R_g @ u[:3], R_g @ u[3:]])  # world-frame [v, w]
        jinv = jnp.where(p.use_estimate, p.jinv_est, arm.true_inverse_jacobian(c.q))
        qdot_full = jinv @ V
        # Eq. 27: a new command only once the previous scaled step has run its dt / alpha
        new = c.hold_k == 0
        alpha_new = tacman.alpha_scale(qdot_full, p.qdot_max, p.beta)
        alpha = jnp.where(new, alpha_new, c.hold_alpha)
        qdot_u = jnp.where(new, qdot_full, c.hold_qdot)
        frac = tacman.stretch_fraction(alpha, c.hold_k.astype(f))
        more = tacman.stretch_fraction(alpha, (c.hold_k + 1).astype(f)) > 0
        hold_k = jnp.where(more & ~c.done, c.hold_k + 1, 0)
        turbo = keep(new, turbo, c.turbo)
        tac = keep(new, tac, c.tac)
        qdot = jnp.where(c.done, 0.0, alpha * frac * qdot_u)
        fracs = jnp.arange(0, static.substeps + 1, dtype=f) / static.substeps
        qs = c.q[None] + fracs[:, None] * (qdot * dt)[None]
        pm, Rm = jax.vmap(arm.pose)(qs)
        mquat = jaxlie.SO3.from_matrix(Rm).wxyz
        phys, sens = _phys_step(static, p.obj, c.phys, pm, mquat, ~c.done, p.grasp)
        finite = jnp.all(jnp.isfinite(sens)) & jnp.all(jnp.isfinite(phys.qpos))
        phys = jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), phys, c.phys)
        sens = jnp.where(finite, sens, c.sens)
        q = qs[-1]
        # truth after the step (noise-free): progress, in-hand deviation, slip
        T_s2, T_h2 = _poses(sens)
        X2 = (T_s2.inverse() @ T_h2) @ c.X1.inverse()
        dev = tacman.deviation(X2, ref, start)
        slip = (jnp.linalg.norm(X2.translation()) > p.slip) | (jnp.linalg.norm(X2.rotation().log()) > p.slip_rot)
        prog = scenes.progress(phys.qpos, lay, p.obj)
        succ = prog >= static.level
        live = ~c.done
        nonfinite = c.nonfinite | (live & ~finite)
        slipped = c.slipped | (live & slip)
        success = c.success | (live & succ & ~slip)
        done = c.done | success | slipped | nonfinite
        steps_used = c.steps_used + live.astype(jnp.int32)
        invalid = c.invalid + (live & new & ~valid).astype(jnp.int32)
        alpha_min = jnp.where(live, jnp.minimum(c.alpha_min, alpha), c.alpha_min)
        G1i = G1.inverse()
        T_g2 = tacman.se3(pm[-1], Rm[-1])
        gap = jnp.linalg.norm(T_h2.translation() - T_g2.translation())
        recovering = live & is_tac & tac.recovering
        rec = (G1i @ T_h2).translation(), (G1i @ T_g2).translation(), prog, dev, live, q, gap, recovering
        return _Carry(phys, sens, q, turbo, tac, c.X1, done, success, slipped, nonfinite, steps_used, invalid,
                      alpha_min, key, hold_k, qdot_u, alpha), rec

    c, (h_tr, g_tr, prog, dev, live, qs, gap, rec_tr) = jax.lax.scan(body, carry, None, length=static.steps)
    n_used = jnp.maximum(c.steps_used, 1)
    w = live.astype(f)
    prog_end = prog[jnp.clip(c.steps_used - 1, 0, static.steps - 1)]
    done_frac = jnp.minimum(prog_end, static.level) / static.level
    efficiency = 100.0 * done_frac / n_used
    efficiency_60hz = 100.0 * done_frac / (60.0 * n_used * dt)
    qall = jnp.concatenate([q0[None], qs])
    jerk_t = jnp.linalg.norm(jnp.diff(qall, n=3, axis=0), axis=-1) / dt**3  # (steps - 2,)
    jw = w[2:]
    jerk = jnp.sum(jw * jerk_t) / jnp.maximum(jnp.sum(jw), 1.0)
    jerk_tw = time_weighted_jerk(qall[:, 0], dt, c.steps_used)
    dev_mean = jnp.sum(w * dev) / jnp.maximum(jnp.sum(w), 1.0)
    dev_max = jnp.max(jnp.where(live, dev, 0.0))
    path_dev = jnp.sum(w * gap) / jnp.maximum(jnp.sum(w), 1.0)
    sl = slice(0, None, static.stride)
    return RolloutResult(c.success, c.slipped | c.nonfinite, c.slipped, c.nonfinite, c.steps_used, prog_end,
                         efficiency, efficiency_60hz, jerk, jerk_tw, path_dev, dev_mean, dev_max, c.invalid,
                         c.alpha_min, jnp.sum(rec_tr.astype(jnp.int32)), eps, jnp.sum(start.astype(jnp.int32)),
                         eps_ok, h_tr[sl], g_tr[sl], prog[sl], dev[sl],
                         rec_tr[sl], jnp.asarray(static.scene_id, jnp.int32))


def time_weighted_jerk(q, dt, n_used):
    """Time average of ``|d^3 q / dt^3|`` over the first ``n_used`` steps of a joint trajectory [s^-3, rad dropped].

    ``q (S + 1,)`` joint angles [rad] at ``t_k = k dt`` (``q[0]`` the start),
    ``dt`` [s], ``n_used`` () int the steps of the task. The third derivative
    is the backward difference ``(q_k - 3 q_{k-1} + 3 q_{k-2} - q_{k-3}) /
    dt^3`` at ``k = 1 .. n_used`` (the trajectory held at its start before
    ``t = 0``, so a start from rest counts), each sample weighted by its
    duration ``dt`` and the sum divided by the task time ``n_used dt``: the
    paper's time-weighted joint jerk (its Fig. 7, base joint) as we read it
    (the paper prints no formula).
    """
    qq = jnp.concatenate([jnp.full((2,), q[0]), q])  # at rest before t = 0
    j = jnp.abs(jnp.diff(qq, n=3)) / dt**3  # (S,) at t_1 .. t_S
    k = jnp.arange(1, j.shape[0] + 1)
    w = (k <= n_used).astype(j.dtype)
    return jnp.sum(w * j * dt) / jnp.maximum(n_used * dt, dt)
