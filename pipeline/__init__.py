"""selpath's engine: stores of capture cubes, the stage registry, workflow specs and runs.

The public surface, for notebooks and plugins::

    from selpath.pipeline import open_store, stage, load_workflow, run_workflow  # or: import selpath
"""

import lazy_loader

# imported when first used (SPEC 1), so that the command line answers --help without importing xarray or dask
_MODULES = [  # ``selpath.pipeline.integrity.…``
    "capture_store", "compute", "constraints", "engine", "errors", "identity", "integrity", "kinds", "locks",
    "manifest", "migrations", "outputs", "provenance", "quality", "reference", "registry", "remote", "report",
    "report_spec", "spec", "store", "workflow_schema", "yaml_source"]
__getattr__, __dir__, _names = lazy_loader.attach(__name__, submodules=_MODULES, submod_attrs={
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
__all__ = [name for name in _names if name not in _MODULES]  # the API; the modules are attributes too
