"""Built-in stages: pure functions on labelled arrays, one module per concern.

Each is a plain function usable in a notebook (``selpath.stages.tomography.calibrate.absorption(capture)``) and
registered for workflows through the ``selpath.stages`` entry-point group. ``selpath.stages.tomography`` holds
chapter 4, ``selpath.stages.procam`` chapter 5; what a user catches or reads from either is exported here:
the solvers' :class:`Solution`, :class:`Result` codes and :class:`SolverError`, and the
:class:`UnsortedSweepWarning` a stage gives when it sorts a sweep.
"""

import lazy_loader

_MODULES = [  # ``selpath.stages.tomography.…``
    "camera_target", "frame_files", "importing", "io", "procam", "tomography"]
__getattr__, __dir__, _names = lazy_loader.attach(__name__, submodules=_MODULES, submod_attrs={
    "_common": ["UnsortedSweepWarning"], "_solution": ["Result", "Solution", "SolverError"]})
__all__ = [name for name in _names if name not in _MODULES]  # the API; the modules are attributes too
