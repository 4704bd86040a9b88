# What this package gives, for type checkers and editors; at run time ``lazy_loader.attach_stub`` reads this file
# and imports each name when it is first used (its __init__.py).

from . import capture_store as capture_store
from . import compute as compute
from . import constraints as constraints
from . import engine as engine
from . import errors as errors
from . import identity as identity
from . import integrity as integrity
from . import kinds as kinds
from . import locks as locks
from . import manifest as manifest
from . import migrations as migrations
from . import outputs as outputs
from . import provenance as provenance
from . import quality as quality
from . import reference as reference
from . import registry as registry
from . import remote as remote
from . import report as report
from . import report_spec as report_spec
from . import spec as spec
from . import store as store
from . import workflow_schema as workflow_schema
from . import yaml_source as yaml_source
from .capture_store import create_capture as create_capture
from .capture_store import missing_frames as missing_frames
from .capture_store import write_frame as write_frame
from .constraints import StorePath as StorePath
from .engine import RunReport as RunReport
from .engine import build as build
from .engine import run_workflow as run_workflow
from .errors import ConfigError as ConfigError
from .errors import DeviceError as DeviceError
from .errors import EnvironmentFault as EnvironmentFault
from .errors import Problem as Problem
from .errors import SelpathError as SelpathError
from .errors import SpecError as SpecError
from .errors import StageError as StageError
from .errors import StoreError as StoreError
from .kinds import FORMAT_VERSION as FORMAT_VERSION
from .kinds import CubeKind as CubeKind
from .kinds import Variable as Variable
from .provenance import read_provenance as read_provenance
from .provenance import write_provenance as write_provenance
from .registry import Stage as Stage
from .registry import StageRegistry as StageRegistry
from .registry import default_registry as default_registry
from .registry import stage as stage
from .spec import Workflow as Workflow
from .spec import load_workflow as load_workflow
from .store import open_store as open_store
from .store import to_store as to_store

__all__ = [
    "ConfigError", "CubeKind", "DeviceError", "EnvironmentFault", "FORMAT_VERSION", "Problem", "RunReport",
    "SelpathError", "SpecError", "Stage", "StageError", "StageRegistry", "StoreError", "StorePath", "Variable",
    "Workflow", "build", "create_capture", "default_registry", "load_workflow", "missing_frames", "open_store",
    "read_provenance", "run_workflow", "stage", "to_store", "write_frame", "write_provenance",
]
