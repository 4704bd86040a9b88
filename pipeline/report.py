"""An HTML page for a finished workflow run: every figure output (its PNG, embedded) and the steps table.

Generic on purpose (the engine's floor imports no stage): a figure is any output whose store has a
``<store>.png`` beside it, which the engine writes for ``figure`` cubes.
"""

from __future__ import annotations

import base64
import html
import os
from pathlib import Path

from pipeline.engine import RunReport
from pipeline.errors import Problem, StoreError
from pipeline.spec import Workflow


def write_html(workflow: Workflow, report: RunReport, path: str | Path, *, summary: list[str] = ()) -> Path:
    """Write ``path`` (one self-contained file) and return it; a file there that selpath did not write (no
    generator tag) is refused, never replaced."""
    figures = []
    for name, out in workflow.outputs.items():
        png = Path(out.store.removesuffix(".zarr") + ".png")
        if png.is_file():
            data = base64.b64encode(png.read_bytes()).decode()
            figures.append(f"<figure><img src='data:image/png;base64,{data}' alt='{html.escape(name)}'>"
                           f"<figcaption>{html.escape(name)} ({html.escape(png.name)})</figcaption></figure>")
    rows = "".join(f"<tr><td>{html.escape(s.id)}</td><td>{html.escape(s.status)}</td><td>{html.escape(s.reason)}"
                   f"</td></tr>" for s in report.steps.values())
    notes = "".join(f"<li>{html.escape(line)}</li>" for line in summary)
    page = f"""<!doctype html><html><head><meta charset="utf-8">{_GENERATOR}<title>{html.escape(workflow.name)}</title>
<style>body{{font-family:sans-serif;max-width:980px;margin:auto}}img{{max-width:100%}}
td{{padding:2px 8px;border-bottom:1px solid #ddd;font-size:90%}}</style></head><body>
<h1>selpath: {html.escape(workflow.name)}</h1><p>{len(report.written)} output(s) written in {report.seconds:.1f} s.</p>
<ul>{notes}</ul>{''.join(figures)}<h2>Steps</h2><table>{rows}</table></body></html>"""
    target = Path(path)
    if target.exists() and _GENERATOR not in target.read_text(encoding="utf-8", errors="replace"):
        raise StoreError(Problem("a report would replace this file, which selpath did not write", where=str(target),
                                 fix="move it away, or give the demo another --out folder"))
    staging = target.with_name(f".{target.name}.partial")
    staging.write_text(page, encoding="utf-8")
    os.replace(staging, target)
    return target


#: marks the HTML reports selpath writes (the only files a report may replace)
_GENERATOR = '<meta name="generator" content="selpath">'
