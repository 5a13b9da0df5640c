# The one list of selfid_jax's public names: type checkers read it, and selfid_jax/__init__.py imports each name from
# it on first use (lazy_loader.attach_stub). One spelling per name: the flat functions a user calls, and the
# subpackages under their own names (a module's functions are reached through its package).

# the subpackages
from . import articulated as articulated
from . import baselines as baselines
from . import control as control
from . import design as design
from . import identify as identify
from . import math as math
from . import robot as robot
from . import runner as runner
from . import sessions as sessions
from . import systems as systems

# the controller
from .control import ControllerParams as ControllerParams
from .control import FollowResult as FollowResult
from .control import follow as follow

# Algorithm 1
from .identify.algorithm import SelfIDResult as SelfIDResult
from .identify.algorithm import self_identify as self_identify
from .identify.algorithm import stateless as stateless

# the estimator (Eq. 6-14, Sec. IV-D)
from .identify.estimator import EstimatorState as EstimatorState
from .identify.estimator import converged as converged
from .identify.estimator import init as init
from .identify.estimator import initial_guess as initial_guess
from .identify.estimator import magnitude_inverse_jacobian as magnitude_inverse_jacobian
from .identify.estimator import objective as objective
from .identify.estimator import record as record
from .identify.estimator import signed_inverse_jacobian as signed_inverse_jacobian
from .identify.estimator import update as update
from .identify.refine import refine as refine

# self-ID from a recorded log
from .robot.offline import fit as fit

# systems
from .systems import System as System
from .systems import arm5 as arm5
from .systems import from_ets as from_ets
from .systems import from_mjcf as from_mjcf
from .systems import from_pose_fn as from_pose_fn
from .systems import model_o as model_o
from .systems import stewart_hand as stewart_hand
from .systems import two_link as two_link
from .systems import ur5e as ur5e

__version__: str
