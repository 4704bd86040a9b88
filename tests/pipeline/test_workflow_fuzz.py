"""Hostile workflow files: random mutations of the shipped workflows never give a traceback, and a mutated
workflow that runs never writes (or deletes) anything outside its declared outputs."""

from __future__ import annotations

import copy
import math
import os
from pathlib import Path

import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from typer.testing import CliRunner

from selpath import workflows
from selpath.pipeline import SelpathError, load_workflow
from selpath.pipeline.cli import app
from tests.conftest import SMALL_WORKFLOW

WORKFLOWS = [workflows.path(name) for name in workflows.names()]
VALUES = st.sampled_from([0, -1, 1, 2, 0.5, -0.5, 1e9, 1e300, -1e300, math.nan, math.inf, -math.inf, "", "x",
                          "..", ".", "/", "out", "out/x.zarr", "$capture", "$capture.nope", "$nope", "[degree]",
                          None, True, [], {}, [1, 2], {"start": 0, "stop": 1e300, "step": 1}])


def _paths(node, prefix=()):
    """Every path to a mapping value or list item of a parsed YAML document."""
    if isinstance(node, dict):
        for key, value in node.items():
            yield (*prefix, key)
            yield from _paths(value, (*prefix, key))
    elif isinstance(node, list):
        for i, value in enumerate(node):
            yield (*prefix, i)
            yield from _paths(value, (*prefix, i))


def _mutate(document, path, action, value):
    *parents, last = path
    node = document
    for part in parents:
        node = node[part]
    if action == "delete":
        del node[last]
    elif action == "replace":
        node[last] = value
    elif action == "duplicate" and isinstance(node, list):
        node.append(node[last])
    return document


@st.composite
def mutated(draw, texts):
    text = draw(st.sampled_from(texts))
    document = yaml.safe_load(text)
    for _ in range(draw(st.integers(1, 3))):
        paths = list(_paths(document))
        if not paths:
            break
        path = draw(st.sampled_from(paths))
        # a copy: the sampled lists and mappings are shared between examples and a later mutation would edit
        # them (even into a list that holds itself)
        document = _mutate(document, path, draw(st.sampled_from(["delete", "replace", "replace", "duplicate"])),
                           copy.deepcopy(draw(VALUES)))
    return yaml.safe_dump(document, allow_unicode=True)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=mutated([p.read_text() for p in WORKFLOWS] + [SMALL_WORKFLOW]))
def test_mutated_workflows_validate_or_fail_with_one_message(tmp_path_factory, text):
    folder = tmp_path_factory.mktemp("fuzz")
    (folder / "scenes").symlink_to(WORKFLOWS[0].parent / "scenes")
    path = folder / "wf.yaml"
    path.write_text(text)
    try:
        load_workflow(path)
    except SelpathError as exc:
        assert str(exc)


def _tree(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


@settings(max_examples=20, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=mutated([SMALL_WORKFLOW]))
def test_a_mutated_workflow_that_runs_writes_only_its_outputs(tmp_path_factory, text):
    folder = tmp_path_factory.mktemp("fuzzrun")
    (folder / "notes.txt").write_text("mine")
    path = folder / "wf.yaml"
    path.write_text(text)
    before = _tree(folder)
    result = CliRunner().invoke(app, ["run", str(path), "--no-progress"], env={"COLUMNS": "200"})
    assert result.exit_code in (0, 2), result.output  # 3 would be an unexpected error (a bug)
    assert "Traceback" not in result.output
    after = _tree(folder)
    assert before <= after and (folder / "notes.txt").read_text() == "mine"
    if result.exit_code == 0:
        stores = [Path(o.store) for o in load_workflow(path).outputs.values()]
        allowed = {os.fspath(p.relative_to(folder)) for s in stores for p in [s, *s.parents] if folder in p.parents}
        for new in after - before:
            assert any(new == a or new.startswith(a + "/") for a in allowed) or new in allowed, new
