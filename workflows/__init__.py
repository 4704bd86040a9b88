"""The workflows (and the scenes they simulate) that selpath ships, as package data.

Copy them to run or edit (``selpath workflows --copy DIR`` copies the workflows and their ``scenes/``: relative
paths in a workflow resolve against the workflow file's folder, and that is where its stores land); ``selpath
demo`` runs :data:`DEMO` into a folder of its own.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path

#: what ``selpath demo`` runs: instrument → shipped workflow (each writes the report its ``report:`` names)
DEMO = {"tomography": "tomography-sim", "procam": "procam-sim"}


def folder() -> Path:
    """The folder holding the shipped workflow files (``*.yaml``) and ``scenes/``."""
    return Path(str(files(__name__)))


def names() -> list[str]:
    """The shipped workflows' names (file names without ``.yaml``), sorted."""
    return sorted(p.stem for p in folder().glob("*.yaml"))


def path(name: str) -> Path:
    """The file of the shipped workflow ``name`` (``tomography-sim`` or ``tomography-sim.yaml``)."""
    file = folder() / (name if name.endswith(".yaml") else f"{name}.yaml")
    if not file.is_file():
        raise KeyError(f"no shipped workflow {name!r}; shipped: {', '.join(names())}")
    return file


def scene(name: str) -> Path:
    """The file of the shipped scene ``name`` (``gelatin-bin`` or ``gelatin-bin.yaml``)."""
    file = folder() / "scenes" / (name if name.endswith(".yaml") else f"{name}.yaml")
    if not file.is_file():
        raise KeyError(f"no shipped scene {name!r}; shipped: "
                       f"{', '.join(sorted(p.stem for p in (folder() / 'scenes').glob('*.yaml')))}")
    return file
