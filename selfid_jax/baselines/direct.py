"""Direct optimisation of the inverse Jacobian from self-ID data (the first baseline of Sec. V-A).

``"direct"``: Eq. 14, ``argmin_J sum_k ||dtheta_k - J V_k||^2`` over the
buffered samples, started from a fixed ``J_init (n, m)`` instead of the
signed x magnitude guess.

Static options:
  ``init``: ``"zero"`` (default) | ``"random"`` (``init_scale * N(0, 1)`` per
    element, drawn from the key at ``init`` and fixed for the whole stream).
  ``refine_method``, ``refine_steps``: as for ``"ours"``
    (:mod:`selfid_jax.baselines.ours`).
Traced parameters: ``init_scale`` (inverse-Jacobian units, actuator per task
unit), ``v_tol`` (unused by the estimate; kept for the shared buffer).

From zero, the closed form is the minimum-norm least-squares solution
``Theta pinv(V)``: the same as ``"ours"`` whenever Eq. 14 has one solution
(``>= m`` independent samples). Only an early-stopped refinement
(``refine_steps``) or an underdetermined buffer tells the two apart.
"""

from __future__ import annotations

import jax

from selfid_jax.baselines.base import Family
from selfid_jax.baselines.ours import buffer_init, buffer_update, refine_from, validate_refine

INITS = ("zero", "random")


def _init(n, m, key, capacity, dtype, static, params):
    J_init = None
    if static["init"] == "random":
        if key is None:
            raise ValueError("direct: init='random' needs a PRNG key (jax.random.key)")
        J_init = params["init_scale"] * jax.random.normal(key, (n, m), dtype)
    return buffer_init(n, m, capacity, dtype, params, J_init)


def _estimate(state, truth, static):
    return refine_from(state.est, state.J_init, static)


def _validate(static):
    if static["init"] not in INITS:
        raise ValueError(f"init: expected one of {INITS}, got {static['init']!r}")
    validate_refine(static)


FAMILIES = {
    "direct": Family(
        init=_init,
        update=buffer_update,
        estimate=_estimate,
        static_defaults={"init": "zero", "refine_method": "closed_form", "refine_steps": None},
        param_defaults={"init_scale": 1.0, "v_tol": 1e-9},
        validate=_validate,
    )
}
