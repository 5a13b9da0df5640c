"""The paper's method: estimator state and update (Eq. 6-14 statistics), magnitudes, refinement, Algorithm 1.

Modules: :mod:`~selfid_jax.identify.estimator` (the state, ``update``, Eq. 13,
the Sec. IV-D convergence record), :mod:`~selfid_jax.identify.magnitude`
(Eq. 11-12 and its variants), :mod:`~selfid_jax.identify.refine` (Eq. 14),
:mod:`~selfid_jax.identify.step` (the one per-sample step: update, initial guess, refine, record),
:mod:`~selfid_jax.identify.recursive` (Eq. 14 kept by rank-one steps once
``S_vv`` has full rank), :mod:`~selfid_jax.identify.algorithm` (Algorithm 1 on a system).
"""

from selfid_jax.identify import algorithm, estimator, magnitude, recursive, refine, step

__all__ = ["algorithm", "estimator", "magnitude", "recursive", "refine", "step"]
