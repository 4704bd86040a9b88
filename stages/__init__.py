"""Built-in stages: pure functions on labelled arrays, one module per concern.

Each is a plain function usable in a notebook (``stages.tomography.calibrate.absorption(capture)``) and
registered for workflows through the ``selpath.stages`` entry-point group.
"""
