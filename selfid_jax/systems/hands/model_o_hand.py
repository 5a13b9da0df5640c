"""Yale Model O holding an object: three tendon commands -> POM pose, the equilibrium of a closed chain.

``assets/model_o.xml`` is the one source of truth (dimensions in its header):
three planar two-joint fingers with joint springs, one fixed tendon and one
position servo (kp 500 N/m) per finger, a 40 mm cylinder held by three
``connect`` point contacts, the POM 30 mm above the object's centre, gravity
off. ``q (3,)``: the servo commands (tendon lengths, m).

``"kinematic"`` backend: the hand rests where ``U = sum k/2 (theta -
theta_ref)^2 + sum_f kp/2 (q_f - a . theta_f)^2`` (joint springs plus servos on
the tendon lengths ``a . theta_f = 0.012 theta_prox + 0.008 theta_dist``) is
stationary subject to the contacts ``tip_f(theta_f) = c + R s_f``. With
multipliers ``lambda_f`` (finger ``f``'s force on the object), 21 equations in
21 unknowns (joint angles, object position and rotation vector, multipliers),
solved by Newton's method in float64: ``grad U + J_tip^T lambda = 0`` (6),
``sum lambda_f = 0`` and ``sum (R s_f) x lambda_f = 0`` (the object's balance,
6), ``tip_f - c - R s_f = 0`` (9). That is MuJoCo's static equilibrium of the
MJCF (servo force ``kp (ctrl - L)``, springs, equality forces), so settled
poses differ by the soft constraints' give only (<= 7e-8 m in the safe box).
6 joints + 6 object coordinates - 9 contact equations leave 3 DOF (lift and
two tilts of the object) for 3 servos: each finger's internal DOF (2 joints, 1
tendon) is closed by the object, and the springs set the squeeze and, through
the servos' compliance, the pose. Jacobians: implicit function theorem.

Guard: NaN pose where Newton does not converge, ``q`` leaves the safe box
``q_home + [-8, +5] mm`` (the System's actuator limits), the object tilts more
than 15 deg, or the equilibrium is not a stable minimum of ``U`` on the
contacts. Beyond, the branch folds and the object rolls over (in MuJoCo too):
pulling one tendon by 6.25 mm (20 deg of tilt), one by 5.75 mm while releasing
another as much (21 deg), two by 8.25 mm (15 deg) or all three by 10.75 mm;
released tendons keep the grasp to 20 mm. ``"mjx"``/``"native"``: the MJCF
settled from its ``grasp`` keyframe (:mod:`~selfid_jax.systems.hands.settle`),
same guard but for the stability test. Build and call them all under
``with jax.enable_x64(True):``.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from importlib import resources
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.math import geometry
from selfid_jax.math.kernels import small_matmul, small_sum
from selfid_jax.math.linalg import implicit_root, jacfwd_with_value, newton_root
from selfid_jax.systems.hands import settle
from selfid_jax.systems.system import System, make_system
from selfid_jax.systems.validation import Limits

__all__ = [
    "MODEL_O_MAX_TILT", "MODEL_O_SAFE_RANGE", "MODEL_O_SETTLE_STEPS", "MODEL_O_SETTLE_TOL", "MODEL_O_SITE",
    "MODEL_O_XML", "ModelOKinematicPose", "ModelOParams", "TiltGuardedPose",
    "load_model_o_params", "model_o", "model_o_home", "model_o_keyframe", "model_o_mjmodel", "tilt_angle",
]

#: Path of the shipped MJCF.
MODEL_O_XML = str(resources.files("selfid_jax.systems") / "assets" / "model_o.xml")
#: POM site name.
MODEL_O_SITE = "pom"
#: Safe command box (m) about the grasp command, ``(low, high)`` offsets (the System's actuator limits).
MODEL_O_SAFE_RANGE = (-0.008, 0.005)
#: Largest object tilt (rad) of the main branch: 15 deg.
MODEL_O_MAX_TILT = float(np.radians(15.0))
#: MJX/native settle budget (steps of 2 ms; 150-500 used) and tolerance on the per-step qpos change.
MODEL_O_SETTLE_STEPS = 1000
MODEL_O_SETTLE_TOL = 1e-10

_ELL = 0.01  # length scale (m) of the Newton unknowns and equations: positions in cm, torques in N cm


class ModelOParams(NamedTuple):
    """The MJCF's geometry and elastic constants plus the grasp solution (a traced pytree; m, rad, N, world frame).

    Per finger (rows): proximal hinge frame ``base_pos (3, 3)``, ``base_rot (3, 3, 3)``, its axis
    ``axis1 (3, 3)`` (local); distal frame in the proximal one ``dist_pos``, ``dist_rot``, axis
    ``axis2``; fingertip site ``tip (3, 3)`` in the distal frame. Object: contact sites
    ``contact (3, 3)``, POM site ``pom (3,)``, ``pom_rot (3, 3)`` (object frame); grasp pose
    ``c0 (3,)``, ``R0 (3, 3)``. ``stiffness``, ``springref``, ``coef (3, 2)``: joint springs
    (N m/rad, rad), tendon coefficients (m/rad); ``kp (3,)`` servo gains (N/m). ``q_home (3,)``
    grasp command (m), ``y_home (21,)`` its solution, ``dy_dq (21, 3)`` its derivative (Newton
    starts at ``y_home + dy_dq (q - q_home)``). Guards: ``safe_low``, ``safe_high (3,)`` (m), ``max_tilt ()`` (rad).
    """

    base_pos: jax.Array
    base_rot: jax.Array
    axis1: jax.Array
    dist_pos: jax.Array
    dist_rot: jax.Array
    axis2: jax.Array
    tip: jax.Array
    contact: jax.Array
    pom: jax.Array
    pom_rot: jax.Array
    c0: jax.Array
    R0: jax.Array
    stiffness: jax.Array
    springref: jax.Array
    coef: jax.Array
    kp: jax.Array
    q_home: jax.Array
    y_home: jax.Array
    dy_dq: jax.Array
    safe_low: jax.Array
    safe_high: jax.Array
    max_tilt: jax.Array


# ------------------------------------------------------------------ equations
def _finger(P, theta):
    """Fingertips ``(3, 3)``, hinge positions ``(3, 2, 3)`` and world hinge axes ``(3, 2, 3)`` at ``theta (3, 2)``."""
    B1 = small_matmul(P.base_rot, geometry.so3_exp(P.axis1 * theta[:, :1]))
    B1d = small_matmul(B1, P.dist_rot)
    B2 = small_matmul(B1d, geometry.so3_exp(P.axis2 * theta[:, 1:]))
    j2 = P.base_pos + _mv(B1, P.dist_pos)
    tip = j2 + _mv(B2, P.tip)
    w1 = _mv(P.base_rot, P.axis1)
    w2 = _mv(B1d, P.axis2)
    return tip, jnp.stack([P.base_pos, j2], 1), jnp.stack([w1, w2], 1)


def _mv(A, x):
    """``A (..., i, j) @ x (..., j)`` by unrolled multiply-adds (these 3x3 products fuse; as dots each is a kernel)."""
    return small_matmul(A, x[..., :, None])[..., 0]


def _unpack(P, y):
    """``theta (3, 2)``, object centre ``c (3,)`` (m), rotation ``R (3, 3)``, multipliers ``lam (3, 3)`` (N)."""
    return (y[:6].reshape(3, 2), P.c0 + _ELL * y[6:9], small_matmul(geometry.so3_exp(y[9:12]), P.R0),
            y[12:].reshape(3, 3))


def _residual(y, args):
    """The 21 equilibrium equations of the module docstring (cm, N cm, N), ``y (21,)`` -> ``(21,)``."""
    P, q = args
    theta, c, R, lam = _unpack(P, y)
    tip, joints, axes = _finger(P, theta)
    spring = P.stiffness * (theta - P.springref) - (P.kp * (q - small_sum(P.coef * theta, 1)))[:, None] * P.coef
    contact = small_sum(jnp.cross(axes, tip[:, None, :] - joints) * lam[:, None, :], -1)  # J_tip^T lambda
    arm = _mv(R[None], P.contact)
    return jnp.concatenate([((spring + contact) / _ELL).ravel(), small_sum(lam, 0),
                            small_sum(jnp.cross(arm, lam), 0) / _ELL, ((tip - c[None, :] - arm) / _ELL).ravel()])


def _pose(P, y):
    """POM pose ``(p (3,), R (3, 3))`` of the unknowns ``y (21,)``."""
    _, c, R, _ = _unpack(P, y)
    return c + R @ P.pom, R @ P.pom_rot


def _vee_columns(dR, R):
    """``(3, k)`` angular velocities ``vee(dR_i R^T)`` of ``k`` rotation derivatives ``dR (k, 3, 3)``."""
    W = jnp.einsum("kij,lj->kil", dR, R)
    return jnp.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=0)


def _stable(y, F_y):
    """Whether ``y`` is a strict minimum of ``U`` on the contacts: the KKT matrix has 9 negative eigenvalues.

    At a KKT point the Newton Jacobian ``F_y`` is the Lagrangian's Hessian
    ``K`` with scaled rows and columns, the torque rows through the rotation
    vector's Jacobian ``J_l`` (``omega = J_l dphi``); ``K`` is recovered and its
    inertia (12 positive, 9 negative: positive-definite reduced Hessian) checked.
    """
    eye = jnp.eye(3, dtype=y.dtype)
    R, dR = jax.vmap(lambda t: jax.jvp(geometry.so3_exp, (y[9:12],), (t,)), out_axes=(None, 0))(eye)
    Jl = _vee_columns(dR, R)
    K = jnp.concatenate([_ELL * F_y[:6], -F_y[6:9], -_ELL * Jl.T @ F_y[9:12], _ELL * F_y[12:]])
    K = K.at[:, 6:9].divide(_ELL)
    return jnp.sum(jnp.linalg.eigvalsh(0.5 * (K + K.T)) < 0) == 9


def tilt_angle(R):
    """Angle (rad) between the POM frame's z axis (the object's axis) and the world z axis: ``R (3, 3)`` -> ``()``."""
    return jnp.arctan2(jnp.sqrt(R[0, 2] ** 2 + R[1, 2] ** 2), R[2, 2])


# ------------------------------------------------------------------ the kinematic pose map
@dataclasses.dataclass(frozen=True)
class ModelOKinematicPose:
    """Pose map ``(ModelOParams, q (3,)) -> (p (3,), R (3, 3))``: the POM at the grasp equilibrium (Newton, float64).

    :func:`~selfid_jax.math.linalg.newton_root` (``rtol``, ``atol``; unknowns in rad, cm, N) from the
    predicted grasp solution, at most ``max_steps``
    steps; NaN unless converged, ``q`` in the safe box, tilt at most
    ``max_tilt`` and (``check_stability``) the equilibrium stable. ``jacobian``
    and ``pose_and_jacobian`` give the world-frame ``(6, 3)`` Jacobian (rows
    ``dp`` in m/m, then ``omega`` in rad/m) by the implicit function theorem.
    Hashable by value.
    """

    rtol: float = 1e-12
    atol: float = 1e-12
    max_steps: int = 30
    check_stability: bool = True

    def solve(self, params, q):
        """``(y (21,), F_y (21, 21), ok ())``: unknowns, the equations' Jacobian there, the validity flag."""
        P = params
        q = jnp.asarray(q, P.q_home.dtype)
        # newton_root passes no tangents: derivatives come from implicit_root (no host callback in the program)
        y0 = P.y_home + P.dy_dq @ (q - P.q_home)
        ys, F_y, ok = newton_root(_residual, y0, (P, q), rtol=self.rtol, atol=self.atol, max_steps=self.max_steps)
        ok = ok & jnp.all((q >= P.safe_low) & (q <= P.safe_high)) & (tilt_angle(_pose(P, ys)[1]) <= P.max_tilt)
        if self.check_stability:
            ok = ok & _stable(ys, F_y)
        return implicit_root(_residual, ys, (P, q), F_y), F_y, ok

    def __call__(self, params, q):
        y, _, ok = self.solve(params, q)
        p, R = _pose(params, y)
        nan = jnp.asarray(jnp.nan, p.dtype)
        return jnp.where(ok, p, nan), jnp.where(ok, R, nan)

    def pose_and_jacobian(self, params, q):
        """``((p (3,), R (3, 3)), J (6, 3))`` from one solve; ``J = [dp/dq; omega/dq]``, NaN where invalid."""
        P = params
        q = jnp.asarray(q, P.q_home.dtype)
        y, F_y, ok = self.solve(P, q)
        y = jax.lax.stop_gradient(y)
        F_q = jax.jacfwd(lambda q_: _residual(y, (P, q_)))(q)
        dy = -jnp.linalg.solve(F_y, F_q)  # (21, 3)
        (p, R), (dp, dR) = jax.vmap(lambda t: jax.jvp(lambda y_: _pose(P, y_), (y,), (t,)), in_axes=1,
                                    out_axes=(None, 0))(dy)
        J = jnp.concatenate([dp.T, _vee_columns(dR, R)], axis=0)
        nan = jnp.asarray(jnp.nan, p.dtype)
        return (jnp.where(ok, p, nan), jnp.where(ok, R, nan)), jnp.where(ok, J, nan)

    def jacobian(self, params, q):
        """World-frame ``(6, 3)`` Jacobian of the POM pose at ``q`` (rows ``dp`` then ``omega``); NaN where invalid."""
        return self.pose_and_jacobian(params, q)[1]


# ------------------------------------------------------------------ reading the MJCF
@functools.lru_cache(maxsize=4)
def model_o_mjmodel(path: str = MODEL_O_XML):
    """The ``mujoco.MjModel`` of ``path`` (cached: treat it as read-only)."""
    import mujoco

    mj = mujoco.MjModel.from_xml_path(path)
    if mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_KEY, "grasp") < 0:
        raise ValueError(f"Model O MJCF {path}: no keyframe 'grasp'")
    return mj


def model_o_keyframe(path: str = MODEL_O_XML):
    """``(qpos (nq,), ctrl (nu,))`` of the ``grasp`` keyframe: the settle start and the grasp command."""
    mj = model_o_mjmodel(path)
    k = mj.key("grasp").id
    return mj.key_qpos[k].copy(), mj.key_ctrl[k].copy()


def model_o_home(path: str = MODEL_O_XML) -> np.ndarray:
    """Grasp command ``(3,)`` (m): the ``ctrl`` of the MJCF's ``grasp`` keyframe."""
    return model_o_keyframe(path)[1]


def _mat(quat):
    import mujoco

    m = np.zeros(9)
    mujoco.mju_quat2Mat(m, np.asarray(quat, np.float64))
    return m.reshape(3, 3)


def _arrays(mj, qpos):
    """NumPy :class:`ModelOParams` fields and the grasp joints ``theta0`` of ``mj`` at ``qpos``."""
    import mujoco

    d = mujoco.MjData(mj)
    d.qpos[:] = qpos
    mujoco.mj_kinematics(mj, d)
    prox = [mj.body(f"f{f}_prox").id for f in range(3)]
    dist = [mj.body(f"f{f}_dist").id for f in range(3)]
    jid = np.array([[mj.body_jntadr[b] for b in pair] for pair in zip(prox, dist)])
    if (any(mj.body_parentid[b] != 0 for b in prox) or np.any(mj.jnt_type[jid] != mujoco.mjtJoint.mjJNT_HINGE)
            or np.any(mj.jnt_pos[jid] != 0) or np.any(mj.qpos0[mj.jnt_qposadr[jid]] != 0)):
        raise ValueError("Model O MJCF: fingers must be world-attached chains of two hinges at body origins, ref 0")
    coef = np.zeros((3, 2))
    for f in range(3):
        t = int(mj.actuator_trnid[f, 0])
        for w in range(mj.tendon_adr[t], mj.tendon_adr[t] + mj.tendon_num[t]):
            i, j = np.argwhere(jid == mj.wrap_objid[w])[0]
            if i != f:
                raise ValueError(f"Model O MJCF: actuator {f}'s tendon moves another finger's joint")
            coef[i, j] = mj.wrap_prm[w]
    kp = mj.actuator_gainprm[:3, 0].copy()
    if not (np.allclose(mj.actuator_biasprm[:3, 1], -kp) and np.all(mj.actuator_biasprm[:3, [0, 2]] == 0)):
        raise ValueError("Model O MJCF: actuators must be position servos without damping (kv 0)")
    site = lambda n: mj.site(n).id
    obj, pom = mj.body("object").id, site(MODEL_O_SITE)
    return {
        "base_pos": mj.body_pos[prox], "base_rot": np.stack([_mat(mj.body_quat[b]) for b in prox]),
        "axis1": mj.jnt_axis[jid[:, 0]], "dist_pos": mj.body_pos[dist],
        "dist_rot": np.stack([_mat(mj.body_quat[b]) for b in dist]), "axis2": mj.jnt_axis[jid[:, 1]],
        "tip": np.stack([mj.site_pos[site(f"f{f}_tip")] for f in range(3)]),
        "contact": np.stack([mj.site_pos[site(f"c{f}")] for f in range(3)]),
        "pom": mj.site_pos[pom], "pom_rot": _mat(mj.site_quat[pom]), "c0": d.xpos[obj], "R0": d.xmat[obj].reshape(3, 3),
        "stiffness": mj.jnt_stiffness[jid], "springref": mj.qpos_spring[mj.jnt_qposadr[jid]], "coef": coef, "kp": kp,
        "theta0": qpos[mj.jnt_qposadr[jid]],
    }


def _offsets(safe_range):
    """``(low (3,), high (3,))`` offsets of ``safe_range``; ``low < 0 < high`` required."""
    try:
        lo, hi = (np.broadcast_to(np.asarray(v, np.float64), (3,)) for v in safe_range)
    except (TypeError, ValueError):
        raise ValueError(f"safe_range must be (low, high), each a scalar or (3,), got {safe_range!r}") from None
    if not (np.all(lo < 0) and np.all(hi > 0)):
        raise ValueError(f"safe_range must have low < 0 < high (offsets from the grasp command), got {safe_range!r}")
    return lo, hi


def _check_x64():
    if jnp.result_type(float) != jnp.float64:
        raise ValueError("the Model O runs in float64: build and call it under `with jax.enable_x64(True):`")


def load_model_o_params(path: str = MODEL_O_XML, *, safe_range=MODEL_O_SAFE_RANGE,
                        max_tilt=MODEL_O_MAX_TILT) -> ModelOParams:
    """:class:`ModelOParams` of the MJCF at ``path``, its grasp equilibrium solved at the keyframe command (float64).

    ``safe_range``: ``(low, high)`` offsets (m, each a scalar or ``(3,)``) of
    the safe command box from the grasp command; ``max_tilt``: largest tilt (rad).
    """
    _check_x64()
    qpos, q_home = model_o_keyframe(path)
    a = _arrays(model_o_mjmodel(path), qpos)
    theta0 = a.pop("theta0")
    lo, hi = _offsets(safe_range)
    f = jnp.float64
    P = ModelOParams(**{k: jnp.asarray(v, f) for k, v in a.items()}, q_home=jnp.asarray(q_home, f),
                     y_home=jnp.zeros(21, f), dy_dq=jnp.zeros((21, 3), f), safe_low=jnp.asarray(q_home + lo, f),
                     safe_high=jnp.asarray(q_home + hi, f), max_tilt=jnp.asarray(max_tilt, f))
    y, ok, dy_dq = _grasp_solution(P, jnp.asarray(theta0, f))
    if not bool(ok):
        raise ValueError(f"Model O MJCF {path}: no stable grasp equilibrium near the 'grasp' keyframe")
    return P._replace(y_home=y, dy_dq=dy_dq)


@jax.jit
def _grasp_solution(P, theta0):
    """Unknowns ``(21,)`` at ``P.q_home`` from the keyframe joints ``theta0 (3, 2)``, an ok flag, ``dy/dq (21, 3)``."""
    q = P.q_home
    y = jnp.concatenate([theta0.ravel(), jnp.zeros(15, theta0.dtype)])  # object at its keyframe pose (no forces)
    # each residual evaluation is compiled again: value and derivative come from one jacfwd each
    A, r0 = jacfwd_with_value(lambda lam: _residual(y.at[12:].set(lam), (P, q))[:12])(jnp.zeros(9, y.dtype))
    y = y.at[12:].set(jnp.linalg.lstsq(A, -r0)[0])  # multipliers: least-squares balance
    y, F_y, ok = newton_root(_residual, y, (P, q), rtol=1e-13, atol=1e-13, max_steps=50)
    F_q, r = jacfwd_with_value(lambda q_: _residual(y, (P, q_)))(q)
    ok = ok & (jnp.max(jnp.abs(r)) < 1e-9) & _stable(y, F_y)
    return y, ok, -jnp.linalg.solve(F_y, F_q)


# ------------------------------------------------------------------ settled backends
@dataclasses.dataclass(frozen=True)
class TiltGuardedPose:
    """Pose map ``((inner_params, max_tilt), q) -> (p, R)``: ``inner``'s pose, NaN beyond ``max_tilt`` (rad).

    ``inner`` is a :class:`~selfid_jax.systems.hands.settle.MjxSettlePose` or
    ``NativeSettlePose`` started from the grasp keyframe; it already gives NaN
    where unsettled or outside the safe box.
    """

    inner: Callable[[Any, jax.Array], tuple[jax.Array, jax.Array]]

    def __call__(self, params, q):
        inner_params, max_tilt = params
        p, R = self.inner(inner_params, q)
        ok = tilt_angle(jax.lax.stop_gradient(R)) <= max_tilt  # False for NaN
        nan = jnp.asarray(jnp.nan, p.dtype)
        return jnp.where(ok, p, nan), jnp.where(ok, R, nan)


# ------------------------------------------------------------------ the System
def model_o(*, backend: str = "kinematic", task_dim: int = 3, m_a=0.0003, dq_max: float = 0.001,
            half_width: float = 0.001, sample_low=None, sample_high=None, min_sigma: float = 0.1,
            safe_range=MODEL_O_SAFE_RANGE, max_tilt: float = MODEL_O_MAX_TILT,
            check_stability: bool = True, max_steps: int = MODEL_O_SETTLE_STEPS, tol: float = MODEL_O_SETTLE_TOL,
            path: str = MODEL_O_XML) -> System:
    """Yale Model O holding a 40 mm object as a :class:`System`: 3 tendon commands (m) -> POM pose on the object.

    Args:
      backend: ``"kinematic"`` (Newton on the equilibrium equations, implicit
        function theorem derivatives; default), ``"mjx"`` (MJX settling,
        float64, forward-mode derivatives) or ``"native"`` (``mujoco.rollout``
        through ``jax.pure_callback``; no derivatives, so ``System.jacobian``
        and ``sample_configs`` do not work on it).
      task_dim: 3 (POM position, default), 2 (x, y) or 6 (position + rotation
        vector: accepted, but the grasp has 3 DOF, so the 6-D Jacobian has
        rank 3 and 6-D targets are met in least squares only).
      m_a: safe self-ID magnitude (m of tendon command), scalar or ``(3,)``.
      dq_max: per-step command change limit (m).
      half_width: sampling box ``grasp +- half_width`` (m), unless ``sample_low``/``sample_high`` ``(3,)`` are given.
      min_sigma: ``sample_configs`` threshold on the Jacobian's smallest singular value (m/m).
      safe_range: ``(low, high)`` offsets (m) of the safe box from the grasp command: the actuator limits;
        outside it poses are NaN.
      max_tilt: object tilt (rad) beyond which poses are NaN.
      check_stability: kinematic: NaN where the equilibrium is not stable.
      max_steps, tol: mjx/native settle budget (steps of 2 ms) and tolerance (qpos change per step).
      path: MJCF file.

    Returns:
      A :class:`System` whose ``params`` is a :class:`ModelOParams` (kinematic)
      or ``(settle params, max_tilt)`` (:class:`TiltGuardedPose`).
    """
    _check_x64()
    if backend not in ("kinematic", "mjx", "native"):
        raise ValueError(f"backend must be 'kinematic', 'mjx' or 'native', got {backend!r}")
    qpos0, home = model_o_keyframe(path)
    lo, hi = _offsets(safe_range)
    q_low, q_high = home + lo, home + hi
    params: ModelOParams | tuple[settle.SettleParams | tuple[jax.Array, jax.Array], jax.Array]
    pose_fn: ModelOKinematicPose | TiltGuardedPose
    if backend == "kinematic":
        params = load_model_o_params(path, safe_range=(lo, hi), max_tilt=max_tilt)
        pose_fn = ModelOKinematicPose(check_stability=bool(check_stability))
    else:
        mj = model_o_mjmodel(path)
        sid, f = int(mj.site(MODEL_O_SITE).id), jnp.float64
        lo, hi = jnp.asarray(q_low, f), jnp.asarray(q_high, f)
        inner_params: settle.SettleParams | tuple[jax.Array, jax.Array]
        inner: settle.MjxSettlePose | settle.NativeSettlePose
        if backend == "mjx":
            inner_params = settle.SettleParams(settle.mjx_model(mj), lo, hi, jnp.asarray(qpos0, f))
            inner = settle.MjxSettlePose(sid, int(max_steps), float(tol))
        else:
            inner_params, inner = (lo, hi), settle.NativeSettlePose(mj, sid, int(max_steps), float(tol), qpos0=qpos0)
        params, pose_fn = (inner_params, jnp.asarray(max_tilt, f)), TiltGuardedPose(inner)
    return make_system(
        name="model_o" if backend == "kinematic" else f"model_o_{backend}", params=params, pose_fn=pose_fn,
        has_rotation=True,
        limits=Limits(3, task_dim, q_low, q_high, dq_max, m_a,
                      np.maximum(q_low, home - half_width) if sample_low is None else sample_low,
                      np.minimum(q_high, home + half_width) if sample_high is None else sample_high, min_sigma),
    )
