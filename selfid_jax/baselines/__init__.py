"""Inverse-Jacobian estimation methods for the ablation (Sec. V-A, Fig. 5), behind one protocol.

Each method is a factory with keyword-only options that returns an
:class:`Estimator`, a ``NamedTuple`` of pure functions in the manner of optax::

    est = rls(lam=0.99)                       # or make("rls", lam=0.99), by name
    state = est.init(n, m, key, capacity=64)  # NamedTuple of fixed-shape arrays
    state = est.update(state, dtheta, V)      # one sample, (n,) and (m,)
    J = est.estimate(state, truth)            # (n, m); truth is read by the oracles only
    estimates = run_stream(est, key, dthetas, Vs, truth)   # (T, n, m)

Structural options are checked when the factory is called; numeric options may
be traced values (``jax.jit(lambda lam: run_stream(rls(lam=lam), ...))``
compiles once for every ``lam``). Invalid samples (non-finite, or all-zero
``dtheta`` or ``V``) only bump the state's ``rejected`` counter, for every
method alike (:mod:`~selfid_jax.baselines.base`). The methods
(:data:`METHODS`, names :data:`METHOD_NAMES`):

* :func:`ours` (:mod:`~selfid_jax.baselines.paper`): the paper's signed x
  magnitude guess refined by least squares (Eq. 6-14);
* :func:`direct` (:mod:`~selfid_jax.baselines.paper`): Eq. 14 from a fixed start;
* :func:`sign_true_mag` and :func:`true` (:mod:`~selfid_jax.baselines.oracle`):
  the estimated signs times the true magnitudes, and the truth itself;
* :func:`broyden` (:mod:`~selfid_jax.baselines.secant`): rank-1 secant updates;
* :func:`rls` (:mod:`~selfid_jax.baselines.filters`): recursive least squares
  with forgetting;
* :func:`kalman` (:mod:`~selfid_jax.baselines.filters`): a Kalman filter on ``vec(J)``;
* :func:`particle` (:mod:`~selfid_jax.baselines.particle_filter`): a particle
  filter over ``J``.
"""

from selfid_jax.baselines import (
    base,
    filters,
    oracle,
    paper,
    particle_filter,
    registry,
    secant,
)
from selfid_jax.baselines.base import Estimator, assemble, run_stream, scan
from selfid_jax.baselines.filters import kalman, rls
from selfid_jax.baselines.oracle import sign_true_mag, true
from selfid_jax.baselines.paper import direct, ours
from selfid_jax.baselines.particle_filter import particle
from selfid_jax.baselines.registry import METHOD_NAMES, METHODS, make, options
from selfid_jax.baselines.secant import broyden

__all__ = [
    "METHODS",
    "METHOD_NAMES",
    "Estimator",
    "assemble",
    "base",
    "broyden",
    "direct",
    "filters",
    "kalman",
    "make",
    "options",
    "oracle",
    "ours",
    "paper",
    "particle",
    "particle_filter",
    "registry",
    "rls",
    "run_stream",
    "scan",
    "secant",
    "sign_true_mag",
    "true",
]
