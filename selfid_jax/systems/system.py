"""The ``System`` pytree: a kinematic robot seen through its actuators and a POM pose.

A :class:`System` bundles a pose map ``pose_fn(params, q) -> (p, R)`` from
actuator positions ``q`` (``(n_act,)``, rad or m) to the pose of the point of
manipulation (POM), the actuator limits, a safe self-ID magnitude and a box of
configurations to sample from. It is a frozen dataclass registered as a JAX
pytree in the MJX manner (``mujoco/mjx/_src/types.py``):

* traced (data) fields: ``params`` (any pytree, e.g. link lengths, an
  ``mjx.Model`` or a :class:`~selfid_jax.systems.kinematics.ChainModel`),
  ``q_low``, ``q_high``, ``dq_max``, ``m_a``, ``sample_low``, ``sample_high``
  (all ``(n_act,)``). A sweep can ``vmap`` over any of them and a ``System``
  can be passed to ``jax.jit`` as an ordinary argument.
* static (meta) fields: ``name``, ``n_act``, ``task_dim``, ``pose_fn``,
  ``min_sigma``, ``has_rotation``, ``task_axes``. Changing one recompiles; ``pose_fn`` is
  hashed by identity (module-level pose functions and the frozen-dataclass
  pose maps, :class:`PositionOnlyPose` here and those of
  :mod:`selfid_jax.systems.kinematics`, hash by value, so rebuilding a
  system does not recompile).

Build one with :func:`from_pose_fn` (a pure JAX pose function, this module)
or :func:`selfid_jax.systems.mjcf.from_mjcf` (an MJCF model, its actuators and
a site name; forward kinematics by a plain-JAX joint chain or by
``mjx.kinematics``). Input checks live in :mod:`selfid_jax.systems.validation`.

Dtypes: array fields take the default float dtype at construction time
(float64 only if ``jax_enable_x64`` is on *when the system is built*); build
systems after enabling x64 where precision matters.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Callable
from typing import Any, Protocol

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from selfid_jax.math import geometry
from selfid_jax.math.linalg import pseudo_inverse
from selfid_jax.systems.validation import Limits, Values, check_task_axes, check_task_dim, default_axes, validate

__all__ = ["System", "SelfIDSystem", "from_pose_fn", "PositionOnlyPose"]

Pose = tuple[jax.Array, jax.Array]
"""A POM pose ``(p (3,), R (3, 3))``: world-frame position and orientation."""


class SelfIDSystem(Protocol):
    """What Algorithm 1 (:func:`selfid_jax.identify.algorithm.run`) uses of a simulated system.

    :class:`System` is one (mypy checks it where a ``System`` is passed); any
    object with these members runs self-ID too. Shapes as in :class:`System`:
    ``n = n_act`` actuators, ``m = task_dim`` task dimensions.
    """

    @property
    def n_act(self) -> int:
        """Number of actuators ``n`` (static)."""
        ...

    @property
    def task_dim(self) -> int:
        """Task dimension ``m`` (static)."""
        ...

    @property
    def m_a(self) -> jax.Array:
        """``(n,)`` default self-ID magnitude per actuator."""
        ...

    def pose(self, q: jax.Array) -> Pose:
        """POM pose ``(p (3,), R (3, 3))`` at actuator positions ``q (n,)``; vmapped over a batch of two."""
        ...

    def apply(self, q: jax.Array, dtheta: jax.Array) -> jax.Array:
        """Actuator positions ``(n,)`` after requesting the change ``dtheta (n,)`` at ``q (n,)``."""
        ...

    def task_difference(self, pose_t: Pose, pose_prev: Pose) -> jax.Array:
        """Task-space pose difference ``V (m,)`` from ``pose_prev`` to ``pose_t``."""
        ...


@dataclasses.dataclass(frozen=True)
class System:
    """A kinematic system: actuator positions -> POM pose, with limits.

    Shapes: ``n = n_act`` actuators, ``m = task_dim`` task dimensions
    (2: planar xy position, 3: position, 6: position + world-frame rotation
    vector). Units: actuator positions in rad (hinge) or m (slide); positions
    in the system's length unit (m for the shipped systems); rotations in rad.

    Traced attributes:
      params: pytree passed to ``pose_fn`` (link lengths, an ``mjx.Model``...).
      q_low, q_high: ``(n,)`` joint limits (may be +-inf).
      dq_max: ``(n,)`` largest actuator change per step (``apply`` clips to it).
      m_a: ``(n,)`` safe self-ID magnitude per actuator (random step size; a scalar is broadcast at build).
      sample_low, sample_high: ``(n,)`` box that ``sample_configs`` draws from.

    Static attributes:
      name: label.
      n_act: number of actuators ``n``.
      task_dim: ``m``: 2, 3 or 6, or the number of ``task_axes``.
      pose_fn: ``pose_fn(params, q (n,)) -> (p (3,), R (3, 3))``.
      min_sigma: ``sample_configs`` keeps configurations whose Jacobian's
        smallest singular value exceeds this (task units per actuator unit).
      has_rotation: False if ``pose_fn`` only knows positions (``R`` is the
        identity); then ``task_dim`` must not be 6.
      task_axes: ``None`` (the first ``task_dim`` components of
        ``[dp, rotation vector]``) or a sorted tuple of indices into it
        (0-2 position, 3-5 rotation), e.g. ``(2, 3, 4)`` for a hand that
        controls its object's height and tilt; set by :meth:`with_task_axes`.
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
    task_axes: tuple[int, ...] | None = dataclasses.field(default=None, metadata=dict(static=True))

    @property
    def axes(self) -> tuple[int, ...]:
        """Indices of the task's components in ``[x, y, z, rx, ry, rz]`` (static): ``(task_dim,)``."""
        return default_axes(self.task_dim) if self.task_axes is None else self.task_axes

    @property
    def position_axes(self) -> tuple[int, ...]:
        """The task's position components, as indices 0-2 into ``p``."""
        return tuple(a for a in self.axes if a < 3)

    @property
    def rotation_axes(self) -> tuple[int, ...]:
        """The task's rotation components, as indices 0-2 into the rotation vector."""
        return tuple(a - 3 for a in self.axes if a >= 3)

    # ---------------------------------------------------------------- poses
    def pose(self, q: jax.Array) -> Pose:
        """POM pose at actuator positions ``q``.

        Args:
          q: ``(n,)`` actuator positions (rad / m).

        Returns:
          ``(p (3,), R (3, 3))``: world-frame position and orientation.
        """
        if self.pose_fn is None:
            raise TypeError(f"System {self.name!r} has no pose_fn: build one with from_pose_fn or make_system")
        return self.pose_fn(self.params, q)

    def task_difference(self, pose_t: Pose, pose_prev: Pose) -> jax.Array:
        """Task-space pose difference ``V`` (DESIGN: ``[p_t - p_prev, log(R_t R_prev^T)]``).

        The entries :attr:`axes` of :func:`geometry.pose_difference`:
        2 -> planar ``(dx, dy)``, 3 -> ``dp``, 6 -> ``(dp, rotation vector)``,
        or the chosen ``task_axes``, all in the world frame.

        Args:
          pose_t: ``(p (3,), R (3, 3))`` current pose.
          pose_prev: ``(p (3,), R (3, 3))`` previous pose.

        Returns:
          ``(task_dim,)`` difference (length unit; rad for rotation).
        """
        p_t, R_t = pose_t
        p_prev, R_prev = pose_prev
        if self.rotation_axes:
            full = geometry.pose_difference(p_t, R_t, p_prev, R_prev)
            return full if self.axes == default_axes(6) else full[..., self.axes]
        return (p_t - p_prev)[..., self.axes]

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
            return self._rows(analytic(self.params, q))
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
        return pose, self._rows(J6)

    def _rows(self, J6):
        """The task's rows ``(task_dim, n)`` of a geometric Jacobian ``(6, n)``."""
        return J6 if self.axes == default_axes(6) else J6[jnp.asarray(self.axes)]

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
    def apply(self, q: ArrayLike, dtheta: ArrayLike) -> jax.Array:
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
    def with_task_dim(self, task_dim: int, *, min_sigma: float | None = None) -> System:
        """Copy of this system with another task dimension (and optionally ``min_sigma``)."""
        check_task_dim(task_dim, self.has_rotation)
        sigma = self.min_sigma if min_sigma is None else float(min_sigma)
        return dataclasses.replace(self, task_dim=int(task_dim), task_axes=None, min_sigma=sigma)

    def with_task_axes(self, axes, *, min_sigma: float | None = None) -> System:
        """Copy of this system whose task is the chosen components of ``[dp, rotation vector]``.

        Args:
          axes: names out of ``("x", "y", "z", "rx", "ry", "rz")`` or indices
            0-5, e.g. ``("z", "rx", "ry")``; ``task_dim`` becomes ``len(axes)``.
          min_sigma: optionally a new singularity threshold for ``sample_configs``.
        """
        axes = check_task_axes(axes, self.has_rotation)
        if axes in (default_axes(2), default_axes(3), default_axes(6)):
            return self.with_task_dim(len(axes), min_sigma=min_sigma)
        sigma = self.min_sigma if min_sigma is None else float(min_sigma)
        return dataclasses.replace(self, task_dim=len(axes), task_axes=axes, min_sigma=sigma)

    def replace(self, **changes) -> System:
        """``dataclasses.replace`` (e.g. another ``m_a`` for a sweep)."""
        return dataclasses.replace(self, **changes)


jax.tree_util.register_dataclass(
    System,
    data_fields=["params", "q_low", "q_high", "dq_max", "m_a", "sample_low", "sample_high"],
    meta_fields=["name", "n_act", "task_dim", "pose_fn", "min_sigma", "has_rotation", "task_axes"],
)


@functools.partial(jax.jit, static_argnums=(2, 3))
def _sample_candidates(system: System, key, k: int, oversample: int):
    """``(k, n)`` configurations of ``system``, valid (``sigma_min > min_sigma``) first, and the ``(k,)`` mask."""
    low, high = system.sample_low, system.sample_high
    dtype = jnp.result_type(low, float)
    cand = jax.random.uniform(key, (k * oversample, system.n_act), dtype=dtype, minval=low, maxval=high)
    valid = jax.vmap(system.sigma_min)(cand) > system.min_sigma
    order = jnp.argsort(jnp.logical_not(valid), stable=True)[:k]
    return cand[order], valid[order]


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


def make_system(*, name, params, pose_fn, has_rotation, limits: Limits) -> System:
    """A :class:`System` from :func:`validate`-checked ``limits``, arrays in the default float dtype."""
    v = validate(limits, has_rotation=has_rotation)
    fl = jnp.result_type(float)  # the default float dtype (float64 only under jax_enable_x64)
    def arr(field: str) -> jax.Array:
        return jnp.asarray(getattr(v, field), fl)

    return System(params=params, q_low=arr("q_low"), q_high=arr("q_high"), dq_max=arr("dq_max"), m_a=arr("m_a"),
                  sample_low=arr("sample_low"), sample_high=arr("sample_high"), name=str(name), n_act=v.n_act,
                  task_dim=v.task_dim, pose_fn=pose_fn, min_sigma=v.min_sigma, has_rotation=has_rotation)


# ---------------------------------------------------------------- builders
def from_pose_fn(
    fn: Callable,
    n_act: int,
    *,
    task_dim: int,
    q_low: Values,
    q_high: Values,
    dq_max: Values,
    m_a: Values,
    params: Any = None,
    sample_low: Values | None = None,
    sample_high: Values | None = None,
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
      m_a: safe self-ID magnitude, scalar or ``(n_act,)``, > 0 (rad or m).
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
    limits = Limits(n_act, task_dim, q_low, q_high, dq_max, m_a, sample_low, sample_high, min_sigma)
    validate(limits, has_rotation=True)  # report bad numbers before tracing fn
    q0 = jax.ShapeDtypeStruct((int(n_act),), jnp.result_type(float))
    try:
        out = jax.eval_shape(fn, params, q0)
    except Exception as e:
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
    return make_system(
        name=name,
        params=params,
        pose_fn=pose_fn,
        has_rotation=has_rotation,
        limits=limits,
    )
