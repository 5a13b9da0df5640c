"""selfid_jax: model-free self-identification of inverse Jacobians in JAX; ``import selfid_jax as sj`` is its API.

``import selfid_jax as sj`` gives the functional API: the estimator
(``sj.init``/``sj.update``/``sj.initial_guess``/``sj.refine``/``sj.record``,
Eq. 6-14 and Sec. IV-D), Algorithm 1 (``sj.self_identify``, ``sj.selfid.run``),
systems (``sj.ur5e``, ``sj.two_link``, ``sj.arm5``, ``sj.from_pose_fn``, ``sj.from_mjcf``,
``sj.from_ets``), kinematic metrics (``sj.manipulability``), damped least-squares IK (``sj.dls``),
the controller (``sj.follow`` with ``sj.ControllerParams``), the estimation
baselines (``sj.baselines``) and the experiment runner (``sj.experiment``, loaded
on first use). README.md has runnable examples.

Layers, bottom to top (import-linter contracts in ``pyproject.toml``):
``math`` < ``systems`` < ``identify`` | ``control`` < ``baselines`` <
``design`` | ``articulated`` < ``experiments``; ``runner`` knows none of them.

Importing the package appends CPU XLA flags to ``XLA_FLAGS`` (see
``selfid_jax._xla``); import it before running any JAX computation.
"""

from selfid_jax._xla import apply_default_xla_flags as _apply_default_xla_flags

_apply_default_xla_flags()

from selfid_jax import baselines, control, design, systems  # noqa: E402
from selfid_jax.control import dls, metrics, paths  # noqa: E402
from selfid_jax.control.loop import ControllerParams, FollowResult, follow  # noqa: E402
from selfid_jax.identify import algorithm as selfid  # noqa: E402
from selfid_jax.identify import estimator, magnitude  # noqa: E402
from selfid_jax.identify import refine as refine_lib  # noqa: E402
from selfid_jax.identify.algorithm import SelfIDResult, self_identify, stateless  # noqa: E402
from selfid_jax.identify.estimator import (  # noqa: E402
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
from selfid_jax.identify.refine import refine  # noqa: E402
from selfid_jax.math import geometry  # noqa: E402
from selfid_jax.systems import (  # noqa: E402
    System, arm5, from_ets, from_mjcf, from_pose_fn, manipulability, model_o, stewart_hand, two_link, ur5e,
)

__version__ = "0.1.0"


def __getattr__(name: str):
    """``sj.experiment``: the runner (:mod:`selfid_jax.runner`), imported on first use (it loads pandas and
    pydantic)."""
    if name == "experiment":
        import importlib

        return importlib.import_module("selfid_jax.runner")
    raise AttributeError(f"module 'selfid_jax' has no attribute {name!r}")


__all__ = [
    "ControllerParams",
    "EstimatorState",
    "FollowResult",
    "SelfIDResult",
    "System",
    "arm5",
    "baselines",
    "design",
    "dls",
    "from_ets",
    "manipulability",
    "control",
    "follow",
    "from_mjcf",
    "from_pose_fn",
    "geometry",
    "magnitude",
    "metrics",
    "model_o",
    "stewart_hand",
    "systems",
    "two_link",
    "ur5e",
    "converged",
    "estimator",
    "experiment",
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
