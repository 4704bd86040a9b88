"""selpath's engine: stores of capture cubes, the stage registry, workflow specs and runs.

The public surface, for notebooks and plugins::

    from selpath.pipeline import open_store, stage, load_workflow, run_workflow  # or: import selpath
"""

from selpath.pipeline.capture_store import create_capture, missing_frames, write_frame
from selpath.pipeline.constraints import StorePath
from selpath.pipeline.engine import RunReport, build, run_workflow
from selpath.pipeline.errors import (
    ConfigError,
    DeviceError,
    EnvironmentFault,
    Problem,
    SelpathError,
    SpecError,
    StageError,
    StoreError,
)
from selpath.pipeline.kinds import FORMAT_VERSION, CubeKind, Variable
from selpath.pipeline.provenance import read_provenance, write_provenance
from selpath.pipeline.registry import Stage, StageRegistry, default_registry, stage
from selpath.pipeline.spec import Workflow, load_workflow
from selpath.pipeline.store import open_store, to_store

__all__ = [
    "FORMAT_VERSION",
    "CubeKind",
    "ConfigError",
    "DeviceError",
    "EnvironmentFault",
    "Problem",
    "RunReport",
    "SelpathError",
    "SpecError",
    "Stage",
    "StageError",
    "StageRegistry",
    "StoreError",
    "StorePath",
    "Variable",
    "Workflow",
    "build",
    "create_capture",
    "default_registry",
    "load_workflow",
    "missing_frames",
    "open_store",
    "read_provenance",
    "run_workflow",
    "stage",
    "to_store",
    "write_frame",
    "write_provenance",
]
