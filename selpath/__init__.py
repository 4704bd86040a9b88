"""selpath: measure selected light paths and turn them into science.

One namespace, four parts. The folders stay at the repository's top level and install under ``selpath``
(``pyproject.toml`` maps them with setuptools' ``package-dir``):

* :mod:`selpath.pipeline` — the engine: stores, cube kinds, the stage registry, workflows, the command line;
* :mod:`selpath.stages` — pure functions on labelled arrays (``selpath.stages.tomography`` for chapter 4,
  ``selpath.stages.procam`` for chapter 5);
* :mod:`selpath.devices` — instrument protocols, serial drivers, the simulated rigs;
* :mod:`selpath.workflows` — the workflows and scenes selpath ships.

What a notebook needs is here::

    import selpath

    capture = selpath.open_store("selpath-demo/capture.zarr")      # lazy, checked against its kind
    report = selpath.run("my-workflows/tomography-sim.yaml")       # a workflow from Python
    selpath.to_store(dataset, "mine.zarr", "absorption")           # any cube as a checked, complete store

and, on every store's Dataset and its variables, the ``.selpath`` accessor (:mod:`selpath.explore.accessor`)::

    transport = selpath.open_store("selpath-demo/transport.zarr")
    transport.selpath.profile(x=0.5, y=0.4)                        # T over offset, with sync delay [µs]
    transport.selpath.relight(line=360).selpath.plot()             # the scene under one projector row

For a plugin, :func:`stage` with :class:`CubeKind` and :class:`Variable` (docs/tutorials/plugins.md).

``import selpath`` imports nothing heavy: each name here is imported when first used (SPEC 1's lazy loading, with
``lazy_loader``), so that ``selpath --version`` and ``--help`` answer at once. The accessor is registered as soon as
xarray is imported, before or after selpath (:mod:`selpath._after_import`).
"""

from __future__ import annotations

import os
from importlib.metadata import PackageNotFoundError, version

from selpath._after_import import after_import
from selpath._lazy import attach

# the names, and the submodules (attributes too), are those of the stub beside this file, which editors read
__getattr__, _lazy_dir, __all__ = attach(__name__, __file__)

try:
    __version__ = version("selpath")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"


def _register_accessor() -> None:
    import selpath.explore.accessor  # noqa: F401, PLC0415  (registers the .selpath accessor on xarray objects)


after_import("xarray", _register_accessor)  # (EAGER_IMPORT=1 imports every name at once: lazy_loader's switch)


def run(file: str | os.PathLike, *, scheduler: str | None = None, force: bool = False, verify: bool = False,
        progress: bool = False):
    """Validate and run the workflow ``file`` as ``selpath run FILE`` does: stale outputs are written, up-to-date
    ones reused. ``scheduler`` overrides the workflow's; ``force`` recomputes every output; ``verify`` reads every
    chunk of the outputs it would reuse first. Returns the :class:`RunReport` (which steps ran, what was written).
    Raises :class:`SpecError` for a file that does not validate (every problem at once)."""
    from selpath.pipeline.engine import run_workflow
    from selpath.pipeline.spec import load_workflow

    return run_workflow(load_workflow(file), scheduler=scheduler, reuse=not force, verify=verify, progress=progress)


def __dir__() -> list[str]:
    return sorted({*_lazy_dir(), "__version__", "run"})
