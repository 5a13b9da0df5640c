# selfid_jax.robot.camera's modules, listed once: read by type checkers and by lazy_loader.attach_stub in __init__.py.

from . import calibrate as calibrate
from . import intrinsics as intrinsics
from . import live as live
from . import measure as measure
from . import render as render
from . import sim as sim
from . import sources as sources
from . import stream as stream
from . import tracker as tracker
