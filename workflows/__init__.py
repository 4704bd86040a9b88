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


def describe(name: str, width: int = 110) -> str:
    """What the shipped workflow ``name`` does, from its opening comment: the first clause (to a colon, or a full
    stop or question mark outside parentheses), with the next one where the first only cites the thesis or an
    issue ("Thesis §4.4.3: any convex shape works"); cut at ``width`` characters."""
    lines = []
    for line in path(name).read_text().splitlines():
        if not line.startswith("#"):
            break
        lines.append(line.lstrip("#").strip())
    text, clauses, depth, start = " ".join(lines), [], 0, 0
    for i, char in enumerate(text):
        depth += (char == "(") - (char == ")")
        ends = char == ":" or (char in ".?" and (i + 1 == len(text) or text[i + 1] == " "))
        if depth == 0 and ends and not text[max(0, i - 3):i].endswith(("Fig", "Figs", "e.g", "i.e")):
            clauses.append(text[start:i + (char == "?")].strip())
            start = i + 1
            if len(clauses) == 2 or not clauses[0].startswith(("Thesis", "Issue")):
                break
    said = ": ".join(clauses) if clauses else text
    return said if len(said) <= width else said[:width - 1].rstrip() + "…"


def scene(name: str) -> Path:
    """The file of the shipped scene ``name`` (``gelatin-bin`` or ``gelatin-bin.yaml``)."""
    return _shipped(folder() / "scenes", name, "scene")


def _shipped(where: Path, name: str, what: str) -> Path:
    file = where / (name if name.endswith(".yaml") else f"{name}.yaml")
    if not file.is_file():
        shipped = ", ".join(sorted(p.stem for p in where.glob("*.yaml")))
        raise KeyError(f"no shipped {what} {name!r}; shipped: {shipped}")
    return file
