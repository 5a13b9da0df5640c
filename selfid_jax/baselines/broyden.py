"""Broyden rank-1 secant updates of the inverse Jacobian.

``"broyden"``: after each sample, ``J <- J + step * (dtheta - J V) V^T / (V^T V)``.

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

Static option ``init``: ``"zero"`` (default) | ``"identity"`` (``init_scale *
eye(n, m)``). Traced parameters: ``step`` (relaxation in ``(0, 2)``, default 1),
``init_scale`` (actuator per task unit).

NaN-safe: the update is computed with ``V`` scaled by its largest magnitude, so
``V^T V`` cannot underflow to 0, and an update that is not finite anyway (``V``
so tiny that the residual overflows) leaves ``J`` unchanged.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp

from selfid_jax.baselines.base import Family

INITS = ("zero", "identity")


class BroydenState(NamedTuple):
    J: jax.Array  # (n, m) float: current inverse-Jacobian estimate, actuator per task unit
    count: jax.Array  # () int32: accepted samples
    rejected: jax.Array  # () int32: rejected samples
    params: dict  # {"step": (), "init_scale": ()}

    @property
    def shape_ref(self) -> jax.Array:
        return self.J


def secant_update(J, dtheta, V, step=1.0):
    """One Broyden/Kaczmarz step ``J + step (dtheta - J V) V^T / (V^T V)`` on ``J (n, m)``; ``J`` if not finite."""
    s = jnp.max(jnp.abs(V))
    safe_s = jnp.where(s > 0, s, 1.0)
    u = V / safe_s  # max |u| = 1, so u.u in [1, m]
    resid = dtheta - J @ V
    J_new = J + step * (resid / safe_s)[:, None] * (u / jnp.sum(u * u))[None, :]
    good = (s > 0) & jnp.all(jnp.isfinite(J_new))
    return jnp.where(good, J_new, J)


def _init(n, m, key, capacity, dtype, static, params):
    if static["init"] == "identity":
        J = params["init_scale"] * jnp.eye(n, m, dtype=dtype)
    else:
        J = jnp.zeros((n, m), dtype)
    return BroydenState(J=J, count=jnp.zeros((), jnp.int32), rejected=jnp.zeros((), jnp.int32), params=params)


def _update(state, dtheta, V, static):
    return state._replace(J=secant_update(state.J, dtheta, V, state.params["step"]))


def _estimate(state, truth, static):
    return state.J


def _validate(static):
    if static["init"] not in INITS:
        raise ValueError(f"init: expected one of {INITS}, got {static['init']!r}")


FAMILIES = {
    "broyden": Family(
        init=_init,
        update=_update,
        estimate=_estimate,
        static_defaults={"init": "zero"},
        param_defaults={"step": 1.0, "init_scale": 1.0},
        validate=_validate,
    )
}
