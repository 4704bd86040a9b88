"""The workflows (and the scenes they simulate) that selpath ships, as package data.

Run one by name (``selpath run tomography-sim``), or copy its file and edit it: relative paths in a workflow
resolve against the workflow file's folder, so a copied workflow keeps finding ``scenes/`` beside it only if
the scenes are copied too (``selpath workflows --copy DIR`` copies both).
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
