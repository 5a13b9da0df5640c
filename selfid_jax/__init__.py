"""selfid_jax: model-free self-identification of inverse Jacobians in JAX; ``import selfid_jax as sj`` is its API.

``import selfid_jax as sj`` gives one spelling per public name. Flat, the
functions a user calls: the estimator (``sj.init``, ``sj.update``,
``sj.signed_inverse_jacobian``, ``sj.magnitude_inverse_jacobian``,
``sj.initial_guess``, ``sj.refine``, ``sj.record``, ``sj.converged``,
``sj.objective``; Eq. 6-14 and Sec. IV-D), Algorithm 1 (``sj.self_identify``,
``sj.stateless``), self-ID from a recorded log (``sj.fit``), systems
(``sj.ur5e``, ``sj.two_link``, ``sj.arm5``, ``sj.model_o``,
``sj.stewart_hand``, ``sj.from_pose_fn``, ``sj.from_mjcf``, ``sj.from_ets``)
and the controller (``sj.follow`` with ``sj.ControllerParams``). Everything
else by its package, under the package's own name: ``sj.math``,
``sj.systems``, ``sj.identify``, ``sj.control``, ``sj.baselines``,
``sj.design``, ``sj.articulated``, ``sj.robot`` and ``sj.runner`` (e.g.
``sj.identify.algorithm.run``, Algorithm 1 on a system; ``sj.control.paths``;
``sj.runner.get``). Each is imported on first use. docs/api_guide.md has
runnable examples.

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
# One spelling per name: the flat functions, and the subpackages under their own names (a module's functions are
# reached through its package, ``sj.identify.estimator.update``, not through a second top-level alias).
_SUBPACKAGES = ("articulated", "baselines", "control", "design", "identify", "math", "robot", "runner", "systems")
_LAZY: dict[str, tuple[str, str | None]] = {
    **{name: (f"selfid_jax.{name}", None) for name in _SUBPACKAGES},
    **{name: ("selfid_jax.identify.estimator", name) for name in (
        "EstimatorState", "converged", "init", "initial_guess", "magnitude_inverse_jacobian", "objective", "record",
        "signed_inverse_jacobian", "update")},
    "refine": ("selfid_jax.identify.refine", "refine"),
    **{name: ("selfid_jax.identify.algorithm", name) for name in ("SelfIDResult", "self_identify", "stateless")},
    "fit": ("selfid_jax.robot.offline", "fit"),
    **{name: ("selfid_jax.control", name) for name in ("ControllerParams", "FollowResult", "follow")},
    **{name: ("selfid_jax.systems", name) for name in (
        "System", "arm5", "from_ets", "from_mjcf", "from_pose_fn", "model_o", "stewart_hand", "two_link", "ur5e")},
}

if TYPE_CHECKING:
    from selfid_jax import articulated, baselines, control, design, identify, math, robot, runner, systems
    from selfid_jax.control import ControllerParams, FollowResult, follow
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
    from selfid_jax.robot.offline import fit
    from selfid_jax.systems import (
        System,
        arm5,
        from_ets,
        from_mjcf,
        from_pose_fn,
        model_o,
        stewart_hand,
        two_link,
        ur5e,
    )

__version__ = "0.1.0"


def __getattr__(name: str):
    """The public names, imported on first use (``sj.runner`` loads pandas and pydantic)."""
    try:
        module, attr = _LAZY[name]
    except KeyError:
        raise AttributeError(f"module 'selfid_jax' has no attribute {name!r}") from None
    import importlib

    value = importlib.import_module(module)
    if attr is not None:
        value = getattr(value, attr)
    _load_public_modules()
    globals()[name] = value
    return value


_EXPANDED: set[str] = set()


def _load_public_modules() -> None:
    """Import the public modules of every subpackage loaded so far, so that ``sj.control.paths.star`` and
    ``sj.identify.algorithm.run`` work however the package was first reached (an import of a subpackage as a
    side effect sets its attribute here without passing through :func:`__getattr__`)."""
    import importlib
    import pkgutil
    import sys

    for sub in _SUBPACKAGES:
        package = sys.modules.get(f"{__name__}.{sub}")
        if package is None or sub in _EXPANDED:
            continue
        _EXPANDED.add(sub)
        for info in pkgutil.iter_modules(package.__path__):
            if not info.name.startswith("_"):
                importlib.import_module(f"{__name__}.{sub}.{info.name}")
        _load_public_modules()  # a module just imported may have loaded another subpackage


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_LAZY))


__all__ = [
    # the estimator (Eq. 6-14, Sec. IV-D) and Algorithm 1
    "EstimatorState",
    "SelfIDResult",
    "converged",
    "fit",
    "init",
    "initial_guess",
    "magnitude_inverse_jacobian",
    "objective",
    "record",
    "refine",
    "self_identify",
    "signed_inverse_jacobian",
    "stateless",
    "update",
    # systems
    "System",
    "arm5",
    "from_ets",
    "from_mjcf",
    "from_pose_fn",
    "model_o",
    "stewart_hand",
    "two_link",
    "ur5e",
    # the controller
    "ControllerParams",
    "FollowResult",
    "follow",
    # the subpackages
    "articulated",
    "baselines",
    "control",
    "design",
    "identify",
    "math",
    "robot",
    "runner",
    "systems",
]
