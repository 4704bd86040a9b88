"""The ``report:`` section of a workflow file: its model and its checks (the page itself is
:mod:`selpath.pipeline.report`).

Apart from the renderer so that the workflow validator (:mod:`selpath.pipeline.spec`) can check the section
without importing what runs and renders a workflow.
"""

from __future__ import annotations

import string

import pydantic

REDUCTIONS = ("mean", "min", "max", "sum", "share_zero", "shape", "size", "list")
#: the most values a ``list`` reduction prints (the line goes into the terminal and the page)
LIST_LIMIT = 1000


class ReportSpec(pydantic.BaseModel):
    """The ``report:`` section of a workflow file."""

    model_config = pydantic.ConfigDict(extra="forbid", strict=True)
    file: str = pydantic.Field(description="HTML file to write, relative to the workflow file's folder "
                               "(must end in .html)")
    figures: list[str] | None = pydantic.Field(None, description="outputs whose figure (<store>.png) the page "
                                               "shows, in order; default: every output with a figure")
    summary: list[str] = pydantic.Field(default_factory=list, description="lines of text with "
                                        "{output.name[.reduction]:format} fields filled from the outputs' stores")
    tables: list[str] = pydantic.Field(default_factory=list, description="outputs shown as tables (a study's "
                                       "results): every variable of at most two small dims, one row per value of "
                                       "the first dim, with its units")


def summary_fields(line: str) -> list[tuple[str, str, str | None]]:
    """The ``(output, name, reduction)`` of every field in a summary line; ValueError names a malformed one."""
    fields = []
    for _, field, spec, conversion in string.Formatter().parse(line):
        if field is None:
            continue
        parts = field.split(".")
        if "{" in (spec or ""):
            raise ValueError(f"field {{{field}}}: a format may not hold another field")
        if conversion is not None or len(parts) not in (2, 3) or not all(p.strip() for p in parts) or any(
                c in field for c in "[]"):
            raise ValueError(f"field {{{field}}} is not output.name or output.name.reduction")
        if len(parts) == 3 and parts[2] not in REDUCTIONS:
            raise ValueError(f"field {{{field}}}: unknown reduction {parts[2]!r}; one of {', '.join(REDUCTIONS)}")
        fields.append((parts[0], parts[1], parts[2] if len(parts) == 3 else None))
    return fields


def report_problems(report: ReportSpec, outputs: list[str]) -> list[tuple[tuple, str, str]]:
    """What is wrong with a ``report:`` section, as ``(location, message, fix)``."""
    problems = []
    if not report.file.endswith(".html"):
        problems.append((("report", "file"), f"report file {report.file!r} must end in .html", "name a .html file"))
    for i, name in enumerate(report.figures or []):
        if name not in outputs:
            problems.append((("report", "figures", i), f"figure {name!r} is not an output of this workflow",
                             f"one of: {', '.join(outputs)}"))
    for i, name in enumerate(report.tables):
        if name not in outputs:
            problems.append((("report", "tables", i), f"table {name!r} is not an output of this workflow",
                             f"one of: {', '.join(outputs)}"))
    for i, line in enumerate(report.summary):
        try:
            fields = summary_fields(line)
        except ValueError as exc:
            problems.append((("report", "summary", i), str(exc), "write {output.name} or {output.name.mean:.3g}"))
            continue
        for output, _, _ in fields:
            if output not in outputs:
                problems.append((("report", "summary", i), f"field names {output!r}, not an output of this workflow",
                                 f"one of: {', '.join(outputs)}"))
    return problems
