"""Built-in stages: pure functions on labelled arrays, one module per concern.

Each is a plain function usable in a notebook (``selpath.stages.tomography.calibrate.absorption(capture)``) and
registered for workflows through the ``selpath.stages`` entry-point group. ``selpath.stages.tomography`` holds
chapter 4, ``selpath.stages.procam`` chapter 5; what a user catches or reads from either is exported here:
the solvers' :class:`Solution`, :class:`Result` codes and :class:`SolverError`, and the
:class:`UnsortedSweepWarning` a stage gives when it sorts a sweep.
"""

from selpath._lazy import attach

# imported when first used (SPEC 1), so that the command line answers --help without importing xarray or dask: the
# names, and the submodules (attributes too), are those of the stub beside this file, which editors read
__getattr__, __dir__, __all__ = attach(__name__, __file__)
