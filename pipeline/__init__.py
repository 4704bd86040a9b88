"""selpath's engine: stores of capture cubes, the stage registry, workflow specs and runs.

The public surface, for notebooks and plugins::

    from selpath.pipeline import open_store, stage, load_workflow, run_workflow  # or: import selpath
"""

import lazy_loader

# imported when first used (SPEC 1), so that the command line answers --help without importing xarray or dask
__getattr__, __dir__, __all__ = lazy_loader.attach(__name__, submod_attrs={
    "capture_store": ["create_capture", "missing_frames", "write_frame"],
    "constraints": ["StorePath"],
    "engine": ["RunReport", "build", "run_workflow"],
    "errors": ["ConfigError", "DeviceError", "EnvironmentFault", "Problem", "SelpathError", "SpecError", "StageError",
               "StoreError"],
    "kinds": ["FORMAT_VERSION", "CubeKind", "Variable"],
    "provenance": ["read_provenance", "write_provenance"],
    "registry": ["Stage", "StageRegistry", "default_registry", "stage"],
    "spec": ["Workflow", "load_workflow"],
    "store": ["open_store", "to_store"],
})
