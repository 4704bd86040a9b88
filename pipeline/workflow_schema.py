"""The workflow file's JSON Schema, with every registered stage's settings, for editors (``selpath schema``).

A YAML editor that reads JSON Schema (VS Code's YAML extension, JetBrains IDEs) then completes stage names and
their settings and marks a wrong name, type or range as you type. The schema is built from the same pydantic
models that :func:`selpath.pipeline.spec.load_workflow` validates with, so the two cannot disagree on a setting; the
checks that need the files (stores, scenes, ``$step`` wiring) stay ``selpath validate``'s.
"""

from __future__ import annotations

from typing import Any

from pydantic.json_schema import models_json_schema

from selpath.pipeline.registry import StageRegistry, default_registry
from selpath.pipeline.spec import WorkflowFile

#: a data input: ``$step`` or ``$step.variable``
INPUT = {"type": "string", "pattern": r"^\$[A-Za-z_][A-Za-z0-9_-]*(\.[A-Za-z_][A-Za-z0-9_]*)?$",
         "description": "a step's result: $step or $step.variable"}


def workflow_schema(registry: StageRegistry | None = None) -> dict[str, Any]:
    """The JSON Schema (draft 2020-12) of a workflow file whose steps use the stages in ``registry``."""
    registry = default_registry() if registry is None else registry
    stages = list(registry)
    refs, schema = models_json_schema([(WorkflowFile, "validation")] + [(s.params, "validation") for s in stages],
                                      ref_template="#/$defs/{model}")
    defs = schema["$defs"]
    root = dict(defs.pop(refs[(WorkflowFile, "validation")]["$ref"].rsplit("/", 1)[1]))
    step = defs["StepSpec"]
    step["properties"]["stage"] = {"enum": [s.name for s in stages], "description": "a registered stage name"}
    step["allOf"] = []
    for s in stages:
        settings = defs.pop(refs[(s.params, "validation")]["$ref"].rsplit("/", 1)[1])
        properties = {name: dict(INPUT, description=f"data input {name!r}" + (" (required)" if name in
                                                                               s.required_inputs else ""))
                      for name in s.inputs}
        properties |= settings.get("properties", {})
        required = list(s.required_inputs) + list(settings.get("required", []))
        with_schema = {"type": "object", "properties": properties, "additionalProperties": False,
                       "description": s.summary}
        if required:
            with_schema["required"] = required
        then = {"properties": {"with": with_schema}}
        if required:
            then["required"] = ["with"]
        step["allOf"].append({"if": {"properties": {"stage": {"const": s.name}}, "required": ["stage"]},
                              "then": then})
    defs["ReportSpec"]["properties"]["file"]["pattern"] = r"\.html$"
    root["$defs"] = defs
    root["$schema"] = "https://json-schema.org/draft/2020-12/schema"
    root["title"] = "selpath workflow"
    return root
