"""The layout of DESIGN §1, read from the source with ast (an import inside a function, or under TYPE_CHECKING,
counts too): one namespace, ``selpath``, whose parts are the top-level folders; pipeline is the floor (imports
neither stages nor devices), devices never depend on stages, explore (the accessor and the explorer) sits on top
and nothing below imports it, the two instruments' stages never import each other
(what both need lives in stages/_*.py and stages/io.py), and no modules import each other in a loop."""

from __future__ import annotations

import ast
import re
import subprocess
import tomllib
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
#: folder → the package it installs as (pyproject.toml's package-dir)
PARTS = {"selpath": "selpath", "pipeline": "selpath.pipeline", "stages": "selpath.stages",
         "devices": "selpath.devices", "geometry": "selpath.geometry", "workflows": "selpath.workflows",
         "explore": "selpath.explore"}
BARE = ("pipeline", "stages", "devices", "geometry", "workflows")


def module_name(path: Path) -> str:
    """``stages/tomography/hull.py`` → ``selpath.stages.tomography.hull``; a package's ``__init__.py`` → its name."""
    parts = path.relative_to(ROOT).with_suffix("").parts
    name = ".".join((PARTS[parts[0]], *parts[1:]))
    return name.removesuffix(".__init__")


def _imported(tree: ast.AST) -> set[str]:
    names = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names |= {alias.name for alias in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            names |= {node.module} | {f"{node.module}.{alias.name}" for alias in node.names}
    return names


def imports(package: str) -> dict[str, set[str]]:
    """module path → the modules it imports (absolute names)."""
    return {str(path.relative_to(ROOT)): _imported(ast.parse(path.read_text(), str(path)))
            for path in sorted((ROOT / package).rglob("*.py"))}


def graph() -> dict[str, set[str]]:
    """selpath module → the selpath modules it imports (``from a.b import c`` names ``a.b.c`` where that is a module,
    else ``a.b``)."""
    files = {module_name(p): p for part in PARTS for p in (ROOT / part).rglob("*.py")}
    edges = {}
    for name, path in files.items():
        targets = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                targets |= {f"{node.module}.{alias.name}" if f"{node.module}.{alias.name}" in files else node.module
                            for alias in node.names}
        edges[name] = (targets & set(files)) - {name}
    return edges


def cycles(edges: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index, low, stack, on, found, counter = {}, {}, [], set(), [], [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in edges[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(edges):
        if v not in index:
            visit(v)
    return found


@pytest.mark.parametrize(("package", "forbidden"), [
    ("pipeline", ("selpath.stages", "selpath.devices", "selpath.explore")),
    ("geometry", ("selpath.stages", "selpath.devices", "selpath.explore")),
    ("devices", ("selpath.stages", "selpath.explore")),
    ("stages", ("selpath.explore",)),
    ("stages/tomography", ("selpath.stages.procam",)),
    ("stages/procam", ("selpath.stages.tomography",)),
])
def test_no_arrow_against_the_layering(package, forbidden):
    wrong = {module: sorted(n for n in names if any(n == f or n.startswith(f + ".") for f in forbidden))
             for module, names in imports(package).items()}
    assert not {m: n for m, n in wrong.items() if n}


#: the stage modules whose job is to simulate (acquisition on the simulated rig, ``simulate_*``, the simulated studies)
#: or to read a simulated capture's truth (phantoms, scene labels): the only ones that may import the simulator
SIMULATING = {"stages/procam/acquire.py", "stages/procam/acquire_patterns.py", "stages/procam/multiplexing.py",
              "stages/procam/_scene_truth.py", "stages/tomography/acquire.py", "stages/tomography/simulate.py",
              "stages/tomography/phantom.py", "stages/tomography/studies.py"}


def test_processing_stages_never_import_the_simulator():
    """Paths, calibration, reconstruction, the scattering model, labels …: the geometry they share with the
    simulator is ``selpath.geometry``'s, so none of them reaches into ``devices.sim``."""
    reaching = {module for module, names in imports("stages").items()
                if any(n == "selpath.devices.sim" or n.startswith("selpath.devices.sim.") for n in names)}
    assert reaching <= SIMULATING, sorted(reaching - SIMULATING)
    assert {"stages/tomography/paths.py", "stages/tomography/_walks.py", "stages/procam/_labels.py"}.isdisjoint(
        reaching)


def test_shared_stage_modules_import_neither_instrument():
    instruments = ("selpath.stages.tomography", "selpath.stages.procam")
    shared = {m: n for m, n in imports("stages").items() if "/" not in m.removeprefix("stages/")}
    assert set(shared) >= {"stages/_common.py", "stages/_figures.py", "stages/_sweeps.py", "stages/io.py"}
    assert not {m: sorted(x for x in n if x.startswith(instruments))
                for m, n in shared.items() if any(x.startswith(instruments) for x in n)}


def test_no_import_cycle():
    assert cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]  # the check itself
    edges = graph()
    assert len(edges) > 100 and "selpath.pipeline.engine" in edges["selpath.pipeline.cli"]
    assert cycles(edges) == []


def test_everything_imports_through_the_one_namespace():
    """No module, test or benchmark imports the folders under their bare names: in a source tree the working
    folder would make those importable and hide a module twice; installed, they do not exist."""
    tracked = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "*.py"], cwd=ROOT,
                             capture_output=True, text=True, check=True).stdout.split()
    bare = {}
    tracked = [file for file in tracked if (ROOT / file).is_file()]  # not one deleted in the work tree
    for file in tracked:
        names = _imported(ast.parse((ROOT / file).read_text(), file))
        wrong = sorted(n for n in names if n.split(".")[0] in BARE)
        if wrong:
            bare[file] = wrong
    assert len(tracked) > 150 and not bare
    # code in strings (a subprocess's script, a plugin written by a test) and in the docs a user copies from
    texts = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "*.py", "*.md", ".ci/*"],
                           cwd=ROOT, capture_output=True, text=True, check=True).stdout.split()
    pattern = re.compile(rf"(?<!selpath )\b(?:from|import) (?:{'|'.join(BARE)})\b")
    quoted = {file: pattern.findall((ROOT / file).read_text()) for file in texts
              if file != "CHANGELOG.md" and (ROOT / file).is_file()}  # (the changelog names the old ones)  # old names
    assert "README.md" in texts and not {file: found for file, found in quoted.items() if found}


def test_every_package_folder_is_installed():
    """pyproject.toml lists packages by hand (package-dir maps folders into the namespace): a new subpackage
    left off the list would be missing from the wheel."""
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    on_disk = {module_name(init) for part in PARTS for init in (ROOT / part).rglob("__init__.py")}
    assert set(config["packages"]) == on_disk
    assert config["package-dir"] == {package: folder for folder, package in PARTS.items()}


#: the most lines a module of the package may have (DESIGN §1: rooms that fit; #56)
MAX_MODULE_LINES = 420


def test_every_module_fits_in_a_room():
    long = {str(p.relative_to(ROOT)): n for part in PARTS for p in (ROOT / part).rglob("*.py")
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES}
    assert not long, f"split these by concern (DESIGN §1): {long}"


def test_no_test_module_imports_another():
    """What tests share lives in tests/helpers (and conftest fixtures), never in a test module another imports:
    importing a test module runs its module-level setup and collects its tests twice in a reader's head."""
    importing = {}
    for path in sorted((ROOT / "tests").rglob("*.py")):
        names = _imported(ast.parse(path.read_text(), str(path)))
        others = sorted(n for n in names if re.search(r"(^|\.)test_\w+$", n) and n.startswith("tests."))
        if others:
            importing[str(path.relative_to(ROOT))] = others
    assert not importing
