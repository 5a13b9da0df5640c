"""Stewart Hand: a 6-6 Stewart platform holding the object; six leg lengths -> object (POM) pose.

The MJCF ``assets/stewart_hand.xml`` is the one source of truth (layout in its
header: base anchors on r_a = 0.05 m, object anchors on r_b = 0.035 m, home
height 0.05 m, home legs 0.0595 m, scaled condition number 2.21 at home).
Three backends evaluate the closed chain at leg lengths ``q (6,)`` (m):

* ``"kinematic"`` (default): Newton's method (:func:`~selfid_jax.math.linalg.newton_root`,
  float64) on ``|p + R b_i - a_i| - q_i = 0`` for the POM pose, started at
  home; derivatives by the implicit function theorem
  (:func:`~selfid_jax.math.linalg.implicit_root`: ``jax.jacfwd`` and
  ``jax.jacrev`` both work, and the program holds no host callback).
* ``"mjx"``: the MJCF stepped in MJX from home under ``ctrl = q`` until settled
  (:mod:`~selfid_jax.systems.hands.settle`); jit/vmap, forward-mode derivatives.
* ``"native"``: the same with ``mujoco.rollout`` on CPU threads through
  ``jax.pure_callback`` (jit/vmap, no derivatives; ``System.jacobian`` is not
  available); :func:`stewart_native_batch` is the plain NumPy batch function.

Every backend returns NaN for ``p`` and ``R`` where a leg is outside the slide
range ``[0.05, 0.07]`` m, the solve fails (Newton not converged / not settled)
or (kinematic) the pose left the home assembly branch: rotation angle above
``max_angle`` or the inverse Jacobian's determinant changed sign (a
singularity was crossed). Build and call under ``with jax.enable_x64(True):``.
"""

from __future__ import annotations

import dataclasses
import functools
from importlib import resources

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax.math import geometry
from selfid_jax.math.linalg import implicit_root, newton_root
from selfid_jax.systems.hands import settle
from selfid_jax.systems.system import System, make_system
from selfid_jax.systems.validation import Limits

__all__ = [
    "STEWART_HALF_WIDTH",
    "STEWART_SETTLE_STEPS",
    "STEWART_SETTLE_TOL",
    "STEWART_SITE",
    "STEWART_XML",
    "StewartKinematicPose",
    "StewartParams",
    "load_stewart_params",
    "stewart_hand",
    "stewart_home",
    "stewart_inverse_jacobian",
    "stewart_native_batch",
]

#: Path of the shipped MJCF.
STEWART_XML = str(resources.files("selfid_jax.systems") / "assets" / "stewart_hand.xml")
#: POM site name.
STEWART_SITE = "pom"
#: Half-width (m) of the default sampling box around the home leg lengths.
STEWART_HALF_WIDTH = 0.005
#: MJX/native settle budget (steps of 5 ms) and tolerance on the per-step qpos change (3 steps running).
#: Random commands in the sampling box settle in 140-185 steps at 1e-9 (native, 500 draws); MJX's
#: per-step qpos noise floor at rest is up to ~9e-10 (object yaw; native: ~1e-11), hence 5e-9.
STEWART_SETTLE_STEPS = 400
STEWART_SETTLE_TOL = 5e-9


@dataclasses.dataclass(frozen=True)
class StewartParams:
    """Kinematic parameters (a traced pytree; m, world frame at the base).

    ``a (6, 3)``: base anchors (ball-joint centres). ``b (6, 3)``: object anchors
    in the POM frame. ``p0 (3,)``, ``R0 (3, 3)``: home POM pose. ``q_low``,
    ``q_high (6,)``: slide ranges. ``det_sign``: sign of ``det`` of the inverse
    Jacobian at home (the assembly branch).
    """

    a: jax.Array
    b: jax.Array
    p0: jax.Array
    R0: jax.Array
    q_low: jax.Array
    q_high: jax.Array
    det_sign: jax.Array

    def replace(self, **changes) -> StewartParams:
        """``dataclasses.replace``."""
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(
    StewartParams, data_fields=[f.name for f in dataclasses.fields(StewartParams)], meta_fields=[]
)


@functools.lru_cache(maxsize=4)
def _mjmodel(path: str = STEWART_XML):
    import mujoco

    return mujoco.MjModel.from_xml_path(path)


def _arrays(mj):
    """NumPy ``a, b, p0, R0, q_low, q_high, home`` of the Stewart MJCF ``mj`` (read at ``qpos0``)."""
    import mujoco

    d = mujoco.MjData(mj)
    mujoco.mj_kinematics(mj, d)
    name = lambda t, n: mujoco.mj_name2id(mj, t, n)
    J = mujoco.mjtObj
    ball = [name(J.mjOBJ_JOINT, f"ball{i}") for i in range(6)]
    slide = [name(J.mjOBJ_JOINT, f"slide{i}") for i in range(6)]
    acts = [int(mj.actuator_trnid[i, 0]) for i in range(mj.nu)]
    if acts != slide:
        raise ValueError(f"Stewart MJCF: actuators must drive slide0..slide5 in order, got joints {acts}")
    pom = name(J.mjOBJ_SITE, STEWART_SITE)
    p0, R0 = d.site_xpos[pom].copy(), d.site_xmat[pom].reshape(3, 3).copy()
    a = d.xanchor[ball].copy()
    b_world = np.stack([d.site_xpos[name(J.mjOBJ_SITE, f"b{i}")] for i in range(6)])
    b = (b_world - p0) @ R0  # rows R0^T (b_w - p0)
    q_low, q_high = mj.jnt_range[slide, 0].copy(), mj.jnt_range[slide, 1].copy()
    home = mj.qpos0[mj.jnt_qposadr[slide]].copy()
    return a, b, p0, R0, q_low, q_high, home


def stewart_inverse_jacobian(params: StewartParams, p, R):
    """Closed-form inverse Jacobian at POM pose ``(p (3,), R (3, 3))``: ``(6, 6)``, row i ``[u_i, (R b_i) x u_i]``.

    ``u_i`` is the unit leg vector from base anchor ``a_i`` to the object
    anchor ``p + R b_i``; ``dq = Jinv @ [dp (m), omega (rad, world frame)]``.
    """
    rb = jnp.einsum("jk,ik->ij", R, params.b)  # (6, 3) rotated anchors
    leg = p[None, :] + rb - params.a
    u = leg / jnp.linalg.norm(leg, axis=1, keepdims=True)
    return jnp.concatenate([u, jnp.cross(rb, u)], axis=1)


def _pose(params, x):
    """POM pose ``(p, R)`` of the solve variable ``x = [p - p0, rotation vector of R R0^T]`` ``(6,)``."""
    return params.p0 + x[:3], geometry.so3_exp(x[3:]) @ params.R0


def _residual(x, args):
    params, q = args
    p, R = _pose(params, x)
    leg = p[None, :] + jnp.einsum("jk,ik->ij", R, params.b) - params.a
    return jnp.linalg.norm(leg, axis=1) - q


@dataclasses.dataclass(frozen=True)
class StewartKinematicPose:
    """Pose map ``(StewartParams, q (6,)) -> (p (3,), R (3, 3))`` by Newton's method on the leg constraints.

    :func:`~selfid_jax.math.linalg.newton_root` (``rtol``, ``atol``) from home, at most
    ``max_steps`` steps; NaN unless converged, every leg inside its range,
    the rotation from home at most ``max_angle`` rad and the inverse Jacobian's
    determinant of the home sign. Hashable by value.
    """

    rtol: float = 1e-10
    atol: float = 1e-12
    max_steps: int = 32
    max_angle: float = 1.0

    def solve(self, params, q):
        """``(x (6,), ok)``: the solve variable (see :func:`_pose`) and the validity flag."""
        q = jnp.asarray(q)
        dt = jnp.result_type(q, params.a)
        x0 = jnp.zeros(6, dt)
        args = (params, q.astype(dt))
        # newton_root passes no tangents: derivatives come from implicit_root (no host callback in the program)
        x, F_x, converged = newton_root(_residual, x0, args, rtol=self.rtol, atol=self.atol, max_steps=self.max_steps)
        x = implicit_root(_residual, x, args, F_x)
        p, R = _pose(params, x)
        det = jnp.linalg.det(stewart_inverse_jacobian(params, p, R))
        ok = (
            converged
            & jnp.all((q >= params.q_low) & (q <= params.q_high))
            & (jnp.linalg.norm(jax.lax.stop_gradient(x[3:])) <= self.max_angle)
            & (jnp.sign(jax.lax.stop_gradient(det)) == params.det_sign)
            & jnp.all(jnp.isfinite(x))
        )
        return x, ok

    def __call__(self, params, q):
        x, ok = self.solve(params, q)
        p, R = _pose(params, x)
        nan = jnp.asarray(jnp.nan, p.dtype)
        return jnp.where(ok, p, nan), jnp.where(ok, R, nan)


def load_stewart_params(path: str = STEWART_XML) -> StewartParams:
    """:class:`StewartParams` read from the MJCF at ``path``, in the default float dtype."""
    a, b, p0, R0, q_low, q_high, _ = _arrays(_mjmodel(path))
    fl = jnp.result_type(float)
    ja, jb, jp0, jR0, jlow, jhigh = (jnp.asarray(v, fl) for v in (a, b, p0, R0, q_low, q_high))
    prm = StewartParams(ja, jb, jp0, jR0, jlow, jhigh, det_sign=jnp.asarray(1.0, fl))
    det = jnp.linalg.det(stewart_inverse_jacobian(prm, prm.p0, prm.R0))
    return prm.replace(det_sign=jnp.sign(det))


def stewart_native_batch(q, *, path: str = STEWART_XML, max_steps: int = STEWART_SETTLE_STEPS,
                         tol: float = STEWART_SETTLE_TOL, nthread: int | None = None):
    """Native-MuJoCo settled POM poses for a batch of leg lengths: ``(p (B, 3), R (B, 3, 3), settled (B,))``.

    ``q (B, 6)`` (m), NumPy float64; ``mujoco.rollout`` on ``nthread`` CPU
    threads from home. NaN poses (and ``settled`` False) where unsettled or a
    leg is outside ``[0.05, 0.07]`` m. Not traceable.
    """
    mj = _mjmodel(path)
    _, _, _, _, q_low, q_high, _ = _arrays(mj)
    return settle.native_pose_batch(mj, STEWART_SITE, q, q_low=q_low, q_high=q_high, max_steps=max_steps, tol=tol,
                                    nthread=nthread)


def stewart_hand(
    *,
    backend: str = "kinematic",
    task_dim: int = 6,
    m_a=0.0005,
    dq_max: float = 0.002,
    half_width: float = STEWART_HALF_WIDTH,
    sample_low=None,
    sample_high=None,
    min_sigma: float = 0.1,
    max_steps: int = STEWART_SETTLE_STEPS,
    tol: float = STEWART_SETTLE_TOL,
    path: str = STEWART_XML,
) -> System:
    """Stewart Hand as a :class:`System`: 6 leg lengths (m) -> POM pose on the object.

    Args:
      backend: ``"kinematic"`` (Newton + implicit function theorem, default),
        ``"mjx"`` (MJX settling, float64) or ``"native"`` (``mujoco.rollout``
        through ``jax.pure_callback``; no derivatives, so ``System.jacobian``
        and ``sample_configs`` do not work on it).
      task_dim: 6 (position + world rotation vector, default), 3 or 2.
      m_a: safe self-ID magnitude (m), scalar or ``(6,)``.
      dq_max: per-step leg change limit (m).
      half_width: sampling box ``home +- half_width`` (m), clipped to the slides.
      sample_low, sample_high: explicit ``(6,)`` sampling box (m), replaces the default.
      min_sigma: ``sample_configs`` threshold on the Jacobian's smallest singular value.
      max_steps, tol: settle budget (steps) and tolerance (qpos change per step), mjx/native.
      path: MJCF file.

    Raises:
      ValueError: an unknown backend, or float64 off (``jax.enable_x64(True)`` not in effect).

    Returns:
      A :class:`System` (``q_low``/``q_high`` = slide ranges 0.05/0.07 m); ``params`` is a
      :class:`StewartParams` (kinematic), a :class:`~selfid_jax.systems.hands.settle.SettleParams`
      (mjx) or ``(q_low, q_high)`` (native).
    """
    fl = jnp.result_type(float)
    if fl != jnp.float64:
        raise ValueError("stewart_hand needs float64: build and call it under `with jax.enable_x64(True):`")
    mj = _mjmodel(path)
    _, _, _, _, q_low, q_high, home = _arrays(mj)
    params: StewartParams | settle.SettleParams | tuple[jax.Array, jax.Array]
    pose_fn: StewartKinematicPose | settle.MjxSettlePose | settle.NativeSettlePose
    if backend == "kinematic":
        params, pose_fn = load_stewart_params(path), StewartKinematicPose()
    elif backend == "mjx":
        sid = int(mj.site(STEWART_SITE).id)
        params = settle.SettleParams(settle.mjx_model(mj), jnp.asarray(q_low, fl), jnp.asarray(q_high, fl))
        pose_fn = settle.MjxSettlePose(sid, int(max_steps), float(tol))
    elif backend == "native":
        params = (jnp.asarray(q_low, fl), jnp.asarray(q_high, fl))
        pose_fn = settle.NativeSettlePose(mj, int(mj.site(STEWART_SITE).id), int(max_steps), float(tol))
    else:
        raise ValueError(f"backend must be 'kinematic', 'mjx' or 'native', got {backend!r}")
    if sample_low is None:
        sample_low = np.maximum(q_low, home - half_width)
    if sample_high is None:
        sample_high = np.minimum(q_high, home + half_width)
    return make_system(
        name=f"stewart_hand_{backend}" if backend != "kinematic" else "stewart_hand",
        params=params,
        pose_fn=pose_fn,
        has_rotation=True,
        limits=Limits(6, task_dim, q_low, q_high, dq_max, m_a, sample_low, sample_high, min_sigma),
    )


def stewart_home(path: str = STEWART_XML) -> np.ndarray:
    """Home leg lengths ``(6,)`` (m) of the MJCF."""
    return _arrays(_mjmodel(path))[-1]
