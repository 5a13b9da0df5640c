"""The paper's estimator and its direct-optimisation baseline: Eq. 14 on the buffered self-ID samples.

:func:`ours`: the signed x magnitude guess (Eq. 6-13) refined by least squares
(Eq. 14), with the magnitude variant of :mod:`selfid_jax.identify.magnitude`
selectable. :func:`direct`: Eq. 14 from a fixed start (zero or random) instead
of the signed x magnitude guess, the first baseline of Sec. V-A.

Both fold samples with :func:`selfid_jax.identify.estimator.accumulate` (sign weights,
magnitude sums and the statistics ``S_vv``, ``S_tv`` of Eq. 14, in constant
memory); the state of ``ours`` is the
:class:`~selfid_jax.identify.estimator.EstimatorState` itself, and ``direct`` adds its
start ``J_init`` next to one. Their refinements (closed form, gradient steps,
sign projection) read the statistics and so cover every accepted sample; only
the buffered magnitude variants of ``ours`` (median, weighted, Kalman) keep a
ring buffer of the last ``capacity`` samples. With ``>= m`` independent
samples and a converged refinement, Eq. 14 has one solution whatever the start
is, so ``ours`` equals ``direct``; they differ with fewer samples than task
dimensions or under an early-stopped refinement (``refine_steps``).
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from selfid_jax.baselines.base import (
    Estimator,
    assemble,
    check_bool,
    check_choice,
    check_count,
    check_number,
)
from selfid_jax.identify import estimator
from selfid_jax.identify import magnitude as _magnitude
from selfid_jax.identify.estimator import EstimatorState
from selfid_jax.identify.refine import refine as _refine

RefineMethod = Literal["closed_form", "optax"]
REFINE_METHODS: tuple[RefineMethod, ...] = ("closed_form", "optax")
INITS: tuple[Literal["zero", "random"], ...] = ("zero", "random")


class DirectState(NamedTuple):
    """State of :func:`direct`: the paper's estimator state (buffer and counters) and a fixed start."""

    est: EstimatorState  # statistics of Eq. 14 (no buffer); its count/rejected count the samples
    J_init: jax.Array  # (n, m) float: start of the refinement, actuator per task unit (fixed for the stream)


def refine_from(est: EstimatorState, J0, *, refine_method: str, refine_steps: int | None, sign_project: bool):
    """Eq. 14 refinement ``(n, m)`` of the start ``J0 (n, m)`` on the statistics of ``est`` (every accepted sample).

    ``refine_steps = k``: ``k`` steps of plain Nesterov gradient descent
    (``refine(method="optax", precondition=False)``); otherwise
    ``refine_method``: ``"closed_form"`` (min-norm least squares from ``J0``)
    or ``"optax"`` (preconditioned gradient descent, 100 steps). ``sign_project``
    projects the gradient iterates onto the signed inverse Jacobian.
    """
    if refine_steps is not None:
        return _refine(est, J0, method="optax", steps=refine_steps, precondition=False, sign_project=sign_project)
    if refine_method == "closed_form" and not sign_project:
        return _refine(est, J0, method="closed_form")
    return _refine(est, J0, method="optax", sign_project=sign_project)


def _check_refine(method: str, refine_method, refine_steps) -> tuple[RefineMethod, int | None]:
    return (
        check_choice(method, "refine_method", refine_method, REFINE_METHODS),
        check_count(method, "refine_steps", refine_steps, allow_none=True),
    )


def _accumulate_est(state: DirectState, dtheta, V) -> DirectState:
    return state._replace(est=estimator.accumulate(state.est, dtheta, V))


def _tally_est(state: DirectState, ok) -> DirectState:
    return state._replace(est=estimator.tally(state.est, ok))


def _fits_est(state: DirectState, dtheta, V):
    return estimator.fits(state.est, dtheta, V)


def ours(
    *,
    magnitude: Literal["mean", "median", "weighted", "kalman"] = "mean",
    refine: bool = True,
    refine_method: Literal["closed_form", "optax"] = "closed_form",
    refine_steps: int | None = None,
    sign_project: bool = False,
    v_tol: ArrayLike = 1e-9,
    magnitude_q: ArrayLike = 1e-2,
    magnitude_r: ArrayLike = 1.0,
    forget: ArrayLike = 1.0,
) -> Estimator:
    """The paper's estimator: ``refine(signed * magnitude)`` ``(n, m)`` (Eq. 6-14).

    State: the :class:`~selfid_jax.identify.estimator.EstimatorState`, constant-size
    (no sample buffer, whatever ``capacity`` ``init`` is given) unless the
    magnitude variant reads samples (median, weighted, Kalman: the last
    ``capacity`` samples). Estimate: ``J0 = signed * magnitude`` (Eq. 13), then
    refined by least squares over every accepted sample (Eq. 14, from the
    statistics ``S_vv``, ``S_tv``).

    Args:
      magnitude: the magnitude inverse Jacobian: ``"mean"`` (the paper's
        Eq. 12, over every accepted sample), ``"median"``, ``"weighted"`` or
        ``"kalman"`` (over the buffer; :mod:`selfid_jax.identify.magnitude`).
      refine: ``False`` returns ``J0`` itself (Eq. 13 alone).
      refine_method: ``"closed_form"`` (min-norm least squares from ``J0``) or
        ``"optax"`` (preconditioned gradient descent, 100 steps).
      refine_steps: ``None``, or a step budget ``k``: ``k`` steps of plain
        Nesterov gradient descent, an early-stopped refinement as the paper's
        SLSQP stopping at its tolerance; overrides ``refine_method``. Under a
        small budget the start ``J0`` matters.
      sign_project: project the gradient iterates onto the signed inverse
        Jacobian; needs a gradient refinement (``refine_method="optax"`` or
        ``refine_steps``).
      v_tol: task units; ``|V_j|`` at or below it does not enter the magnitude
        ratio (Eq. 11). May be traced.
      magnitude_q, magnitude_r: dimensionless process and measurement noise
        variances of the ``"kalman"`` magnitude, relative to the running
        estimate (:func:`selfid_jax.identify.magnitude.kalman`). May be traced.
      forget: exponential forgetting factor in ``(0, 1]`` of the sums
        (:func:`selfid_jax.identify.estimator.init`); 1 (default) never forgets. May be
        traced.
    """
    name = "ours"
    magnitude = check_choice(name, "magnitude", magnitude, _magnitude.VARIANTS)
    refine = check_bool(name, "refine", refine)
    refine_method, refine_steps = _check_refine(name, refine_method, refine_steps)
    sign_project = check_bool(name, "sign_project", sign_project)
    if sign_project and refine_method == "closed_form" and refine_steps is None:
        raise ValueError(
            f"{name}: sign_project: True needs a gradient refinement: refine_method='optax' or refine_steps, "
            f"got refine_method={refine_method!r}, refine_steps=None"
        )
    for option, value in (("v_tol", v_tol), ("magnitude_q", magnitude_q), ("magnitude_r", magnitude_r),
                          ("forget", forget)):
        check_number(name, option, value)
    buffered = magnitude in _magnitude.BUFFERED

    def init(n, m, key, capacity, dtype):
        if buffered and capacity == 0:
            raise ValueError(f"{name}: magnitude {magnitude!r} reads the last `capacity` samples: capacity must be "
                             "> 0, got 0")
        return estimator.init(n, m, capacity=capacity if buffered else 0, v_tol=v_tol, forget=forget, dtype=dtype)

    def read(state: EstimatorState, truth):
        if magnitude == "kalman":
            mag = _magnitude.kalman(state, q=magnitude_q, r=magnitude_r)
        else:
            mag = _magnitude.get(magnitude)(state)
        J0 = estimator.signed_inverse_jacobian(state) * mag  # Eq. 13
        if not refine:
            return J0
        return refine_from(
            state, J0, refine_method=refine_method, refine_steps=refine_steps, sign_project=sign_project
        )

    return assemble(name, init=init, fold=estimator.accumulate, read=read, ref=lambda s: s.sign_net,
                    admit=estimator.fits, zero_is_identity=True)


def direct(
    *,
    init: Literal["zero", "random"] = "zero",
    init_scale: ArrayLike = 1.0,
    refine_method: Literal["closed_form", "optax"] = "closed_form",
    refine_steps: int | None = None,
    v_tol: ArrayLike = 1e-9,
    forget: ArrayLike = 1.0,
) -> Estimator:
    """Direct optimisation: ``argmin_J sum_k ||dtheta_k - J V_k||^2`` ``(n, m)`` from a fixed start (Eq. 14).

    State: :class:`DirectState` (the estimator's constant-size statistics, no
    sample buffer, and the start ``J_init (n, m)``). From zero, the closed form is the minimum-norm
    least-squares solution ``Theta pinv(V)``: the same as :func:`ours` whenever
    Eq. 14 has one solution (``>= m`` independent samples).

    Args:
      init: the start ``J_init``: ``"zero"``, or ``"random"``
        (``init_scale * N(0, 1)`` per element, drawn from the key given to
        ``init``, which then must not be ``None``; fixed for the stream).
      init_scale: actuator per task unit; the random start's standard
        deviation. May be traced.
      refine_method, refine_steps: as for :func:`ours`.
      v_tol: task units; the estimator's Eq. 11 threshold. It does not
        change this method's estimate (kept for configurations that set it).
      forget: exponential forgetting factor in ``(0, 1]`` of the statistics, as
        for :func:`ours`. May be traced.
    """
    name = "direct"
    start = check_choice(name, "init", init, INITS)
    refine_method, refine_steps = _check_refine(name, refine_method, refine_steps)
    check_number(name, "init_scale", init_scale)
    check_number(name, "v_tol", v_tol)
    check_number(name, "forget", forget)

    def init_fn(n, m, key, capacity, dtype):
        if start == "random":
            if key is None:
                raise ValueError("direct: init='random' needs a PRNG key (jax.random.key)")
            J_init = jnp.asarray(init_scale, dtype) * jax.random.normal(key, (n, m), dtype)
        else:
            J_init = jnp.zeros((n, m), dtype)
        est = estimator.init(n, m, capacity=0, v_tol=v_tol, forget=forget, dtype=dtype)
        return DirectState(est=est, J_init=J_init)

    def read(state: DirectState, truth):
        return refine_from(
            state.est, state.J_init, refine_method=refine_method, refine_steps=refine_steps, sign_project=False
        )

    return assemble(name, init=init_fn, fold=_accumulate_est, read=read, ref=lambda s: s.J_init, tally=_tally_est,
                    admit=_fits_est, zero_is_identity=True)
