"""The ``System`` pytree: a kinematic robot seen through its actuators and a POM pose.

A :class:`System` bundles a pose map ``pose_fn(params, q) -> (p, R)`` from
actuator positions ``q`` (``(n_act,)``, rad or m) to the pose of the point of
manipulation (POM), the actuator limits, a safe self-ID magnitude and a box of
configurations to sample from. It is a frozen dataclass registered as a JAX
pytree in the MJX manner (``mujoco/mjx/_src/types.py``):

* traced (data) fields: ``params`` (any pytree, e.g. link lengths or an
  ``mjx.Model``), ``q_low``, ``q_high``, ``dq_max``, ``m_a``, ``sample_low``,
  ``sample_high``. A sweep can ``vmap`` over any of them and a ``System`` can
  be passed to ``jax.jit`` as an ordinary argument.
* static (meta) fields: ``name``, ``n_act``, ``task_dim``, ``pose_fn``,
  ``min_sigma``, ``has_rotation``. Changing one recompiles; ``pose_fn`` is
  hashed by identity (module-level pose functions and the frozen-dataclass
  callables below hash by value, so rebuilding a system does not recompile).

Build one with :func:`from_pose_fn` (a pure JAX pose function) or
:func:`from_mjcf` (an MJCF file and a site name, forward kinematics by
``mjx.kinematics`` or by an equivalent plain-JAX joint chain read from the
same ``mjx.Model``).

Dtypes: array fields take the default float dtype at construction time
(float64 only if ``jax_enable_x64`` is on *when the system is built*); build
systems after enabling x64 where precision matters.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import os
from typing import Any, Callable

import jax
import jax.numpy as jnp
import numpy as np

from selfid_jax import geometry

__all__ = ["System", "from_pose_fn", "from_mjcf", "MjxSitePose", "ChainSitePose", "PositionOnlyPose"]

TASK_DIMS = (2, 3, 6)


@dataclasses.dataclass(frozen=True)
class System:
    """A kinematic system: actuator positions -> POM pose, with limits.

    Shapes: ``n = n_act`` actuators, ``m = task_dim`` task dimensions
    (2: planar xy position, 3: position, 6: position + world-frame rotation
    vector). Units: actuator positions in rad (hinge) or m (slide); positions
    in the system's length unit (m for the shipped systems); rotations in rad.

    Attributes (traced):
      params: pytree passed to ``pose_fn`` (link lengths, an ``mjx.Model``...).
      q_low, q_high: ``(n,)`` joint limits (may be +-inf).
      dq_max: ``(n,)`` largest actuator change per step (``apply`` clips to it).
      m_a: scalar safe self-ID magnitude (per-actuator random step size).
      sample_low, sample_high: ``(n,)`` box that ``sample_configs`` draws from.

    Attributes (static):
      name: label.
      n_act: number of actuators ``n``.
      task_dim: ``m`` in ``{2, 3, 6}``.
      pose_fn: ``pose_fn(params, q (n,)) -> (p (3,), R (3, 3))``.
      min_sigma: ``sample_configs`` keeps configurations whose Jacobian's
        smallest singular value exceeds this (task units per actuator unit).
      has_rotation: False if ``pose_fn`` only knows positions (``R`` is the
        identity); then ``task_dim`` must not be 6.
    """

    params: Any
    q_low: jax.Array
    q_high: jax.Array
    dq_max: jax.Array
    m_a: jax.Array
    sample_low: jax.Array
    sample_high: jax.Array
    name: str = dataclasses.field(default="system", metadata=dict(static=True))
    n_act: int = dataclasses.field(default=0, metadata=dict(static=True))
    task_dim: int = dataclasses.field(default=3, metadata=dict(static=True))
    pose_fn: Callable[[Any, jax.Array], tuple[jax.Array, jax.Array]] | None = dataclasses.field(
        default=None, metadata=dict(static=True)
    )
    min_sigma: float = dataclasses.field(default=0.0, metadata=dict(static=True))
    has_rotation: bool = dataclasses.field(default=True, metadata=dict(static=True))

    # ---------------------------------------------------------------- poses
    def pose(self, q):
        """POM pose at actuator positions ``q``.

        Args:
          q: ``(n,)`` actuator positions (rad / m).

        Returns:
          ``(p (3,), R (3, 3))``: world-frame position and orientation.
        """
        return self.pose_fn(self.params, q)

    def task_difference(self, pose_t, pose_prev):
        """Task-space pose difference ``V`` (DESIGN: ``[p_t - p_prev, log(R_t R_prev^T)]``).

        The first ``task_dim`` entries of :func:`geometry.pose_difference`:
        2 -> planar ``(dx, dy)``, 3 -> ``dp``, 6 -> ``(dp, rotation vector)``,
        all in the world frame.

        Args:
          pose_t: ``(p (3,), R (3, 3))`` current pose.
          pose_prev: ``(p (3,), R (3, 3))`` previous pose.

        Returns:
          ``(task_dim,)`` difference (length unit; rad for rotation).
        """
        p_t, R_t = pose_t
        p_prev, R_prev = pose_prev
        if self.task_dim == 6:
            return geometry.pose_difference(p_t, R_t, p_prev, R_prev)
        return (p_t - p_prev)[..., : self.task_dim]

    def task_vector(self, q, q_prev):
        """``task_difference(pose(q), pose(q_prev))``: ``(task_dim,)``."""
        return self.task_difference(self.pose(q), self.pose(q_prev))

    # ------------------------------------------------------------ jacobians
    def jacobian(self, q):
        """Task Jacobian ``dV/dq`` at ``q``, world frame.

        Forward-mode derivative of ``q' -> task_difference(pose(q'), pose(q))``
        at ``q' = q`` (the reference pose held constant). Differentiating the
        relative rotation ``log(R(q') R(q)^T)`` at the identity gives the
        world-frame angular Jacobian (as MuJoCo's ``mj_jacSite`` ``jacr``);
        differentiating ``log(R(q'))`` would not. Pose maps that know their
        geometric Jacobian (``pose_fn.jacobian(params, q) -> (6, n)``, as
        :class:`ChainSitePose`) supply it directly instead.

        Args:
          q: ``(n,)`` actuator positions.

        Returns:
          ``(task_dim, n_act)`` Jacobian (length unit or rad, per rad or m).
        """
        q = jnp.asarray(q, dtype=jnp.result_type(q, float))
        analytic = getattr(self.pose_fn, "jacobian", None)
        if analytic is not None:
            J6 = analytic(self.params, q)
            return J6 if self.task_dim == 6 else J6[: self.task_dim]
        ref = jax.lax.stop_gradient(self.pose(q))
        return jax.jacfwd(lambda q_: self.task_difference(self.pose(q_), ref))(q)

    def pose_and_jacobian(self, q):
        """``((p (3,), R (3, 3)), J (task_dim, n_act))`` at ``q``: one kinematics pass where the pose map allows.

        Pose maps with ``pose_and_jacobian(params, q)`` (as :class:`ChainSitePose`)
        give both from one walk of the kinematic tree; otherwise this is
        ``(pose(q), jacobian(q))``.
        """
        fused = getattr(self.pose_fn, "pose_and_jacobian", None)
        if fused is None:
            return self.pose(q), self.jacobian(q)
        q = jnp.asarray(q, dtype=jnp.result_type(q, float))
        pose, J6 = fused(self.params, q)
        return pose, (J6 if self.task_dim == 6 else J6[: self.task_dim])

    def true_inverse_jacobian(self, q):
        """Pseudo-inverse of :meth:`jacobian` at ``q`` (the estimator's target).

        Square ``J``: ``solve(J, I)``; ``n > m``: minimum-norm right inverse
        ``J^T solve(J J^T, I)``; ``n < m``: least-squares left inverse
        ``solve(J^T J, J^T)``. Matrices up to 3x3 are inverted by the adjugate
        formula (elementwise arithmetic, several times faster than a batched
        ``solve`` on CPU). Undefined (inf/nan) at singular configurations.

        Args:
          q: ``(n,)`` actuator positions.

        Returns:
          ``(n_act, task_dim)`` inverse Jacobian, ``dtheta = Jinv @ V``.
        """
        return pseudo_inverse(self.jacobian(q))

    def singular_values(self, q):
        """Singular values of :meth:`jacobian` at ``q``, descending: ``(min(m, n),)``."""
        return jnp.linalg.svd(self.jacobian(q), compute_uv=False)

    def sigma_min(self, q):
        """Smallest singular value of :meth:`jacobian` at ``q`` (scalar, task units per actuator unit)."""
        return self.singular_values(q)[-1]

    def manipulability(self, q):
        """Yoshikawa manipulability ``prod(singular values) = sqrt(det(J J^T))`` (scalar)."""
        return jnp.prod(self.singular_values(q))

    # ------------------------------------------------------------ actuation
    def apply(self, q, dtheta):
        """Actuate: ``clip(q + clip(dtheta, -dq_max, dq_max), q_low, q_high)``.

        Args:
          q: ``(n,)`` actuator positions.
          dtheta: ``(n,)`` requested change.

        Returns:
          ``(n,)`` new actuator positions.
        """
        step = jnp.clip(dtheta, -self.dq_max, self.dq_max)
        return jnp.clip(q + step, self.q_low, self.q_high)

    def sample_configs(self, key, k: int, *, oversample: int = 8, return_valid: bool = False):
        """Draw ``k`` configurations away from singularities.

        Draws ``k * oversample`` candidates uniformly in
        ``[sample_low, sample_high]`` and keeps those with
        ``sigma_min(jacobian(q)) > min_sigma`` (smallest singular value of the
        ``(task_dim, n_act)`` Jacobian of the current task). Valid candidates
        come first in draw order (stable argsort), so the result is uniform on
        the valid part of the box. If fewer than ``k`` candidates are valid,
        the remainder are invalid candidates; ask for ``return_valid=True`` to
        see which, or raise ``oversample``. Jit-able (``k``, ``oversample``
        static).

        Args:
          key: ``jax.random`` key.
          k: number of configurations (static).
          oversample: candidates drawn per returned configuration (static).
          return_valid: also return the ``(k,)`` bool validity mask.

        Returns:
          ``(k, n_act)`` configurations (and the mask if ``return_valid``).
        """
        cand, valid = _sample_candidates(self, key, int(k), int(oversample))
        if return_valid:
            return cand, valid
        return cand

    # ---------------------------------------------------------------- copies
    def with_task_dim(self, task_dim: int, *, min_sigma: float | None = None) -> "System":
        """Copy of this system with another task dimension (and optionally ``min_sigma``)."""
        _check_task_dim(task_dim, self.has_rotation)
        kw = dict(task_dim=int(task_dim))
        if min_sigma is not None:
            kw["min_sigma"] = float(min_sigma)
        return dataclasses.replace(self, **kw)

    def replace(self, **changes) -> "System":
        """``dataclasses.replace`` (e.g. another ``m_a`` for a sweep)."""
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(
    System,
    data_fields=["params", "q_low", "q_high", "dq_max", "m_a", "sample_low", "sample_high"],
    meta_fields=["name", "n_act", "task_dim", "pose_fn", "min_sigma", "has_rotation"],
)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _sample_candidates(system: "System", key, k: int, oversample: int):
    """``(k, n)`` configurations of ``system``, valid (``sigma_min > min_sigma``) first, and the ``(k,)`` mask."""
    low, high = system.sample_low, system.sample_high
    dtype = jnp.result_type(low, float)
    cand = jax.random.uniform(key, (k * oversample, system.n_act), dtype=dtype, minval=low, maxval=high)
    valid = jax.vmap(system.sigma_min)(cand) > system.min_sigma
    order = jnp.argsort(jnp.logical_not(valid), stable=True)[:k]
    return cand[order], valid[order]


def _mjx():
    """``mujoco.mjx``, imported with its stdout notices about the optional Warp backend silenced."""
    import contextlib
    import io

    with contextlib.redirect_stdout(io.StringIO()):
        from mujoco import mjx
    return mjx


def pseudo_inverse(J):
    """Pseudo-inverse ``(n, m)`` of a Jacobian ``J (m, n)`` (see :meth:`System.true_inverse_jacobian`)."""
    m, n = J.shape
    if n == m:
        return _small_inverse(J) if m <= 3 else jnp.linalg.solve(J, jnp.eye(m, dtype=J.dtype))
    if n > m:
        A = J @ J.T
        return J.T @ (_small_inverse(A) if m <= 3 else jnp.linalg.solve(A, jnp.eye(m, dtype=J.dtype)))
    return jnp.linalg.solve(J.T @ J, J.T)


def _small_inverse(A):
    """Inverse of a ``(k, k)`` matrix, ``k <= 3``, by the adjugate over the determinant.

    NaN where ``A`` is numerically singular: ``|det A|`` at most ``1e3 eps``
    times the product of its row norms (Hadamard's bound, so the test is
    scale-free), as an exactly singular ``solve`` would give inf/NaN.
    """
    k = A.shape[0]
    if k == 1:
        adj, det = jnp.ones_like(A), A[0, 0]
    elif k == 2:
        adj = jnp.stack([jnp.stack([A[1, 1], -A[0, 1]]), jnp.stack([-A[1, 0], A[0, 0]])])
        det = A[0, 0] * A[1, 1] - A[0, 1] * A[1, 0]
    else:
        c0, c1, c2 = jnp.cross(A[1], A[2]), jnp.cross(A[2], A[0]), jnp.cross(A[0], A[1])
        adj = jnp.stack([c0, c1, c2], axis=1)
        det = jnp.dot(A[0], c0)
    bound = jnp.prod(jnp.sqrt(jnp.sum(A * A, axis=1)))
    singular = jnp.abs(det) <= 1e3 * jnp.finfo(A.dtype).eps * bound
    return jnp.where(singular, jnp.nan, adj / jnp.where(singular, 1.0, det))


# ----------------------------------------------------------------- pose maps
@dataclasses.dataclass(frozen=True)
class PositionOnlyPose:
    """Wraps ``fn(params, q) -> p`` (``(3,)`` or planar ``(2,)``) as a pose map with ``R = I``."""

    fn: Callable[[Any, jax.Array], jax.Array]
    planar: bool = False

    def __call__(self, params, q):
        p = jnp.asarray(self.fn(params, q))
        if self.planar:
            p = jnp.concatenate([p, jnp.zeros((1,), p.dtype)])
        return p, jnp.eye(3, dtype=p.dtype)


# --------------------------------------------------------------- validation
def _check_task_dim(task_dim, has_rotation: bool = True) -> None:
    if isinstance(task_dim, bool) or not isinstance(task_dim, (int, np.integer)) or task_dim not in TASK_DIMS:
        raise ValueError(f"task_dim must be one of {TASK_DIMS}, got {task_dim!r}")
    if task_dim == 6 and not has_rotation:
        raise ValueError("task_dim=6 needs an orientation, but the pose function returns a position only")


def _vector(name: str, value, n: int) -> np.ndarray:
    """Eager check: ``value`` is a scalar or ``(n,)`` real array; returns ``(n,)`` float64 numpy."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as e:
        raise ValueError(f"{name} must be a real scalar or array of shape ({n},), got {value!r}") from e
    if arr.ndim == 0:
        arr = np.full((n,), float(arr))
    if arr.shape != (n,):
        raise ValueError(f"{name} must have shape ({n},) (n_act={n}) or be a scalar, got shape {arr.shape}")
    if np.isnan(arr).any():
        raise ValueError(f"{name} contains NaN: {arr}")
    return arr


def _validate(
    *, n_act, task_dim, has_rotation, q_low, q_high, dq_max, m_a, sample_low, sample_high, min_sigma
) -> dict[str, Any]:
    if isinstance(n_act, bool) or not isinstance(n_act, (int, np.integer)) or n_act < 1:
        raise ValueError(f"n_act must be a positive integer, got {n_act!r}")
    n_act = int(n_act)
    _check_task_dim(task_dim, has_rotation)
    q_low = _vector("q_low", q_low, n_act)
    q_high = _vector("q_high", q_high, n_act)
    if not np.all(q_low < q_high):
        raise ValueError(f"q_low must be < q_high elementwise, got q_low={q_low}, q_high={q_high}")
    dq_max = _vector("dq_max", dq_max, n_act)
    if not np.all((dq_max > 0) & np.isfinite(dq_max)):
        raise ValueError(f"dq_max must be positive and finite, got {dq_max}")
    m_a_arr = np.asarray(m_a, dtype=np.float64) if np.ndim(m_a) == 0 else None
    if m_a_arr is None:
        raise ValueError(f"m_a must be a scalar, got shape {np.shape(m_a)}")
    if not (np.isfinite(m_a_arr) and m_a_arr > 0):
        raise ValueError(f"m_a must be positive and finite, got {m_a!r}")
    if sample_low is None:
        sample_low = q_low
    if sample_high is None:
        sample_high = q_high
    sample_low = _vector("sample_low", sample_low, n_act)
    sample_high = _vector("sample_high", sample_high, n_act)
    if not (np.all(np.isfinite(sample_low)) and np.all(np.isfinite(sample_high))):
        raise ValueError(
            "the sampling box must be finite (pass sample_low/sample_high when joint limits are infinite), "
            f"got sample_low={sample_low}, sample_high={sample_high}"
        )
    if not np.all(sample_low < sample_high):
        raise ValueError(
            f"sample_low must be < sample_high elementwise, got sample_low={sample_low}, sample_high={sample_high}"
        )
    if np.any(sample_low < q_low) or np.any(sample_high > q_high):
        raise ValueError(
            f"the sampling box [{sample_low}, {sample_high}] must lie inside the joint limits [{q_low}, {q_high}]"
        )
    min_sigma = float(min_sigma)
    if not (math.isfinite(min_sigma) and min_sigma >= 0):
        raise ValueError(f"min_sigma must be finite and >= 0, got {min_sigma}")
    return dict(
        n_act=n_act,
        task_dim=int(task_dim),
        q_low=q_low,
        q_high=q_high,
        dq_max=dq_max,
        m_a=m_a_arr,
        sample_low=sample_low,
        sample_high=sample_high,
        min_sigma=min_sigma,
    )


def _make_system(*, name, params, pose_fn, has_rotation, **kw) -> System:
    v = _validate(has_rotation=has_rotation, **kw)
    f = jnp.asarray  # default float dtype (float64 only under jax_enable_x64)
    fl = jnp.result_type(float)
    return System(
        params=params,
        q_low=f(v["q_low"], fl),
        q_high=f(v["q_high"], fl),
        dq_max=f(v["dq_max"], fl),
        m_a=f(v["m_a"], fl),
        sample_low=f(v["sample_low"], fl),
        sample_high=f(v["sample_high"], fl),
        name=str(name),
        n_act=v["n_act"],
        task_dim=v["task_dim"],
        pose_fn=pose_fn,
        min_sigma=v["min_sigma"],
        has_rotation=has_rotation,
    )


# ---------------------------------------------------------------- builders
def from_pose_fn(
    fn: Callable,
    n_act: int,
    *,
    task_dim: int,
    q_low,
    q_high,
    dq_max,
    m_a,
    params: Any = None,
    sample_low=None,
    sample_high=None,
    min_sigma: float = 1e-3,
    name: str = "custom",
) -> System:
    """Build a :class:`System` from a pure JAX pose function.

    Everything is validated eagerly (shapes, orderings, positivity; the output
    structure of ``fn`` via ``jax.eval_shape``, which traces but does not
    compute) and a ``ValueError`` names the offending argument.

    Args:
      fn: ``fn(params, q (n_act,)) -> (p (3,), R (3, 3))``, or ``-> p`` with
        ``p`` of shape ``(3,)`` (position only, ``R = I``) or ``(2,)`` (planar,
        ``z = 0``; only with ``task_dim=2``). Must be pure and traceable.
      n_act: number of actuators.
      task_dim: 2 (planar xy), 3 (position) or 6 (position + rotation).
      q_low, q_high: joint limits, scalar or ``(n_act,)`` (rad or m; may be inf).
      dq_max: per-step actuator limit, scalar or ``(n_act,)``, > 0.
      m_a: safe self-ID magnitude (scalar, > 0).
      params: pytree passed to ``fn`` (traced).
      sample_low, sample_high: sampling box, default the joint limits (must be
        finite and inside the limits).
      min_sigma: singularity threshold for ``sample_configs``.
      name: label.

    Returns:
      A :class:`System`.
    """
    if not callable(fn):
        raise ValueError(f"fn must be callable fn(params, q), got {fn!r}")
    if isinstance(n_act, bool) or not isinstance(n_act, (int, np.integer)) or n_act < 1:
        raise ValueError(f"n_act must be a positive integer, got {n_act!r}")
    limits = dict(
        n_act=n_act,
        task_dim=task_dim,
        q_low=q_low,
        q_high=q_high,
        dq_max=dq_max,
        m_a=m_a,
        sample_low=sample_low,
        sample_high=sample_high,
        min_sigma=min_sigma,
    )
    _validate(has_rotation=True, **limits)  # report bad numbers before tracing fn
    q0 = jax.ShapeDtypeStruct((int(n_act),), jnp.result_type(float))
    try:
        out = jax.eval_shape(fn, params, q0)
    except Exception as e:  # noqa: BLE001 - report any tracing failure as bad input
        raise ValueError(f"fn(params, q) failed on q of shape ({n_act},): {type(e).__name__}: {e}") from e
    if isinstance(out, (tuple, list)) and len(out) == 2:
        p_s, r_s = out
        if getattr(p_s, "shape", None) != (3,) or getattr(r_s, "shape", None) != (3, 3):
            raise ValueError(
                "fn must return (p (3,), R (3, 3)) or p (3,) / (2,); got shapes "
                f"({getattr(p_s, 'shape', p_s)}, {getattr(r_s, 'shape', r_s)})"
            )
        pose_fn, has_rotation = fn, True
    elif hasattr(out, "shape") and out.shape in ((3,), (2,)):
        planar = out.shape == (2,)
        if planar and task_dim != 2:
            raise ValueError(f"fn returns a planar position of shape (2,), which needs task_dim=2, got {task_dim!r}")
        pose_fn, has_rotation = PositionOnlyPose(fn, planar), False
    else:
        raise ValueError(f"fn must return (p (3,), R (3, 3)) or p (3,) / (2,); got {out}")
    return _make_system(
        name=name,
        params=params,
        pose_fn=pose_fn,
        has_rotation=has_rotation,
        **limits,
    )


# ---------------------------------------------------------------- MJCF / MJX
@dataclasses.dataclass(frozen=True)
class MjxSitePose:
    """Pose map of an MJCF site by ``mjx.kinematics``: ``(mjx.Model, q) -> (site_xpos, site_xmat)``.

    ``q`` is written into ``qpos`` (hinge/slide joints only, so ``q = qpos``).
    Hashable by value, so systems rebuilt from the same file share compiled
    code.
    """

    site_id: int

    def __call__(self, model, q):
        mjx = _mjx()

        d = mjx.make_data(model)
        d = d.replace(qpos=jnp.asarray(q, dtype=d.qpos.dtype))
        d = mjx.kinematics(model, d)
        return d.site_xpos[self.site_id], d.site_xmat[self.site_id].reshape(3, 3)


def _quat_to_mat(q):
    """Rotation matrices ``(..., 3, 3)`` of unit quaternions ``(..., 4)`` ``(w, x, y, z)``."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(r, axis=-1) for r in rows], axis=-2)


@dataclasses.dataclass(frozen=True)
class ChainSitePose:
    """Pose map of an MJCF site by a plain-JAX product of joint transforms.

    Walks only the bodies from the world to the site's body (static indices),
    reading ``body_pos``, ``body_quat``, ``jnt_pos``, ``jnt_axis``, ``qpos0``,
    ``site_pos`` and ``site_quat`` from the ``mjx.Model`` in ``params`` (so it
    follows the MJCF, including a swept/batched model), with rotation matrices
    instead of MJX's quaternions and without computing every body, geom and
    site. Same convention as MuJoCo: a hinge rotates about its anchor by
    ``qpos - qpos0``; a slide translates by ``qpos - qpos0``. The constant
    body rotations and all joint rotations are built in one vectorised step
    each, which keeps tracing and compilation short.

    Attributes:
      site_id: site index.
      bodies: body ids from the world's child down to the site's body.
      joints: per body, tuple of ``(joint id, qpos address, is_hinge)``.
    """

    site_id: int
    bodies: tuple[int, ...]
    joints: tuple[tuple[tuple[int, int, bool], ...], ...]

    def __call__(self, model, q):
        p, R, _ = self._walk(model, q)
        return p, R

    def jacobian(self, model, q):
        """Site Jacobian ``(6, nq)`` in the world frame: rows ``[dp/dq; omega/dq]`` (as ``mj_jacSite``).

        Hinge column ``i``: ``[a_i x (p - c_i); a_i]`` with world axis ``a_i`` and
        anchor ``c_i``; slide column: ``[a_i; 0]``. Computed from the same walk as
        the pose, so it costs about one forward-kinematics pass instead of the
        ``nq + 1`` of ``jax.jacfwd``.
        """
        return self.pose_and_jacobian(model, q)[1]

    def pose_and_jacobian(self, model, q):
        """``((p, R), J (6, nq))`` from one walk: the pose of :meth:`__call__` and :meth:`jacobian`."""
        p, R, joints = self._walk(model, q)
        nq = jnp.shape(q)[-1]
        cols = [jnp.zeros(6, p.dtype)] * nq
        for adr, is_hinge, axis_w, anchor in joints:
            if is_hinge:
                cols[adr] = jnp.concatenate([jnp.cross(axis_w, p - anchor), axis_w])
            else:
                cols[adr] = jnp.concatenate([axis_w, jnp.zeros(3, p.dtype)])
        return (p, R), jnp.stack(cols, axis=1)

    def _walk(self, model, q):
        """World pose of the site and, per joint, ``(qpos address, is_hinge, world axis, world anchor)``."""
        q = jnp.asarray(q)
        dtype = jnp.result_type(q, model.body_pos)
        bodies = np.asarray(self.bodies, dtype=np.int32)
        flat = [jt for jnts in self.joints for jt in jnts]
        jid = np.asarray([j for j, _, _ in flat], dtype=np.int32)
        adr = np.asarray([a for _, a, _ in flat], dtype=np.int32)

        body_p = model.body_pos[bodies].astype(dtype)  # (nb, 3)
        body_R = _quat_to_mat(model.body_quat[bodies]).astype(dtype)  # (nb, 3, 3)
        if len(flat):
            angle = (q[adr] - model.qpos0[adr]).astype(dtype)  # (nj,)
            axis = model.jnt_axis[jid].astype(dtype)  # (nj, 3)
            jpos = model.jnt_pos[jid].astype(dtype)  # (nj, 3)
            k = geometry.hat(axis)
            eye = jnp.broadcast_to(jnp.eye(3, dtype=dtype), k.shape)
            # Rodrigues for unit axes (MuJoCo normalises jnt_axis): smooth, no division.
            joint_R = eye + jnp.sin(angle)[:, None, None] * k + (1.0 - jnp.cos(angle))[:, None, None] * (k @ k)

        pos = jnp.zeros(3, dtype)
        rot = jnp.eye(3, dtype=dtype)
        joints = []
        i = 0
        for b, jnts in enumerate(self.joints):
            pos = pos + rot @ body_p[b]
            rot = rot @ body_R[b]
            for _, qadr, is_hinge in jnts:
                axis_w = rot @ axis[i]
                if is_hinge:
                    anchor = pos + rot @ jpos[i]
                    rot = rot @ joint_R[i]
                    pos = anchor - rot @ jpos[i]
                    joints.append((qadr, True, axis_w, anchor))
                else:
                    pos = pos + axis_w * angle[i]
                    joints.append((qadr, False, axis_w, None))
                i += 1
        p = pos + rot @ model.site_pos[self.site_id].astype(dtype)
        R = rot @ _quat_to_mat(model.site_quat[self.site_id]).astype(dtype)
        return p, R, joints


def _load_mjmodel(path_or_xml):
    import mujoco

    if isinstance(path_or_xml, mujoco.MjModel):
        return path_or_xml, "<MjModel>"
    if isinstance(path_or_xml, (str, os.PathLike)) and not str(path_or_xml).lstrip().startswith("<"):
        label = os.fspath(path_or_xml)
        try:
            return mujoco.MjModel.from_xml_path(label), label
        except Exception as e:  # noqa: BLE001 - mujoco raises ValueError/Exception
            raise ValueError(f"could not load MJCF file {label!r}: {e}") from e
    if isinstance(path_or_xml, str):
        try:
            return mujoco.MjModel.from_xml_string(path_or_xml), "<xml string>"
        except Exception as e:  # noqa: BLE001
            raise ValueError(f"could not parse MJCF XML string: {e}") from e
    raise ValueError(f"path_or_xml must be a path, an XML string or a mujoco.MjModel, got {type(path_or_xml)}")


def from_mjcf(
    path_or_xml,
    site: str,
    *,
    task_dim: int,
    m_a,
    dq_max=0.1,
    q_low=None,
    q_high=None,
    sample_low=None,
    sample_high=None,
    min_sigma: float = 1e-3,
    fk: str = "mjx",
    name: str | None = None,
) -> System:
    """Build a :class:`System` from an MJCF model and the name of the POM site.

    The actuators are the model's joints, which must all be hinge or slide
    joints (``q = qpos``, ``n_act = nq``). Joint limits come from
    ``jnt_range`` for limited joints, else +-inf (override with
    ``q_low``/``q_high``); the sampling box defaults to the limits, with
    ``[-pi, pi]`` for unlimited hinges (unlimited slides need an explicit box).

    The ``mjx.Model`` is stored in ``params`` as a traced pytree: MJX marks its
    ``jax.Array`` fields as data and its ints/numpy arrays/enums (``nq``,
    ``jnt_type``, ``body_parentid``...) as hashable static metadata, so the
    whole ``System`` passes through ``jit``/``vmap`` (checked with MJX 3.17),
    and a sweep can batch model fields (e.g. ``body_pos``) with ``in_axes``.

    Args:
      path_or_xml: MJCF file path, XML string, or a ``mujoco.MjModel``.
      site: name of the POM site.
      task_dim: 2, 3 or 6.
      m_a: safe self-ID magnitude (scalar, rad / m).
      dq_max: per-step actuator limit, scalar or ``(nq,)``.
      q_low, q_high: override the limits from the file.
      sample_low, sample_high: sampling box (default: the limits).
      min_sigma: singularity threshold for ``sample_configs``.
      fk: ``"mjx"`` (``mjx.kinematics``, reads ``site_xpos``/``site_xmat``) or
        ``"chain"`` (:class:`ChainSitePose`, the same kinematics as a plain-JAX
        joint chain, faster; tested equal to ``"mjx"``).
      name: label (default: the model's name).

    Returns:
      A :class:`System` whose ``params`` is the ``mjx.Model``.
    """
    import mujoco
    mjx = _mjx()

    mj, label = _load_mjmodel(path_or_xml)
    if not isinstance(site, str):
        raise ValueError(f"site must be a site name (str), got {site!r}")
    site_id = mujoco.mj_name2id(mj, mujoco.mjtObj.mjOBJ_SITE, site)
    if site_id < 0:
        names = [mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_SITE, i) for i in range(mj.nsite)]
        raise ValueError(f"site {site!r} not found in MJCF {label}; sites are {names}")
    hinge, slide = int(mujoco.mjtJoint.mjJNT_HINGE), int(mujoco.mjtJoint.mjJNT_SLIDE)
    bad = [
        (mujoco.mj_id2name(mj, mujoco.mjtObj.mjOBJ_JOINT, j), int(t))
        for j, t in enumerate(mj.jnt_type)
        if int(t) not in (hinge, slide)
    ]
    if bad or mj.njnt == 0:
        raise ValueError(f"MJCF {label}: every joint must be a hinge or slide (one actuator per joint); bad: {bad}")
    n = int(mj.nq)

    limited = np.asarray(mj.jnt_limited, bool)
    rng = np.asarray(mj.jnt_range, np.float64)
    lo = np.where(limited, rng[:, 0], -np.inf)
    hi = np.where(limited, rng[:, 1], np.inf)
    adr = np.asarray(mj.jnt_qposadr)
    file_low, file_high = np.empty(n), np.empty(n)
    file_low[adr], file_high[adr] = lo, hi
    q_low = file_low if q_low is None else q_low
    q_high = file_high if q_high is None else q_high
    is_hinge = np.empty(n, bool)
    is_hinge[adr] = np.asarray(mj.jnt_type) == hinge
    if sample_low is None:
        ql = _vector("q_low", q_low, n)
        sample_low = np.where(np.isfinite(ql), ql, np.where(is_hinge, -np.pi, ql))
    if sample_high is None:
        qh = _vector("q_high", q_high, n)
        sample_high = np.where(np.isfinite(qh), qh, np.where(is_hinge, np.pi, qh))

    if fk == "mjx":
        pose_fn = MjxSitePose(int(site_id))
    elif fk == "chain":
        body = int(mj.site_bodyid[site_id])
        path = []
        while body != 0:
            path.append(body)
            body = int(mj.body_parentid[body])
        path = path[::-1]
        joints = []
        for b in path:
            start, num = int(mj.body_jntadr[b]), int(mj.body_jntnum[b])
            joints.append(
                tuple((j, int(mj.jnt_qposadr[j]), int(mj.jnt_type[j]) == hinge) for j in range(start, start + num))
            )
        pose_fn = ChainSitePose(int(site_id), tuple(path), tuple(joints))
    else:
        raise ValueError(f"fk must be 'mjx' or 'chain', got {fk!r}")

    model = mjx.put_model(mj)
    if name is None:
        name = os.path.splitext(os.path.basename(label))[0] if label[0] != "<" else "mjcf"
    return _make_system(
        name=name,
        params=model,
        pose_fn=pose_fn,
        has_rotation=True,
        n_act=n,
        task_dim=task_dim,
        q_low=q_low,
        q_high=q_high,
        dq_max=dq_max,
        m_a=m_a,
        sample_low=sample_low,
        sample_high=sample_high,
        min_sigma=min_sigma,
    )
