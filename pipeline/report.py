"""A workflow's report: an HTML page of its figure outputs, the numbers its ``report:`` section names, and the steps.

Generic on purpose (the engine's floor imports no stage): a workflow declares its report, and any workflow can
have one (``selpath run FILE --report``)::

    report:
      file: out/procam/procam-report.html          # relative to the workflow file, like stores
      figures: [delay_profiles, relighting]        # outputs whose <store>.png is shown (default: every figure)
      summary:                                     # lines; {output.name[.reduction]:format} fields are filled
        - "v_p = {scan_speed.scan_speed_px_per_us:.5f} rows/µs"
        - "{transport.converged.mean:.1%} converged"
      tables: [study]                              # outputs shown as tables (a study's results, with units)

A summary field is ``output.name`` where ``name`` is an attr of the output's store (a number, text or list), or a
data variable: a 0-d variable is its value, a larger one needs a reduction after it: ``mean``, ``min``, ``max``,
``sum`` (NaN skipped; computed chunk by chunk), ``share_zero`` (the share of values equal to 0, e.g. of
unflagged pixels in a ``flags`` variable), ``shape`` (the sizes of its dims), ``size`` (how many values) or
``list`` (every value, for at most :data:`LIST_LIMIT` of them). An attr takes ``size`` (a list attr's length)
or no reduction. The format after ``:`` is Python's format mini-language.

``selpath run`` prints the summary lines and tables at the end of every run of a workflow with a ``report:``
section; ``--report`` also writes the page: the summary, the tables, each figure with the caption its stage wrote
(the figure store's ``caption`` attr), every step's settings, and what the run computed or reused and how long it
took.
"""

from __future__ import annotations

import base64
import html
import os
import re
import string
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import dask
import numpy as np
import xarray as xr

from selpath.pipeline.engine import RunReport
from selpath.pipeline.errors import Problem, StoreError
from selpath.pipeline.report_spec import LIST_LIMIT, REDUCTIONS, summary_fields
from selpath.pipeline.spec import Workflow, is_path_setting
from selpath.pipeline.store import open_store


def _value(store, output: str, name: str, reduction: str | None) -> Any:
    """One summary field's value, or for a reduction of a variable a lazy 0-d DataArray: every field of the report
    is then computed in one pass, chunk by chunk on the stores' dask arrays (bounded memory)."""
    if name in store.data_vars:
        variable = store[name]
        if reduction is None:
            if variable.ndim:
                raise StoreError(Problem(f"report: variable {name!r} of output {output!r} has dims "
                                         f"{variable.dims}; a summary field needs a reduction",
                                         fix=f"write {{{output}.{name}.mean}} ({', '.join(REDUCTIONS)})"))
            return variable
        if reduction == "shape":
            return tuple(variable.shape)
        if reduction == "size":
            return int(variable.size)
        if reduction == "list":
            if variable.size > LIST_LIMIT:
                raise StoreError(Problem(f"report: {{{output}.{name}.list}} would print {variable.size:,} values "
                                         f"(at most {LIST_LIMIT})", fix="reduce it (mean, min, max, sum, shape)"))
            return variable.values.tolist()
        if reduction == "share_zero":
            return (variable == 0).mean()
        return getattr(variable.astype(float), reduction)(skipna=True)
    if name in store.attrs:
        value = store.attrs[name]
        if reduction is None:
            return value
        if reduction == "size" and isinstance(value, list | tuple):
            return len(value)
        raise StoreError(Problem(f"report: {{{output}.{name}.{reduction}}}: {name!r} is an attr "
                                 f"({type(value).__name__}); an attr takes no reduction but size (of a list)",
                                 fix=f"write {{{output}.{name}}}"))
    raise StoreError(Problem(f"report: output {output!r} has no attr or variable {name!r}",
                             fix=f"its variables: {sorted(map(str, store.data_vars))}; attrs: {sorted(store.attrs)}"))


def summary_lines(workflow: Workflow) -> list[str]:
    """The report's summary lines with their fields filled from the written output stores."""
    if workflow.report is None:
        return []
    stores: dict[str, Any] = {}
    fields = [summary_fields(line) for line in workflow.report.summary]
    values: dict[str, Any] = {}
    for output, name, reduction in (field for line in fields for field in line):
        key = f"{output}.{name}" + (f".{reduction}" if reduction else "")
        if key not in values:
            if output not in stores:
                stores[output] = open_store(workflow.outputs[output].store, registry=workflow.registry)
            values[key] = _value(stores[output], output, name, reduction)
    lazy = [k for k, v in values.items() if isinstance(v, xr.DataArray)]
    with np.errstate(all="ignore"):
        computed = dask.compute(*(values[k].data for k in lazy))
    values |= {k: np.asarray(v).item() for k, v in zip(lazy, computed, strict=True)}
    lines = []
    for number, line in enumerate(workflow.report.summary):
        try:
            lines.append(_Filled(values).format(line))
        except (ValueError, TypeError) as exc:
            used = {f"{o}.{n}" + (f".{r}" if r else "") for o, n, r in fields[number]}
            shown = ", ".join(f"{k} = {values[k]!r:.60} ({type(values[k]).__name__})" for k in sorted(used))
            raise StoreError(Problem(f"report: summary line {number} cannot be formatted ({exc}); its fields: {shown}",
                                     where=workflow.source, path=f"report.summary[{number}]",
                                     fix="give each field a format its value takes (e.g. :.3g for a number)")) from None
    return lines


#: a table shows variables whose dims hold at most this many values each (a study's light angles, methods)
TABLE_LIMIT = 64


@dataclass(frozen=True)
class TableView:
    """A study's results as text cells: one row per value of ``columns[0]``'s dim."""

    title: str
    columns: list[str]
    rows: list[list[str]]


def _label(array: xr.DataArray, name: str, detail: Any = None) -> str:
    units = array.attrs.get("units")
    return name + (f" {detail}" if detail is not None else "") + (f" [{units}]" if units not in (None, "", "1")
                                                                   else "")


def _cell(value: Any) -> str:
    if isinstance(value, float | np.floating):
        return "NaN" if not np.isfinite(value) else f"{value:.4g}"
    if isinstance(value, np.bool_ | bool):
        return "yes" if value else "no"
    return str(value)


def store_tables(store: xr.Dataset, title: str) -> list[TableView]:
    """The variables of ``store`` with at most two dims of at most :data:`TABLE_LIMIT` values, as tables: one per
    first dim (and one row of the 0-d ones), a column per variable (and per value of its second dim) in name order,
    with units; computed in one pass."""
    chosen = sorted(str(v) for v in store.data_vars if store[v].ndim <= 2
                    and all(store.sizes[d] <= TABLE_LIMIT for d in store[v].dims))
    by_dim: dict[str, list[str]] = {}
    for name in chosen:
        by_dim.setdefault(str(store[name].dims[0]) if store[name].ndim else "", []).append(name)
    values = dict(zip(chosen, dask.compute(*(store[n].data for n in chosen)), strict=True))
    tables = []
    scalars = by_dim.pop("", [])
    if scalars:  # 0-d values (an error's RMSE, a usable share): one row
        tables.append(TableView(title, [_label(store[n], n) for n in scalars],
                                [[_cell(np.asarray(values[n]).item()) for n in scalars]]))
    for dim, names in by_dim.items():
        index = store[dim] if dim in store.coords else xr.DataArray(np.arange(store.sizes[dim]), dims=dim)
        columns, cells = [_label(index, dim)], [[_cell(v) for v in index.values.tolist()]]
        for name in names:
            array, data = store[name], np.asarray(values[name])
            if array.ndim == 1:
                columns.append(_label(array, name))
                cells.append([_cell(v) for v in data])
                continue
            other = array.dims[1]
            labels = store[other].values.tolist() if other in store.coords else range(store.sizes[other])
            for j, label in enumerate(labels):
                columns.append(_label(array, name, label))
                cells.append([_cell(v) for v in data[:, j]])
        tables.append(TableView(f"{title} (by {dim})" if len(by_dim) + bool(scalars) > 1 else title, columns,
                                [list(row) for row in zip(*cells, strict=True)]))
    return tables


def report_tables(workflow: Workflow) -> list[TableView]:
    """The tables the ``report:`` section names, from the written output stores."""
    if workflow.report is None:
        return []
    return [table for name in workflow.report.tables
            for table in store_tables(open_store(workflow.outputs[name].store, registry=workflow.registry), name)]


class _Filled(string.Formatter):
    """Fills whole dotted field names from a mapping (never attribute access on Python objects)."""

    def __init__(self, values: dict[str, Any]):
        self.values = values

    def get_field(self, field_name, args, kwargs):
        return self.values[field_name], field_name


def default_report_file(workflow: Workflow) -> Path:
    """Where a workflow without a ``report:`` section has its report: beside its first output's store."""
    stores = [o.store for o in workflow.outputs.values() if "://" not in o.store]
    folder = Path(stores[0]).parent if stores else workflow.base_dir
    name = re.sub(r"[^A-Za-z0-9_.-]+", "-", workflow.name).strip(".-") or "workflow"
    return folder / f"{name}-report.html"


def _figure_html(workflow: Workflow, name: str) -> str:
    """One figure of the page: its PNG and its caption (the figure store's ``caption`` attr, set by the stage)."""
    store = workflow.outputs[name].store
    png = Path(store.removesuffix(".zarr") + ".png")
    if not png.is_file():
        return ""
    try:
        caption = str(open_store(store, registry=workflow.registry).attrs.get("caption", ""))
    except StoreError:
        caption = ""
    data = base64.b64encode(png.read_bytes()).decode()
    return (f"<figure><img src='data:image/png;base64,{data}' alt='{html.escape(name)}'><figcaption><b>"
            f"{html.escape(name)}</b> ({html.escape(png.name)}). {html.escape(caption)}</figcaption></figure>")


def _table_html(table: TableView) -> str:
    head = "".join(f"<th>{html.escape(c)}</th>" for c in table.columns)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(c)}</td>" for c in row) + "</tr>" for row in table.rows)
    return f"<h3>{html.escape(table.title)}</h3><table><tr>{head}</tr>{body}</table>"


def _settings_html(workflow: Workflow) -> str:
    """Every step's stage and settings: those the workflow file sets in bold, the stage's defaults plain."""
    rows = []
    for step_id, step in workflow.steps.items():
        given = step.settings.model_fields_set
        paths = {k for k in type(step.settings).model_fields if is_path_setting(type(step.settings), k)}
        cells = [f"<b>{html.escape(k)} = {html.escape(_setting_text(v, k in paths))}</b>" if k in given else
                 f"{html.escape(k)} = {html.escape(_setting_text(v, k in paths))}"
                 for k, v in step.settings.model_dump(mode="json").items()]
        inputs = ", ".join(f"{k} = {r}" for k, r in step.inputs.items())
        rows.append(f"<tr><td>{html.escape(step_id)}</td><td>{html.escape(step.stage.name)}</td>"
                    f"<td>{html.escape(inputs)}</td><td>{'; '.join(cells)}</td></tr>")
    return ("<h2>Settings</h2><p>Each step's stage, inputs and settings: those the workflow file sets in bold, the "
            "stage's defaults plain (<code>selpath stages NAME</code> explains each).</p><table><tr><th>step</th>"
            f"<th>stage</th><th>inputs</th><th>settings</th></tr>{''.join(rows)}</table>")


def _setting_text(value: Any, path: bool = False) -> str:
    """A setting's value for the page: a path setting by its file name (the full path is in the store's
    provenance, and where the folder was is nobody's business on a shared page), anything long cut at 80."""
    if path and isinstance(value, str) and value:
        value = re.split(r"[\\/]", value.rstrip("/\\"))[-1]
    text = repr(value) if isinstance(value, str) else str(value)
    return text if len(text) <= 80 else text[:77] + "…"


def _steps_html(report: RunReport) -> str:
    rows = "".join(
        f"<tr><td>{html.escape(s.id)}</td><td>{html.escape(s.stage)}</td><td>{html.escape(s.status)}</td>"
        f"<td>{'' if s.seconds is None else f'{s.seconds:.1f} s'}</td><td>{html.escape(s.reason)}</td></tr>"
        for s in report.steps.values())
    return ("<h2>Steps</h2><p>What this run computed and what it reused (an output whose stored provenance matches "
            "its step is read back, never recomputed); the time of a stored step includes the unstored steps it "
            "reads.</p><table><tr><th>step</th><th>stage</th><th>status</th><th>time</th><th>why</th></tr>"
            f"{rows}</table>")


def write_html(workflow: Workflow, report: RunReport, path: str | Path | None = None, *,
               summary: list[str] | None = None, tables: list[TableView] | None = None) -> Path:
    """Write the workflow's report page (one self-contained file) and return its path.

    ``path`` defaults to the ``report:`` section's file, else :func:`default_report_file`; ``summary`` and
    ``tables`` to the section's filled lines and tables. The page shows them, every figure with its caption, the
    steps' settings and what the run did. A file there that selpath did not write (no generator tag) is refused,
    never replaced.
    """
    spec = workflow.report
    target = Path(path) if path is not None else Path(spec.file) if spec is not None else default_report_file(
        workflow)
    summary = summary_lines(workflow) if summary is None else summary
    tables = report_tables(workflow) if tables is None else tables
    names = spec.figures if spec is not None and spec.figures is not None else list(workflow.outputs)
    figures = "".join(_figure_html(workflow, name) for name in names)
    notes = "".join(f"<li>{html.escape(line)}</li>" for line in summary)
    counts = {status: sum(s.status == status for s in report.steps.values()) for status in ("computed", "reused")}
    page = f"""<!doctype html><html><head><meta charset="utf-8">{_GENERATOR}<title>{html.escape(workflow.name)}</title>
<style>body{{font-family:sans-serif;max-width:980px;margin:auto;padding:0 8px}}img{{max-width:100%}}
figure{{margin:24px 0}}figcaption{{font-size:92%;line-height:1.4}}table{{border-collapse:collapse;margin:8px 0}}
th{{text-align:left;font-size:90%;padding:2px 8px;border-bottom:2px solid #999}}
td{{padding:2px 8px;border-bottom:1px solid #ddd;font-size:90%;vertical-align:top}}</style></head><body>
<h1>selpath: {html.escape(workflow.name)}</h1>
<p>Workflow file {html.escape(Path(workflow.source).name)}: {counts['computed']} step(s) computed and
{counts['reused']} reused in {report.seconds:.1f} s; {len(report.written)} output(s) written.</p>
<ul>{notes}</ul>{''.join(_table_html(t) for t in tables)}{figures}{_settings_html(workflow)}{_steps_html(report)}
</body></html>"""
    if target.exists() and _GENERATOR not in target.read_text(encoding="utf-8", errors="replace"):
        raise StoreError(Problem("a report would replace this file, which selpath did not write", where=str(target),
                                 fix="move it away, or name another report file (or --out folder)"))
    target.parent.mkdir(parents=True, exist_ok=True)
    staging = target.with_name(f".{target.name}.partial")
    staging.write_text(page, encoding="utf-8")
    os.replace(staging, target)
    return target


#: marks the HTML reports selpath writes (the only files a report may replace)
_GENERATOR = '<meta name="generator" content="selpath">'
