"""The docstrings' examples run, module by module, on the installed ``selpath`` namespace (pytest's
``--doctest-modules`` would import the top-level folders a second time under their bare names)."""

from __future__ import annotations

import doctest
import importlib
import pkgutil

import pytest

import selpath
from selpath import devices, explore, geometry, pipeline, stages, workflows


def modules() -> list[str]:
    names = ["selpath"]
    for package in (pipeline, stages, devices, geometry, workflows, explore):
        names.append(package.__name__)
        names += [m.name for m in pkgutil.walk_packages(package.__path__, f"{package.__name__}.")]
    return sorted(n for n in names if not n.endswith("__main__"))


def test_the_walk_finds_every_part():
    found = modules()
    assert {"selpath.pipeline.registry", "selpath.stages.tomography.sinogram", "selpath.devices.sim.scene",
            "selpath.workflows", "selpath.explore.accessor"} <= set(found)
    assert selpath.__name__ == "selpath"


def with_examples(name: str) -> bool:
    return any(test.examples for test in doctest.DocTestFinder().find(importlib.import_module(name)))


@pytest.mark.parametrize("name", [n for n in modules() if with_examples(n)])
def test_docstring_examples(name):
    module = importlib.import_module(name)
    finder, runner = doctest.DocTestFinder(), doctest.DocTestRunner(optionflags=doctest.ELLIPSIS)
    tests = [t for t in finder.find(module) if t.examples]
    for test in tests:
        runner.run(test)
    result = runner.summarize(verbose=False)
    assert result.failed == 0, f"{result.failed} of {result.attempted} examples failed in {name} (output above)"
