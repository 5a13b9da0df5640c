# selfid_jax.sessions' public names, listed once: read by type checkers and by lazy_loader.attach_stub in __init__.py.
# The run-directory helpers (summary, write_run, redraw, file names) stay under their modules: fit and online each
# have their own.

from . import fit_run as fit_run
from . import online_config as online_config
from . import online_figures as online_figures
from . import online_progress as online_progress
from . import online_run as online_run
from . import online_sim as online_sim
from .fit_run import fit_to_run as fit_to_run
from .online_config import OnlineConfig as OnlineConfig
from .online_config import load_online_config as load_online_config
from .online_progress import ProgressLine as ProgressLine
from .online_run import run_session as run_session
from .online_sim import RobotSimConfig as RobotSimConfig
from .online_sim import load_sim_config as load_sim_config
