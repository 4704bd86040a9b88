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

#: a shipped workflow that reads what another writes → that one: run it first, in the same folder (until then the
#: reader does not validate: its input store does not exist yet)
AFTER = {"procam-materials-apply": "procam-materials"}


def folder() -> Path:
    """The folder holding the shipped workflow files (``*.yaml``) and ``scenes/``."""
    return Path(str(files(__name__)))


def names() -> list[str]:
    """The shipped workflows' names (file names without ``.yaml``), sorted."""
    return sorted(p.stem for p in folder().glob("*.yaml"))


def path(name: str) -> Path:
    """The file of the shipped workflow ``name`` (``tomography-sim`` or ``tomography-sim.yaml``)."""
    return _shipped(folder(), name, "workflow")


def scene(name: str) -> Path:
    """The file of the shipped scene ``name`` (``gelatin-bin`` or ``gelatin-bin.yaml``)."""
    return _shipped(folder() / "scenes", name, "scene")


def _shipped(where: Path, name: str, what: str) -> Path:
    file = where / (name if name.endswith(".yaml") else f"{name}.yaml")
    if not file.is_file():
        shipped = ", ".join(sorted(p.stem for p in where.glob("*.yaml")))
        raise KeyError(f"no shipped {what} {name!r}; shipped: {shipped}")
    return file
