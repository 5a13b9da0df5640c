"""Broyden rank-1 secant updates of the inverse Jacobian.

:func:`broyden`: after each sample, ``J <- J + step * (dtheta - J V) V^T / (V^T V)``.

Why this form: we estimate the inverse Jacobian ``J (n, m)`` directly, and each
sample gives the secant condition ``J V = dtheta``. Among all ``J'`` that satisfy
it, this update is the one closest to ``J`` in the Frobenius norm (Broyden's
"good" update applied to the inverse map ``V -> dtheta``; with ``step = 1`` it is
a Kaczmarz projection of every row of ``J`` onto the sample's hyperplane). The
classic alternatives need what we do not have: the "bad"/Sherman-Morrison form
updates the inverse of a forward Jacobian estimate, which needs ``n = m`` and
an invertible starting matrix (a zero start is impossible there). Noise-free,
``m`` mutually orthogonal ``V`` recover ``J`` exactly; generic independent ``V``
converge linearly (the error's component along each new ``V`` is removed).
Each update forgets old samples partly, so noise is not averaged away:
``step < 1`` damps it.

NaN-safe: the update is computed with ``V`` scaled by its largest magnitude, so
``V^T V`` cannot underflow to 0, and an update that is not finite anyway (``V``
so tiny that the residual overflows) leaves ``J`` unchanged.
"""

from __future__ import annotations

from typing import Literal, NamedTuple

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from selfid_jax.baselines.base import Estimator, assemble, check_choice, check_number

INITS = ("zero", "identity")


class BroydenState(NamedTuple):
    """State of :func:`broyden`."""

    J: jax.Array  # (n, m) float: current inverse-Jacobian estimate, actuator per task unit
    count: jax.Array  # type: ignore[assignment]  # () int32: accepted samples
    rejected: jax.Array  # () int32: rejected samples


def secant_update(J, dtheta, V, step=1.0):
    """One Broyden/Kaczmarz step ``J + step (dtheta - J V) V^T / (V^T V)`` on ``J (n, m)``; ``J`` if not finite."""
    s = jnp.max(jnp.abs(V))
    safe_s = jnp.where(s > 0, s, 1.0)
    u = V / safe_s  # max |u| = 1, so u.u in [1, m]
    resid = dtheta - J @ V
    J_new = J + step * (resid / safe_s)[:, None] * (u / jnp.sum(u * u))[None, :]
    good = (s > 0) & jnp.all(jnp.isfinite(J_new))
    return jnp.where(good, J_new, J)


def broyden(
    *, init: Literal["zero", "identity"] = "zero", step: ArrayLike = 1.0, init_scale: ArrayLike = 1.0
) -> Estimator:
    """Broyden (secant) estimate ``J (n, m)``: ``J <- J + step (dtheta - J V) V^T / (V^T V)`` per sample.

    State: :class:`BroydenState`.

    Args:
      init: the start: ``"zero"`` or ``"identity"`` (``init_scale * eye(n, m)``).
      step: relaxation, dimensionless, in ``(0, 2)``; 1 solves each sample's
        secant condition exactly, ``< 1`` damps noise. May be traced.
      init_scale: actuator per task unit; scale of the identity start. May be traced.
    """
    name = "broyden"
    start = check_choice(name, "init", init, INITS)
    check_number(name, "step", step)
    check_number(name, "init_scale", init_scale)

    def init_fn(n, m, key, capacity, dtype):
        if start == "identity":
            J = jnp.asarray(init_scale, dtype) * jnp.eye(n, m, dtype=dtype)
        else:
            J = jnp.zeros((n, m), dtype)
        return BroydenState(J=J, count=jnp.zeros((), jnp.int32), rejected=jnp.zeros((), jnp.int32))

    def fold(state: BroydenState, dtheta, V):
        return state._replace(J=secant_update(state.J, dtheta, V, jnp.asarray(step, state.J.dtype)))

    return assemble(name, init=init_fn, fold=fold, read=lambda state, truth: state.J, ref=lambda s: s.J)
