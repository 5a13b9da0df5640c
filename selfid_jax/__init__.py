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
``sj.design``, ``sj.articulated``, ``sj.robot``, ``sj.sessions`` (a fitted log or an online session
written into a run directory, as the commands do) and ``sj.runner`` (e.g.
``sj.identify.algorithm.run``, Algorithm 1 on a system; ``sj.control.paths``;
``sj.runner.get``). Each is imported on first use, with its public modules. docs/api_guide.md has
runnable examples.

Layers, bottom to top (import-linter contracts in ``pyproject.toml``):
``math`` < ``systems`` < ``identify`` | ``control`` < ``baselines`` <
``design`` | ``articulated`` | ``robot`` < ``experiments`` | ``sessions`` < ``commands`` < ``cli``; ``runner``
knows none of them.

The public names are listed once, in ``selfid_jax/__init__.pyi``: type checkers
read it, and :func:`lazy_loader.attach_stub` (SPEC 1) imports each name from it
on first use, so ``import selfid_jax`` loads no JAX, pandas or pydantic and the
command line can take over its signals first.

Importing the package appends CPU XLA flags to ``XLA_FLAGS`` (see
``selfid_jax._xla``); import it before running any JAX computation.
"""

import lazy_loader as _lazy

from selfid_jax._xla import apply_default_xla_flags as _apply_default_xla_flags

_apply_default_xla_flags()

__getattr__, __dir__, __all__ = _lazy.attach_stub(__name__, __file__)

__version__ = "0.1.0"
