"""selfid_jax: model-free self-identification of inverse Jacobians in JAX; ``import selfid_jax as sj`` is its API.

``import selfid_jax as sj`` gives the functional API: the estimator
(``sj.init``/``sj.update``/``sj.initial_guess``/``sj.refine``/``sj.record``,
Eq. 6-14 and Sec. IV-D), self-ID from a recorded log (``sj.fit``), Algorithm 1
(``sj.self_identify``, ``sj.selfid.run``), systems (``sj.ur5e``, ``sj.two_link``, ``sj.arm5``,
``sj.from_pose_fn``, ``sj.from_mjcf``, ``sj.from_ets``), kinematic metrics (``sj.manipulability``),
damped least-squares IK (``sj.dls``), the controller (``sj.follow`` with ``sj.ControllerParams``), the estimation
baselines (``sj.baselines``) and the experiment runner (``sj.experiment``, loaded
on first use). docs/api_guide.md has runnable examples.

Layers, bottom to top (import-linter contracts in ``pyproject.toml``):
``math`` < ``systems`` < ``identify`` | ``control`` < ``baselines`` <
``design`` | ``articulated`` | ``robot`` < ``experiments`` < ``commands`` < ``cli``; ``runner`` knows none of them.

Importing the package appends CPU XLA flags to ``XLA_FLAGS`` (see
``selfid_jax._xla``); import it before running any JAX computation.
"""

from pathlib import Path as _Path


class _CheckoutFolders:
    """Finds selfid_jax.experiments and selfid_jax.configs in a checkout's top-level experiments/ and configs/.

    pyproject.toml's package-dir installs the two folders under this package: a wheel holds them beside this file
    and an editable install maps them with setuptools' own finder. A checkout imported from its root (``python -m
    pytest``, Sphinx's conf.py) has neither beside this file; this finder, consulted only after the regular ones
    and registered only in that case, resolves exactly those two names to the same folders, and nothing else.
    """

    FOLDERS = {"selfid_jax.experiments": "experiments", "selfid_jax.configs": "configs"}

    def __init__(self, root: _Path) -> None:
        self.root = root

    def find_spec(self, name, path=None, target=None):
        from importlib.machinery import ModuleSpec
        from importlib.util import spec_from_file_location

        if name not in self.FOLDERS:
            return None
        folder = self.root / self.FOLDERS[name]
        if (folder / "__init__.py").is_file():
            return spec_from_file_location(name, folder / "__init__.py", submodule_search_locations=[str(folder)])
        spec = ModuleSpec(name, None, is_package=True)  # configs/: a data folder, imported as a namespace package
        spec.submodule_search_locations = [str(folder)]
        return spec


def _find_checkout_folders() -> None:
    import sys

    here = _Path(__file__).resolve().parent
    if not (here / "experiments").is_dir() and (here.parent / "experiments" / "__init__.py").is_file():
        sys.meta_path.append(_CheckoutFolders(here.parent))


_find_checkout_folders()

from selfid_jax._xla import apply_default_xla_flags as _apply_default_xla_flags  # noqa: E402

_apply_default_xla_flags()

from typing import TYPE_CHECKING  # noqa: E402

# name -> (module, attribute or None for the module itself): imported on first use (PEP 562), so that
# ``import selfid_jax`` costs milliseconds and the command line can set up its signal handling before JAX loads.
_LAZY: dict[str, tuple[str, str | None]] = {
    "baselines": ("selfid_jax.baselines", None),
    "control": ("selfid_jax.control", None),
    "design": ("selfid_jax.design", None),
    "systems": ("selfid_jax.systems", None),
    "dls": ("selfid_jax.control.dls", None),
    "metrics": ("selfid_jax.control.metrics", None),
    "paths": ("selfid_jax.control.paths", None),
    "selfid": ("selfid_jax.identify.algorithm", None),
    "estimator": ("selfid_jax.identify.estimator", None),
    "magnitude": ("selfid_jax.identify.magnitude", None),
    "refine_lib": ("selfid_jax.identify.refine", None),
    "geometry": ("selfid_jax.math.geometry", None),
    "manipulability": ("selfid_jax.systems.manipulability", None),
    "experiment": ("selfid_jax.runner", None),
    **{name: ("selfid_jax.control.loop", name) for name in ("ControllerParams", "FollowResult", "follow")},
    **{name: ("selfid_jax.identify.algorithm", name) for name in ("SelfIDResult", "self_identify", "stateless")},
    **{name: ("selfid_jax.identify.estimator", name) for name in (
        "EstimatorState", "converged", "init", "initial_guess", "magnitude_inverse_jacobian", "objective", "record",
        "signed_inverse_jacobian", "update")},
    "refine": ("selfid_jax.identify.refine", "refine"),
    "robot": ("selfid_jax.robot", None),
    "fit": ("selfid_jax.robot.offline", "fit"),
    **{name: ("selfid_jax.systems", name) for name in (
        "System", "arm5", "from_ets", "from_mjcf", "from_pose_fn", "model_o", "stewart_hand", "two_link", "ur5e")},
}

if TYPE_CHECKING:
    from selfid_jax import baselines, control, design, systems
    from selfid_jax import runner as experiment
    from selfid_jax.control import dls, metrics, paths
    from selfid_jax.control.loop import ControllerParams, FollowResult, follow
    from selfid_jax.identify import algorithm as selfid
    from selfid_jax.identify import estimator, magnitude
    from selfid_jax.identify import refine as refine_lib
    from selfid_jax.identify.algorithm import SelfIDResult, self_identify, stateless
    from selfid_jax.identify.estimator import (
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
    from selfid_jax.identify.refine import refine
    from selfid_jax import robot
    from selfid_jax.robot.offline import fit
    from selfid_jax.math import geometry
    from selfid_jax.systems import (
        System, arm5, from_ets, from_mjcf, from_pose_fn, manipulability, model_o, stewart_hand, two_link, ur5e,
    )

__version__ = "0.1.0"


def __getattr__(name: str):
    """The public names, imported on first use (``sj.experiment``, the runner, loads pandas and pydantic)."""
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'selfid_jax' has no attribute {name!r}") from None
    import importlib

    value = importlib.import_module(module)
    if attr is not None:
        value = getattr(value, attr)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


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
    "fit",
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
    "robot",
    "selfid",
    "self_identify",
    "signed_inverse_jacobian",
    "stateless",
    "update",
]
