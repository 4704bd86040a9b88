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
"""

from __future__ import annotations

import os
from importlib.metadata import PackageNotFoundError, version

import selpath.explore.accessor  # noqa: F401  (registers the .selpath accessor on xarray objects)
from selpath.pipeline.engine import RunReport, run_workflow
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
from selpath.pipeline.registry import StageRegistry, default_registry, stage
from selpath.pipeline.spec import Workflow, load_workflow
from selpath.pipeline.store import open_store, to_store

try:
    __version__ = version("selpath")
except PackageNotFoundError:  # a source tree that was never installed
    __version__ = "0+unknown"


def run(file: str | os.PathLike, *, scheduler: str | None = None, force: bool = False, verify: bool = False,
        progress: bool = False) -> RunReport:
    """Validate and run the workflow ``file`` as ``selpath run FILE`` does: stale outputs are written, up-to-date
    ones reused. ``scheduler`` overrides the workflow's; ``force`` recomputes every output; ``verify`` reads every
    chunk of the outputs it would reuse first. Returns the :class:`RunReport` (which steps ran, what was written).
    Raises :class:`SpecError` for a file that does not validate (every problem at once)."""
    return run_workflow(load_workflow(file), scheduler=scheduler, reuse=not force, verify=verify, progress=progress)


__all__ = [
    "FORMAT_VERSION",
    "ConfigError",
    "CubeKind",
    "DeviceError",
    "EnvironmentFault",
    "Problem",
    "RunReport",
    "SelpathError",
    "SpecError",
    "StageError",
    "StageRegistry",
    "StoreError",
    "Variable",
    "Workflow",
    "__version__",
    "default_registry",
    "load_workflow",
    "open_store",
    "run",
    "run_workflow",
    "stage",
    "to_store",
]
