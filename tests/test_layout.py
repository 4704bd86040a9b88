"""The layering of DESIGN §1, read from the source with ast (an import inside a function counts too):
pipeline is the floor (imports neither stages nor devices), devices never import stages, and the two
instruments' stages never import each other (what both need lives in stages/_*.py and stages/io.py)."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def imports(package: str) -> dict[str, set[str]]:
    """module path → the modules it imports (absolute names)."""
    found = {}
    for path in sorted((ROOT / package).rglob("*.py")):
        names = set()
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                names |= {alias.name for alias in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                names |= {node.module} | {f"{node.module}.{alias.name}" for alias in node.names}
        found[str(path.relative_to(ROOT))] = names
    return found


@pytest.mark.parametrize(("package", "forbidden"), [
    ("pipeline", ("stages", "devices")),
    ("devices", ("stages",)),
    ("stages/tomography", ("stages.procam",)),
    ("stages/procam", ("stages.tomography",)),
])
def test_no_arrow_against_the_layering(package, forbidden):
    wrong = {module: sorted(n for n in names if any(n == f or n.startswith(f + ".") for f in forbidden))
             for module, names in imports(package).items()}
    assert not {m: n for m, n in wrong.items() if n}


def test_shared_stage_modules_import_neither_instrument():
    shared = {m: n for m, n in imports("stages").items() if "/" not in m.removeprefix("stages/")}
    assert set(shared) >= {"stages/_common.py", "stages/_figures.py", "stages/_sweeps.py", "stages/io.py"}
    assert not {m: sorted(x for x in n if x.startswith(("stages.tomography", "stages.procam")))
                for m, n in shared.items() if any(x.startswith(("stages.tomography", "stages.procam")) for x in n)}
