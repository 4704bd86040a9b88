"""selpath's engine: stores of capture cubes, the stage registry, workflow specs and runs.

The public surface, for notebooks and plugins::

    from selpath.pipeline import open_store, stage, load_workflow, run_workflow  # or: import selpath
"""

from selpath._lazy import attach

# imported when first used (SPEC 1), so that the command line answers --help without importing xarray or dask: the
# names, and the submodules (attributes too), are those of the stub beside this file, which editors read
__getattr__, __dir__, __all__ = attach(__name__, __file__)
