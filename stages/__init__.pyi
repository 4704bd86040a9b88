# What this package gives, for type checkers and editors; at run time ``lazy_loader.attach_stub`` reads this file
# and imports each name when it is first used (its __init__.py).

from . import camera_target as camera_target
from . import frame_files as frame_files
from . import importing as importing
from . import io as io
from . import procam as procam
from . import tomography as tomography
from ._common import UnsortedSweepWarning as UnsortedSweepWarning
from ._solution import Result as Result
from ._solution import Solution as Solution
from ._solution import SolverError as SolverError

__all__ = [
    "Result", "Solution", "SolverError", "UnsortedSweepWarning",
]
