# selfid_jax.robot's modules, listed once: read by type checkers and by lazy_loader.attach_stub in __init__.py.

from . import bags as bags
from . import camera as camera
from . import drivers as drivers
from . import fit_options as fit_options
from . import journal as journal
from . import latency as latency
from . import live as live
from . import log as log
from . import offline as offline
from . import options as options
from . import protocol as protocol
from . import quality as quality
from . import read as read
from . import safety as safety
from . import session as session
from . import steps as steps
from . import streams as streams
from . import tables as tables
from . import transport as transport
from . import virtual as virtual
