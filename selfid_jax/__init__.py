"""selfid_jax: model-free self-identification of inverse Jacobians in JAX.

The functional API (``import selfid_jax as sj``)::

    state = sj.init(n, m, capacity=64)
    state = sj.update(state, dtheta, V)            # one self-ID sample (Eq. 6-12)
    J0 = sj.initial_guess(state)                   # signed * magnitude (Eq. 13)
    J = sj.refine(state, J0, method="optax")      # Eq. 14
    state = sj.record(state, J, eps); sj.converged(state, eps)   # Sec. IV-D
    result = sj.self_identify(observe, key, m_a, eps, n_act=n, task_dim=m, iters=50)  # Algorithm 1

    arm = sj.ur5e(task_dim=3)                                  # or sj.from_pose_fn / sj.from_mjcf
    res = sj.selfid.run(arm, key, q0, iters=30, eps=0.5)       # Algorithm 1 on a simulated system
    out = sj.follow(arm, sj.control.fixed(res.estimate), sj.paths.star(size=0.05), res.env, steps=400)

Importing the package appends CPU XLA flags to ``XLA_FLAGS`` (see
``selfid_jax._xla``); import it before running any JAX computation.
"""

from selfid_jax._xla import apply_default_xla_flags as _apply_default_xla_flags

_apply_default_xla_flags()

from selfid_jax import baselines, control, estimator, geometry, magnitude, paths, systems  # noqa: E402
from selfid_jax import refine as refine_lib, selfid  # noqa: E402
from selfid_jax.estimator import (  # noqa: E402
    EstimatorState,
    converged,
    init,
    initial_guess,
    magnitude_inverse_jacobian,
    objective,
    record,
    signed_inverse_jacobian,
    update,
)
from selfid_jax.refine import refine  # noqa: E402
from selfid_jax.selfid import SelfIDResult, self_identify, stateless  # noqa: E402
from selfid_jax.control import FollowResult, follow  # noqa: E402
from selfid_jax.systems import System, from_mjcf, from_pose_fn, two_link, ur5e  # noqa: E402

__version__ = "0.1.0"

__all__ = [
    "EstimatorState",
    "FollowResult",
    "SelfIDResult",
    "System",
    "baselines",
    "control",
    "follow",
    "from_mjcf",
    "from_pose_fn",
    "geometry",
    "magnitude",
    "systems",
    "two_link",
    "ur5e",
    "converged",
    "estimator",
    "init",
    "initial_guess",
    "magnitude_inverse_jacobian",
    "objective",
    "paths",
    "record",
    "refine",
    "refine_lib",
    "selfid",
    "self_identify",
    "signed_inverse_jacobian",
    "stateless",
    "update",
]
