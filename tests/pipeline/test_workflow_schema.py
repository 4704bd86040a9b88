"""`selpath schema` exports the workflow JSON Schema: every shipped workflow conforms (checked by the
jsonschema library, an independent validator), and a wrong stage, setting name, type or range is caught
exactly where `selpath validate` catches it."""

from __future__ import annotations

import json

import jsonschema
import pytest
import yaml
from typer.testing import CliRunner

from selpath import workflows
from selpath.pipeline.cli import app
from selpath.pipeline.workflow_schema import workflow_schema


@pytest.fixture(scope="module")
def validator():
    schema = json.loads(CliRunner().invoke(app, ["schema"]).output)
    jsonschema.Draft202012Validator.check_schema(schema)
    return jsonschema.Draft202012Validator(schema)


@pytest.mark.parametrize("name", workflows.names())
def test_every_shipped_workflow_conforms(validator, name):
    errors = list(validator.iter_errors(yaml.safe_load(workflows.path(name).read_text())))
    assert errors == [], [(list(e.absolute_path), e.message) for e in errors]


@pytest.mark.parametrize(("edit", "where"), [
    (lambda wf: wf["steps"][1].update(stage="absorb"), ["steps", 1, "stage"]),
    (lambda wf: wf["steps"][1]["with"].update(min_signl=1.0), ["steps", 1, "with"]),
    (lambda wf: wf["steps"][1]["with"].update(min_signal="one"), ["steps", 1, "with", "min_signal"]),
    (lambda wf: wf["steps"][1]["with"].update(min_signal_relative=2.0), ["steps", 1, "with",
                                                                          "min_signal_relative"]),
    (lambda wf: wf["steps"][1]["with"].update(capture="capture"), ["steps", 1, "with", "capture"]),
    (lambda wf: wf.update(scheduler=3), ["scheduler"]),
    (lambda wf: wf["steps"][1].pop("with"), ["steps", 1]),
    (lambda wf: wf.update(report={"file": "r.txt"}), ["report", "file"]),
])
def test_a_wrong_step_is_caught_where_validate_catches_it(validator, workflow_text, edit, where):
    workflow = yaml.safe_load(workflow_text)
    validator.validate(workflow)
    edit(workflow)
    errors = list(validator.iter_errors(workflow))
    assert errors
    assert any(list(e.absolute_path)[:len(where)] == where or any(
        list(c.absolute_path)[:len(where)] == where for c in (e.context or [])) for e in errors), [
        (list(e.absolute_path), e.message) for e in errors]


def test_every_registered_stage_and_setting_is_in_the_schema():
    from selpath.pipeline.registry import default_registry

    schema = workflow_schema()
    branches = {b["if"]["properties"]["stage"]["const"]: b["then"]["properties"]["with"]
                for b in schema["$defs"]["StepSpec"]["allOf"]}
    for stage in default_registry():
        assert set(branches[stage.name]["properties"]) == set(stage.inputs) | set(stage.params.model_fields)
