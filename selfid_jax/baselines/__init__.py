"""Inverse-Jacobian estimation methods for the ablation (Sec. V-A, Fig. 5), behind one interface.

``method = get_method(name, **options)`` (``name`` in :data:`METHOD_NAMES`) gives a
static, hashable :class:`Method` with ``init(n, m, key, *, capacity)``,
``update(state, dtheta, V)`` and ``estimate(state, truth)``; :func:`run_stream`
runs one over a sample stream. One module per method family:

* :mod:`~selfid_jax.baselines.ours`: ``"ours"``, the paper's signed x magnitude
  guess refined by least squares (Eq. 6-14);
* :mod:`~selfid_jax.baselines.direct`: ``"direct"``, Eq. 14 from a fixed start;
* :mod:`~selfid_jax.baselines.oracle`: ``"sign_true_mag"`` and ``"true"``;
* :mod:`~selfid_jax.baselines.broyden`: ``"broyden"``, rank-1 secant updates;
* :mod:`~selfid_jax.baselines.rls`: ``"rls"``, recursive least squares with forgetting;
* :mod:`~selfid_jax.baselines.kalman`: ``"kalman"``, a Kalman filter on ``vec(J)``;
* :mod:`~selfid_jax.baselines.particle`: ``"particle"``, a particle filter over ``J``.
"""

from selfid_jax.baselines import broyden, direct, kalman, oracle, ours, particle, rls
from selfid_jax.baselines.base import METHOD_NAMES, Family, Method, accept, get_method, run_stream, scan

__all__ = [
    "METHOD_NAMES",
    "Family",
    "Method",
    "accept",
    "broyden",
    "direct",
    "get_method",
    "kalman",
    "oracle",
    "ours",
    "particle",
    "rls",
    "run_stream",
    "scan",
]
