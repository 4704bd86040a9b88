# What ``import selpath`` gives, for type checkers and editors; at run time ``lazy_loader.attach_stub`` reads this
# file and imports each name when it is first used (selpath/__init__.py).
import os

from . import devices as devices
from . import explore as explore
from . import geometry as geometry
from . import pipeline as pipeline
from . import stages as stages
from . import workflows as workflows
from .pipeline.engine import RunReport as RunReport
from .pipeline.engine import run_workflow as run_workflow
from .pipeline.errors import ConfigError as ConfigError
from .pipeline.errors import DeviceError as DeviceError
from .pipeline.errors import EnvironmentFault as EnvironmentFault
from .pipeline.errors import Problem as Problem
from .pipeline.errors import SelpathError as SelpathError
from .pipeline.errors import SpecError as SpecError
from .pipeline.errors import StageError as StageError
from .pipeline.errors import StoreError as StoreError
from .pipeline.kinds import FORMAT_VERSION as FORMAT_VERSION
from .pipeline.kinds import CubeKind as CubeKind
from .pipeline.kinds import Variable as Variable
from .pipeline.registry import StageRegistry as StageRegistry
from .pipeline.registry import default_registry as default_registry
from .pipeline.registry import stage as stage
from .pipeline.spec import Workflow as Workflow
from .pipeline.spec import load_workflow as load_workflow
from .pipeline.store import open_store as open_store
from .pipeline.store import to_store as to_store

__all__ = [
    "ConfigError", "CubeKind", "DeviceError", "EnvironmentFault", "FORMAT_VERSION", "Problem", "RunReport",
    "SelpathError", "SpecError", "StageError", "StageRegistry", "StoreError", "Variable", "Workflow", "__version__",
    "default_registry", "load_workflow", "open_store", "run", "run_workflow", "stage", "to_store",
]

__version__: str

def run(file: str | os.PathLike, *, scheduler: str | None = None, force: bool = False, verify: bool = False,
        progress: bool = False) -> RunReport: ...
