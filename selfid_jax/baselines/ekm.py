"""E-KM (seed 002): a nominal kinematic model with wrong parameters, corrected by a Sparse Online GP.

The seed's Enhanced Kinematic Model predicts the task step as the nominal
model's plus a GP-learned residual (Eq. 3), trained on (Eq. 9)
``x = [q, da]``, ``y = ds - J_m da``. Here the nominal model is a
:class:`~selfid_jax.systems.System` with wrong parameters
(:func:`nominal_system`: link lengths scaled, joint offsets), the GP is
:mod:`selfid_jax.baselines.sogp` (Csato & Opper), and two formulations are
offered (``formulation``):

* ``"incremental"`` (the seed's): input ``[q, da]`` (``2n``), target
  ``V - J_nom(q) da``. The GP is nonlinear in ``da``, so the control model is
  its first-order expansion at ``da = 0``: ``V ~ g(q, 0) + (J_nom(q) +
  dg/dda(q, 0)) da``. Any task dimension. ``symmetric`` (default True) also
  feeds each sample's mirror ``([q, -da], -y)``: the residual of a
  differential motion is odd in ``da``. Without it an RBF GP fitted to
  samples at ``|da| ~ m_a << length_da`` is nearly flat in ``da``: it
  predicts ``g(q, 0) ~ y`` (motion without actuation) and a slope about
  ``(m_a / length_da)^2`` of the true one, and the controller is misled (a
  2-link star, GP fixed after 1-20 self-ID samples: 0.00-0.39 completion on
  the hard nominal model, 0.94-0.96 with the mirror; experiments/ekm_study.py).
  With the mirror the slope at ``da = 0`` is the finite difference ``y / da``
  along ``da``, and the control model is the GP's odd part in ``da``,
  ``(g(q, da) - g(q, -da)) / 2``: same slope, zero at ``da = 0`` (the GP
  alone is odd only while no mirrored pair is split by the novelty
  projection; a split pair left offsets of 2-8 mm, a stall beyond the 2 mm
  tolerance). Not in the seed; both are offered.
* ``"absolute"``: the residual of forward kinematics, input ``q`` (``n``),
  target ``(p(q) - p(q0)) - (p_nom(q) - p_nom(q0))`` (task position relative
  to the start ``q0``; the camera's displacement ``p(q) - p(q0)`` is the sum of
  the observed ``V``, so a constant residual ``g(q0)`` drops out, as it does
  from every Jacobian). Control Jacobian ``J_nom(q) + dg/dq(q)``. Position
  tasks only (task dimension 2 or 3).

Control: :func:`follow` runs the Eq. 10-11 controller of
:mod:`selfid_jax.control.qp` with that Jacobian at every step, in one of two
modes: ``"fixed"`` (GP learned during self-ID only) or ``"online"`` (also
from every executed control step, as in the seed's look-and-move loop).

Behind the estimator protocol (:func:`ekm`, ``baselines.make("ekm", ...)``),
``update(state, dtheta, V)`` gets no configuration, so the state dead-reckons
it from ``q0`` (``q <- q + dtheta``: exact unless ``System.apply`` clipped the
step at a joint limit), and ``estimate`` is the pseudo-inverse of the control
Jacobian at ``q0``. The protocol extension that would remove the dead
reckoning is a configuration argument to ``update``/``estimate``.

Defaults (stated; all traced numbers): RBF kernel, lengthscale
``length_q = 1.0`` rad on ``q`` and ``length_da = 0.2`` rad on ``da`` (4x the
2-link self-ID magnitude), signal sd ``signal = 0.1`` task units, noise sd
``noise = 1e-3`` task units, ``novelty_tol = 1e-4``; GP capacity = the
estimator's ``capacity``. Float64 (the SOGP needs it).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any, Literal, NamedTuple, Protocol, runtime_checkable

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from selfid_jax.baselines import sogp
from selfid_jax.baselines.base import Estimator, assemble, check_bool, check_choice, check_number
from selfid_jax.control import qp as qp_control
from selfid_jax.control.loop import FollowResult
from selfid_jax.control.task import DEFAULT_STEPS, ControllerParams
from selfid_jax.identify.estimator import guarded_update
from selfid_jax.math.checks import check_array, check_positive_int
from selfid_jax.math.linalg import pseudo_inverse
from selfid_jax.systems.kinematics import ChainModel
from selfid_jax.systems.system import System

FORMULATIONS: tuple[Literal["incremental", "absolute"], ...] = ("incremental", "absolute")
MODES: tuple[Literal["fixed", "online"], ...] = ("fixed", "online")

__all__ = ["FORMULATIONS", "MODES", "EKMModel", "EKMState", "nominal_system", "model", "init", "observe",
           "linearise", "update", "fold", "follow", "ekm"]


# ------------------------------------------------------------------------------------ nominal model
@dataclasses.dataclass(frozen=True)
class OffsetPose:
    """``pose(params, q) = inner(params[0], q + params[1])``: a pose map read with joint offsets (rad or m)."""

    inner: Callable[[Any, jax.Array], tuple[jax.Array, jax.Array]]

    def __call__(self, params, q):
        return self.inner(params[0], q + params[1])


@runtime_checkable
class _JacobianPose(Protocol):
    """A pose map that also gives its geometric Jacobian ``(6, n)`` (as ``ChainSitePose``, ``EtsPose``)."""

    def __call__(self, params: Any, q: jax.Array) -> tuple[jax.Array, jax.Array]: ...

    def jacobian(self, params: Any, q: jax.Array) -> jax.Array: ...

    def pose_and_jacobian(self, params: Any, q: jax.Array) -> tuple[tuple[jax.Array, jax.Array], jax.Array]: ...


@dataclasses.dataclass(frozen=True)
class OffsetChainPose(OffsetPose):
    """:class:`OffsetPose` of a pose map with an analytic ``jacobian`` (``d(q + offset)/dq = I``)."""

    inner: _JacobianPose

    def jacobian(self, params, q):
        return self.inner.jacobian(params[0], q + params[1])

    def pose_and_jacobian(self, params, q):
        return self.inner.pose_and_jacobian(params[0], q + params[1])


def nominal_system(system: System, *, scale: ArrayLike = 1.0, offset: ArrayLike = 0.0) -> System:
    """``system`` with wrong parameters: the E-KM's nominal model (a copy; no system file is edited).

    Args:
      system: the true system.
      scale: length factors. Array ``params`` (the 2-link arm's link lengths
        ``(l1, l2)``): ``params * scale``, ``scale`` () or ``params.shape``. A
        :class:`~selfid_jax.systems.kinematics.ChainModel` (the UR5e, MJCF
        chains: its ``body_pos`` rows are the DH ``d``/``a`` offsets): ``body_pos
        * scale[:, None]``, ``scale`` () or ``(nbody,)``. Other ``params`` (an
        ``mjx.Model``) only take ``scale = 1``.
      offset: joint offsets, () or ``(n_act,)`` actuator units (rad): the
        nominal pose at ``q`` is the true map's at ``q + offset`` (the DH
        ``theta`` offsets).
    """
    params = system.params
    if not (np.ndim(offset) == 0 or np.shape(offset) == (system.n_act,)):
        raise ValueError(f"nominal_system: offset: expected shape () or ({system.n_act},), got {np.shape(offset)}")
    if isinstance(params, ChainModel):
        nb = params.body_pos.shape[0]
        if not (np.ndim(scale) == 0 or np.shape(scale) == (nb,)):
            raise ValueError(f"nominal_system: scale: expected shape () or ({nb},) for a ChainModel, "
                             f"got {np.shape(scale)}")
        params = params.replace(body_pos=params.body_pos * jnp.broadcast_to(jnp.asarray(scale), (nb,))[:, None])
    elif isinstance(params, (jax.Array, np.ndarray)):
        if not (np.ndim(scale) == 0 or np.shape(scale) == np.shape(params)):
            raise ValueError(f"nominal_system: scale: expected shape () or {np.shape(params)}, got {np.shape(scale)}")
        params = params * jnp.asarray(scale, params.dtype)
    elif not (np.ndim(scale) == 0 and float(scale) == 1.0):  # type: ignore[arg-type]  # ArrayLike admits complex
        raise ValueError("nominal_system: scale: only array or ChainModel params can be scaled, "
                         f"not {type(params).__name__}")
    pose_fn = system.pose_fn
    if pose_fn is None:  # only the placeholder of the dataclass default
        raise TypeError(f"nominal_system: System {system.name!r} has no pose_fn: build one with from_pose_fn or "
                        "make_system")
    wrapped = OffsetChainPose(pose_fn) if isinstance(pose_fn, _JacobianPose) else OffsetPose(pose_fn)
    off = jnp.broadcast_to(jnp.asarray(offset, system.q_low.dtype), (system.n_act,))
    return system.replace(params=(params, off), pose_fn=wrapped, name=f"{system.name}_nominal")


# ------------------------------------------------------------------------------------ the model
@dataclasses.dataclass(frozen=True)
class EKMModel:
    """The E-KM's fixed parts: the nominal :class:`System` and the GP settings (traced), the formulation (static)."""

    nominal: System
    length_q: jax.Array | float  # () GP lengthscale on q [rad]
    length_da: jax.Array | float  # () GP lengthscale on da [rad] (incremental)
    signal: jax.Array | float  # () GP signal sd [task units]
    noise: jax.Array | float  # () GP noise sd [task units]
    novelty_tol: jax.Array | float  # () SOGP novelty threshold, relative to signal^2
    formulation: str = dataclasses.field(default="incremental", metadata=dict(static=True))
    symmetric: bool = dataclasses.field(default=True, metadata=dict(static=True))  # incremental: mirror samples


jax.tree_util.register_dataclass(
    EKMModel, data_fields=["nominal", "length_q", "length_da", "signal", "noise", "novelty_tol"],
    meta_fields=["formulation", "symmetric"])


class EKMState(NamedTuple):
    """State of an E-KM: the GP and where the arm is (``n`` actuators, ``m`` task dimensions)."""

    gp: sogp.SOGPState  # residual GP: input n (absolute) or 2n (incremental), output m
    q0: jax.Array  # (n,) start configuration: where estimate() reads and follow() starts [rad]
    q: jax.Array  # (n,) current configuration (dead-reckoned behind the protocol) [rad]
    s: jax.Array  # (m,) task displacement p(q) - p(q0), the sum of observed V [task units]
    p0_nom: jax.Array  # (m,) nominal task position at q0 [task units]
    count: jax.Array  # type: ignore[assignment]  # () int32 accepted samples
    rejected: jax.Array  # () int32 rejected samples


def model(nominal: System, *, formulation: Literal["incremental", "absolute"] = "incremental", symmetric: bool = True,
          length_q=1.0, length_da=0.2, signal=0.1, noise=1e-3, novelty_tol=1e-4) -> EKMModel:
    """An :class:`EKMModel` (module docstring: formulations, defaults); checks the options eagerly."""
    symmetric = check_bool("ekm", "symmetric", symmetric)
    if not isinstance(nominal, System):
        raise ValueError(f"ekm: nominal: expected a System (see ekm.nominal_system), got {nominal!r}")
    formulation = check_choice("ekm", "formulation", formulation, FORMULATIONS)
    if formulation == "absolute" and nominal.task_dim not in (2, 3):
        raise ValueError(f"ekm: formulation='absolute' needs a position task (task_dim 2 or 3), got {nominal.task_dim}")
    for name, v in (("length_q", length_q), ("length_da", length_da), ("signal", signal), ("noise", noise),
                    ("novelty_tol", novelty_tol)):
        check_number("ekm", name, v)
    return EKMModel(nominal, length_q, length_da, signal, noise, novelty_tol, formulation, symmetric)


def _task_pos(nominal: System, q):
    return nominal.pose(q)[0][: nominal.task_dim]


def init(mdl: EKMModel, q0, *, capacity: int = 30) -> EKMState:
    """An E-KM with an empty GP of ``capacity`` basis elements at the start ``q0 (n,)`` (absolute: knows
    ``g(q0) = 0``)."""
    nom = mdl.nominal
    n, m = nom.n_act, nom.task_dim
    check_array("q0", q0, (n,))
    capacity = check_positive_int("ekm: capacity", capacity)
    dtype = jnp.result_type(float)
    q0 = jnp.asarray(q0, dtype)
    incremental = mdl.formulation == "incremental"
    ls = jnp.concatenate([jnp.full((n,), mdl.length_q, dtype), jnp.full((n,), mdl.length_da, dtype)]) if incremental \
        else jnp.full((n,), mdl.length_q, dtype)
    gp = sogp.init(ls.shape[0], m, capacity=capacity, kernel=sogp.RBF(ls, jnp.asarray(mdl.signal, dtype) ** 2),
                   noise=jnp.asarray(mdl.noise, dtype), novelty_tol=jnp.asarray(mdl.novelty_tol, dtype), dtype=dtype)
    if not incremental:
        gp = sogp.update(gp, q0, jnp.zeros((m,), dtype))
        gp = gp._replace(count=jnp.zeros((), jnp.int32))
    zero = jnp.zeros((), jnp.int32)
    return EKMState(gp, q0, q0, jnp.zeros((m,), dtype), _task_pos(nom, q0), zero, zero)


def observe(mdl: EKMModel, state: EKMState, q, da, V) -> EKMState:
    """Learn from one executed step: from ``q (n,)`` the actuators moved by ``da (n,)`` and the task by ``V (m,)``.

    Incremental: GP sample ``([q, da], V - J_nom(q) da)`` (Eq. 9), and with
    ``symmetric`` its mirror ``([q, -da], -(V - J_nom(q) da))``. Absolute:
    ``s <- s + V`` and sample ``(q + da, s - (p_nom(q + da) - p_nom(q0)))``.
    Then ``state.q = q + da``.
    """
    nom = mdl.nominal
    q_new = q + da
    if mdl.formulation == "incremental":
        y = V - nom.jacobian(q) @ da
        gp = sogp.update(state.gp, jnp.concatenate([q, da]), y)
        if mdl.symmetric:
            gp = sogp.update(gp, jnp.concatenate([q, -da]), -y)
            gp = gp._replace(count=jnp.minimum(gp.count, state.gp.count + 1))  # one sample, fed twice
        s = state.s
    else:
        s = state.s + V
        gp = sogp.update(state.gp, q_new, s - (_task_pos(nom, q_new) - state.p0_nom))
    return state._replace(gp=gp, q=q_new, s=s)


def linearise(mdl: EKMModel, state: EKMState, q) -> tuple[jax.Array, jax.Array]:
    """The control model at ``q (n,)``: ``V ~ offset (m,) + J (m, n) da`` (the GP linearised at ``da = 0``).

    Incremental: ``J = J_nom(q) + dg/dda(q, 0)``, ``offset = g(q, 0)`` (0 with
    ``symmetric``: the odd part). Absolute: ``J = J_nom(q) + dg/dq(q)``, ``offset = 0``.
    """
    nom = mdl.nominal
    J_nom = nom.jacobian(q)
    if mdl.formulation == "incremental":
        n = nom.n_act
        g = lambda da: sogp.mean(state.gp, jnp.concatenate([q, da]))
        zero = jnp.zeros((n,), J_nom.dtype)
        # symmetric: the model is the odd part (g(q, da) - g(q, -da)) / 2, zero at da = 0 (same slope there)
        offset = jnp.zeros_like(J_nom[:, 0]) if mdl.symmetric else g(zero)
        return J_nom + jax.jacfwd(g)(zero), offset
    dg = jax.jacfwd(lambda x: sogp.mean(state.gp, x))(q)
    return J_nom + dg, jnp.zeros((nom.task_dim,), J_nom.dtype)


def fold(mdl: EKMModel, state: EKMState, dthetas, Vs) -> EKMState:
    """Fold a self-ID stream ``dthetas (T, n)``, ``Vs (T, m)`` from ``state.q`` (dead-reckoned), under ``lax.scan``."""
    return jax.lax.scan(lambda s, x: (update(mdl, s, *x), None), state, (dthetas, Vs))[0]


def follow(mdl: EKMModel, state: EKMState, system: System, path, controller: ControllerParams = ControllerParams(),
           *, mode: Literal["fixed", "online"] = "fixed", weights=1.0, steps: int = DEFAULT_STEPS,
           qp_iters: int = 20) -> tuple[FollowResult, EKMState]:
    """Follow ``path (W, m)`` on the true ``system`` from ``state.q0`` with the E-KM and the Eq. 10-11 controller.

    The arm is back at ``q0`` (``q = q0``, ``s = 0``); each step linearises the
    E-KM at the current ``q`` (:func:`linearise`) and solves the QP
    (:func:`selfid_jax.control.qp.follow`, weights ``weights``, box: joint
    limits and ``dq_max``). ``mode="online"`` also learns from every executed
    step (:func:`observe`). Returns the metrics and the final E-KM state.
    """
    mode = check_choice("ekm", "mode", mode, MODES)
    start = state._replace(q=state.q0, s=jnp.zeros_like(state.s))
    obs = (lambda st, q, da, V: observe(mdl, st, q, da, V)) if mode == "online" else None
    return qp_control.follow(system, lambda st, q: linearise(mdl, st, q), start, path, state.q0, controller,
                             observe=obs, weights=weights, steps=steps, qp_iters=qp_iters)


def update(mdl: EKMModel, state: EKMState, dtheta, V) -> EKMState:
    """One self-ID sample ``dtheta (n,)``, ``V (m,)`` from the dead-reckoned ``state.q``; an invalid one
    (non-finite, or all-zero ``dtheta`` or ``V``) only bumps ``rejected`` (the protocol's sample screen)."""
    n, m = mdl.nominal.n_act, mdl.nominal.task_dim
    return guarded_update(lambda s, d, v: observe(mdl, s, s.q, d, v), state, dtheta, V, shape=(n, m),
                          dtype=state.s.dtype)


# ------------------------------------------------------------------------------------ the estimator protocol
def ekm(
    *,
    nominal: System | None = None,
    q0: ArrayLike | None = None,
    formulation: Literal["incremental", "absolute"] = "incremental",
    mode: Literal["fixed", "online"] = "fixed",
    symmetric: bool = True,
    length_q: ArrayLike = 1.0,
    length_da: ArrayLike = 0.2,
    signal: ArrayLike = 0.1,
    noise: ArrayLike = 1e-3,
    novelty_tol: ArrayLike = 1e-4,
) -> Estimator:
    """E-KM behind the estimator protocol: ``pinv(J_nom(q0) + dg)`` ``(n, m)`` after the self-ID samples.

    State: :class:`EKMState` (GP of ``capacity`` basis elements). ``update``
    dead-reckons the configuration from ``q0``; ``estimate`` reads the
    control Jacobian at ``q0`` (``truth`` unused). ``mode`` is read by
    :func:`follow` (the model-based rollout), not by the estimate.

    Args:
      nominal: the nominal :class:`System` (:func:`nominal_system`); may be
        ``None`` to validate options only: ``init`` then raises.
      q0: ``(n,)`` start configuration [rad] (may be traced); ``init`` raises if ``None``.
      formulation, mode: ``"incremental"``/``"absolute"``, ``"fixed"``/``"online"``.
      symmetric: incremental formulation: also feed each sample's mirror (module docstring).
      length_q, length_da, signal, noise, novelty_tol: GP settings (module docstring).
    """
    check_choice("ekm", "mode", mode, MODES)
    check_choice("ekm", "formulation", formulation, FORMULATIONS)
    settings: dict[str, Any] = dict(formulation=formulation, symmetric=check_bool("ekm", "symmetric", symmetric),
                                    length_q=length_q, length_da=length_da, signal=signal, noise=noise,
                                    novelty_tol=novelty_tol)
    mdl = None if nominal is None else model(nominal, **settings)
    if nominal is None:
        for name in ("length_q", "length_da", "signal", "noise", "novelty_tol"):
            check_number("ekm", name, settings[name])

    def nominal_model() -> EKMModel:
        """The model of ``nominal``; without one, no state exists (``init`` raises here first)."""
        if mdl is None:
            raise ValueError("ekm: nominal: init needs the nominal System: "
                             "ekm(nominal=ekm.nominal_system(system, ...))")
        return mdl

    def init_fn(n, m, key, capacity, dtype):
        ekm_model = nominal_model()
        if q0 is None:
            raise ValueError("ekm: q0: init needs the start configuration q0 (n,): ekm(nominal=..., q0=...)")
        if (n, m) != (ekm_model.nominal.n_act, ekm_model.nominal.task_dim):
            raise ValueError(f"ekm: init for (n, m) = ({n}, {m}) but the nominal system has "
                             f"({ekm_model.nominal.n_act}, {ekm_model.nominal.task_dim})")
        if np.dtype(dtype) != np.float64:
            raise ValueError(f"ekm: needs float64 (its SOGP does), got {np.dtype(dtype)}: enable jax_enable_x64")
        return init(ekm_model, q0, capacity=capacity)

    def fold_fn(state, dtheta, V):
        return observe(nominal_model(), state, state.q, dtheta, V)

    def read(state, truth):
        J, _ = linearise(nominal_model(), state, state.q0)
        return pseudo_inverse(J)

    return assemble("ekm", init=init_fn, fold=fold_fn, read=read,
                    ref=lambda s: jnp.zeros(s.q0.shape[-1:] + s.s.shape[-1:], s.s.dtype))
