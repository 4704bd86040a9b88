"""The documentation site's pages that describe the code, generated from it: one page per registered stage (what it
does, its data inputs, its settings with their types, ranges, defaults and units, the kinds it makes and their
variables), one per cube kind, and one per shipped workflow (what it reproduces, its steps, its outputs and the
summary lines of its report). ``docs/conf.py`` writes them when the site is built (:func:`write_pages`), so they
cannot drift from the code; ``tests/test_docs_site.py`` checks that every stage, kind and shipped workflow has one.

Pages are MyST Markdown. A docstring's reST (``:func:`x```, ````x````) becomes Markdown code spans; its numpydoc
``Parameters`` section is not repeated (each setting's row carries its description).
"""

from __future__ import annotations

import inspect
import json
import re
import shutil
from dataclasses import dataclass
from pathlib import Path

import yaml

from selpath.pipeline.constraints import bounds_text, describe
from selpath.pipeline.kinds import CubeKind
from selpath.pipeline.registry import ROLE, Stage, StageRegistry, default_registry

_SECTION = re.compile(r"^(\S[^\n]*)\n-{3,}\s*$", re.MULTILINE)
#: the thesis's sections as a workflow's opening comment cites them (``§5.4.7``, ``Fig. 49``)
_THESIS = re.compile(r"(?:§\s?\d+(?:\.\d+)*|Figs?\. \d+(?:[–-]\d+)?)")


def markdown(doc: str) -> str:
    """Docstring text as Markdown: reST roles and literals as code spans (``:func:`a.b``` → `` `a.b` ``).

    >>> markdown("see :func:`~selpath.x.pool` and ``keep``")
    'see `pool` and `keep`'
    """
    text = ROLE.sub(lambda m: f"`{m.group(1).rsplit('.', 1)[-1] if m.group(0).count('~') else m.group(1)}`", doc)
    return re.sub(r"``([^`]+)``", r"`\1`", text)


def _cell(text: str) -> str:
    """Text for one cell of a Markdown table (no line breaks, no bare pipes)."""
    return markdown(" ".join(str(text).split())).replace("|", "\\|") or "—"


#: numpydoc sections of ``type`` lines with indented descriptions
_TYPED = ("Returns", "Yields", "Raises", "Warns")


def _entries(section: str) -> str:
    """A numpydoc section of ``type`` lines, each with its indented description (Returns, Raises), as one paragraph
    per entry: ``type``: description. Text in another shape is kept as it is."""
    entries, current = [], None
    for line in section.splitlines():
        if line and not line.startswith(" "):
            current = [f"`{line.strip()}`:", []]
            entries.append(current)
        elif current is not None and line.strip():
            current[1].append(line.strip())
        elif line.strip():
            return section
    return "\n\n".join(f"{head} {' '.join(text)}" for head, text in entries) if entries else section


def _body(stage: Stage) -> str:
    """The stage's docstring after its summary, without the Parameters section (the tables carry it)."""
    doc = inspect.cleandoc(stage.func.__doc__ or "")
    rest = doc.split("\n\n", 1)[1] if "\n\n" in doc else ""
    sections = list(_SECTION.finditer(rest))
    if not sections:
        return markdown(rest).strip()
    kept = [rest[:sections[0].start()]]
    for i, match in enumerate(sections):
        end = sections[i + 1].start() if i + 1 < len(sections) else len(rest)
        if match.group(1).strip() != "Parameters":
            title, text = match.group(1).strip(), rest[match.end():end].strip("\n")
            kept.append(f"**{title}**\n\n" + (_entries(text) if title in _TYPED else text))
    return markdown("\n\n".join(part.strip() for part in kept if part.strip()))


def stage_page(stage: Stage) -> str:
    """The reference page of one stage."""
    lines = [f"(stage-{stage.name})=", f"# `{stage.name}`", "", markdown(stage.summary), ""]
    module = stage.func.__module__
    makes = ", ".join(f"[`{k.name}`](../kinds/{k.name}.md)" for k in stage.kinds) or (
        "any kind (its result's `selpath_kind` attr names it)")
    lines += [f"**Module** `{module}` · **makes** {makes}", ""]
    body = _body(stage)
    if body:
        lines += [body, ""]
    if stage.inputs:
        lines += ["## Inputs", "", "Data wired in a workflow as `$step` or `$step.variable`.", "",
                  "| input | | what it is |", "|---|---|---|"]
        lines += [f"| `{name}` | {'required' if name in stage.required_inputs else 'optional'} | "
                  f"{_cell(stage.param_docs.get(name, ''))} |" for name in stage.inputs]
        lines.append("")
    fields = stage.params.model_fields
    if fields:
        lines += ["## Settings", "", "Under `with:` beside the inputs; units in brackets.", "",
                  "| setting | type and range | default | what it does |", "|---|---|---|---|"]
        for name, field in fields.items():
            default = "required" if field.is_required() else f"`{field.default!r}`"
            lines.append(f"| `{name}` | {_cell(describe(field))} | {default} | {_cell(field.description or '')} |")
        lines.append("")
    lines += ["## Use it", "", "```yaml", "steps:", f"  - id: {stage.name.split('_')[0]}", f"    stage: {stage.name}",
              "    with: {" + ", ".join(f"{name}: $step" for name in stage.required_inputs) + "}", "```", ""]
    return "\n".join(lines)


def kind_page(kind: CubeKind, makers: list[str]) -> str:
    """The reference page of one cube kind: its variables, coordinates' units and required attrs."""
    lines = [f"(kind-{kind.name})=", f"# `{kind.name}`", "", markdown(kind.description or ""), ""]
    if makers:
        lines += ["Made by " + ", ".join(f"[`{m}`](../stages/{m}.md)" for m in makers) + ".", ""]
    lines += ["| variable | dims | units | | what it holds |", "|---|---|---|---|---|"]
    for name, var in kind.variables.items():
        units = "not fixed" if var.units == "" else "none" if var.units is None else var.units
        text = "; ".join(t for t in (var.long_name, var.description) if t)
        lines.append(f"| `{name}` | ({', '.join(var.dims)}) | {_cell(units)} | "
                     f"{'required' if var.required else 'optional'} | {_cell(text)} |")
    lines.append("")
    if kind.coord_units:
        lines += ["| coordinate | units |", "|---|---|"]
        lines += [f"| `{dim}` | {', '.join(sorted(units))} |" for dim, units in kind.coord_units.items()]
        lines.append("")
    if kind.attrs:
        lines += ["| attr (required) | what it holds |", "|---|---|"]
        lines += [f"| `{attr}` | {_cell(text)} |" for attr, text in kind.attrs.items()]
        lines.append("")
    if kind.batch_dims:
        lines += [f"Stores of this kind stack over {', '.join(f'`{d}`' for d in kind.batch_dims)}.", ""]
    if kind.png:
        lines += [f"A workflow output also saves `{kind.png}` as `<store>.png`.", ""]
    return "\n".join(lines)


def _annotation_text(annotation, queue: list) -> str:
    """A field's type for people: a quantity as what it is with an example and its units, a nested model as a link
    to its section (queued to be described), tuples and lists spelt out, ranges after the type."""
    import types
    import typing

    import pydantic

    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        base, *metadata = args
        quantity = next((m for m in metadata if hasattr(m, "example") and hasattr(m, "units")), None)
        limits = ", ".join(bounds_text(metadata))
        text = (f"{quantity.what} (`{quantity.example}`; {', '.join(quantity.units)})" if quantity
                else _annotation_text(base, queue))
        return f"{text} {limits}" if limits else text
    if origin in (typing.Union, types.UnionType):
        return " or ".join("null" if a is type(None) else _annotation_text(a, queue) for a in args)
    if origin is typing.Literal:
        return " or ".join(f"`{v}`" for v in args)
    if origin is tuple:
        return "[" + ", ".join(_annotation_text(a, queue) for a in args if a is not Ellipsis) + (
            ", …]" if Ellipsis in args else "]")
    if origin in (list, typing.List):  # noqa: UP006 (what typing.get_origin returns for list[...])
        return f"list of {_annotation_text(args[0], queue)}"
    if isinstance(annotation, type) and issubclass(annotation, pydantic.BaseModel):
        if annotation not in queue:
            queue.append(annotation)
        return f"[{annotation.__name__}](#{annotation.__name__.lower()})"
    return getattr(annotation, "__name__", str(annotation))


def _default_text(field, annotation) -> str:
    """A field's default as a file would write it: a quantity with its canonical unit (``0 mm``)."""
    import typing

    import pydantic

    value = field.get_default(call_default_factory=True)
    if isinstance(value, pydantic.BaseModel):
        return "its defaults"
    metadata = typing.get_args(annotation)[1:] if typing.get_origin(annotation) is typing.Annotated else ()
    quantity = next((m for m in metadata if hasattr(m, "canonical")), None)
    if quantity is not None and isinstance(value, float):
        return f"`{value:g} {quantity.canonical}`"
    return f"`{value!r}`"


def pydantic_doc() -> str | None:
    """pydantic's own BaseModel docstring (a model without one of its own inherits none: ``__doc__`` is None)."""
    import pydantic

    return pydantic.BaseModel.__doc__


def model_page(title: str, intro: str, model) -> str:
    """A file format defined by a pydantic ``model`` (a scene file, a rig file): one section per model class
    reachable from it, one row per field with its type (quantities with their units), default and description."""
    order, lines = [model], [f"# {title}", "", intro, ""]
    for current in order:  # grows as fields name further models (each described once, in the order first met)
        doc = inspect.cleandoc(current.__doc__ or "")
        lines += [f"## {current.__name__}", ""]
        if doc and current.__doc__ is not pydantic_doc():
            lines += [markdown(doc.split("\n\n")[0].replace("\n", " ")), ""]
        lines += ["| field | type | default | what it is |", "|---|---|---|---|"]
        for name, field in current.model_fields.items():
            annotation = field.annotation
            if field.metadata:  # constraints pydantic moved off the annotation
                import typing

                annotation = typing.Annotated[(annotation, *field.metadata)]
            default = "required" if field.is_required() else _default_text(field, annotation)
            lines.append(f"| `{name}` | {_cell(_annotation_text(annotation, order))} | {_cell(default)} | "
                         f"{_cell(field.description or '')} |")
        lines.append("")
    return "\n".join(lines)


def _opening(text: str) -> str:
    """A workflow file's opening comment, as one paragraph."""
    lines = []
    for line in text.splitlines():
        if not line.startswith("#"):
            break
        lines.append(line.lstrip("#").strip())
    return " ".join(lines)


def workflow_page(name: str, path: Path, registry: StageRegistry, run: Run | None = None) -> str:
    """The gallery page of the shipped workflow ``name`` (file ``path``): what it reproduces, how to run it, its
    steps (each linked to its stage's page), outputs and report lines, and what ``run`` (a run of it the build was
    given) produced: its time, its report's summary filled in, its figures with their captions."""
    text = path.read_text()
    spec = yaml.safe_load(text)
    opening = _opening(text)
    cited = sorted(set(_THESIS.findall(opening)), key=opening.find)
    lines = [f"(workflow-{name})=", f"# {name}", "", markdown(opening), ""]
    if cited:
        lines += [f"**Thesis** {', '.join(cited)}", ""]
    lines += ["```console", f"selpath workflows --copy my-workflows && selpath run my-workflows/{name}.yaml", "```",
              ""]
    steps = spec.get("steps", [])
    lines += ["## Steps", "", "| step | stage | what it does |", "|---|---|---|"]
    for step in steps:
        known = step["stage"] in registry
        summary = registry[step["stage"]].summary if known else "(a stage of a plugin)"
        link = f"[`{step['stage']}`](../stages/{step['stage']}.md)" if known else f"`{step['stage']}`"
        lines.append(f"| `{step['id']}` | {link} | {_cell(summary)} |")
    lines.append("")
    outputs = spec.get("outputs", {})
    if outputs:
        lines += ["## Outputs", "", "| output | from step | store |", "|---|---|---|"]
        lines += [f"| `{key}` | `{value.get('from', '')}` | `{value.get('store', '')}` |"
                  for key, value in outputs.items()]
        lines.append("")
    summary = (spec.get("report") or {}).get("summary", [])
    if summary:
        lines += ["## What its report says", "", "Each line is filled in from the run's stores:", ""]
        lines += [f"- {_cell(line)}" for line in summary]
        lines.append("")
    if run is not None:
        lines += ["## A run", "", f"Run when this site was built: **{run.seconds:.0f} s** on {run.machine}, with the "
                  "compile cache as the build found it.", ""]
        lines += [f"- {_cell(line)}" for line in run.summary]
        lines.append("")
        for output, (image, caption) in run.figures.items():
            lines += [f"```{{figure}} {image}", f":alt: {output}", "", f"**{output}**. {_cell(caption)}", "```", ""]
        if not run.figures and not run.summary:
            lines += ["It draws no figure.", ""]
    lines += ["## The workflow file", "", f"```yaml\n{text.rstrip()}\n```", ""]
    return "\n".join(lines)


@dataclass(frozen=True)
class Run:
    """What a run of a workflow left for its gallery page: wall ``seconds``, the ``machine`` it ran on, its report's
    ``summary`` lines filled in, and ``figures`` (output → (image path relative to the page, caption))."""

    seconds: float
    machine: str
    summary: tuple[str, ...]
    figures: dict[str, tuple[str, str]]


def read_run(name: str, runs: Path, images: Path) -> Run | None:
    """The run of workflow ``name`` in ``runs`` (a folder of workflows copied with ``selpath workflows --copy`` and
    run there, each leaving ``<name>.run.json``: ``seconds`` and ``machine``, written by ``docs/run_gallery.py``),
    its figures' PNGs copied into ``images``; None where it was not run."""
    record = runs / f"{name}.run.json"
    if not record.is_file():
        return None
    from selpath.pipeline.report import summary_lines
    from selpath.pipeline.spec import load_workflow
    from selpath.pipeline.store import open_store

    facts = json.loads(record.read_text())
    workflow = load_workflow(runs / f"{name}.yaml")
    figures = {}
    for output, spec in workflow.outputs.items():
        png = Path(spec.store.removesuffix(".zarr") + ".png")
        if not png.is_file():
            continue
        target = images / name / f"{output}.png"
        target.parent.mkdir(parents=True, exist_ok=True)
        if not target.is_file() or target.read_bytes() != png.read_bytes():
            shutil.copyfile(png, target)
        caption = str(open_store(spec.store, registry=workflow.registry).attrs.get("caption", ""))
        figures[output] = (f"{images.name}/{name}/{output}.png", caption)
    summary = tuple(summary_lines(workflow)) if workflow.report else ()
    return Run(float(facts["seconds"]), str(facts.get("machine", "")), summary, figures)


def write_pages(folder: Path, registry: StageRegistry | None = None, workflows: dict[str, Path] | None = None,
                runs: Path | None = None, formats: dict[str, tuple[str, str, type]] | None = None) -> list[Path]:
    """Write every stage's, kind's and workflow's page under ``folder`` (``stages/``, ``kinds/``, ``workflows/``,
    each with an ``index.md``), replacing what was there (pages and figures of what no longer exists are removed);
    the paths written. ``workflows``: name → file (default:
    the shipped ones); ``runs``: a folder where they were run (:func:`read_run`), whose times, summaries and
    figures the gallery then shows; ``formats``: file name → (title, introduction, pydantic model) of the file
    formats to describe (:func:`model_page`, under ``formats/``)."""
    from selpath import workflows as shipped

    registry = default_registry() if registry is None else registry
    workflows = {n: shipped.path(n) for n in shipped.names()} if workflows is None else workflows
    written = []

    def write(path: Path, text: str) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        if not path.is_file() or path.read_text() != text:  # unchanged pages keep their time: no rebuild
            path.write_text(text)
        written.append(path)

    groups = {}
    for stage in registry:
        write(folder / "stages" / f"{stage.name}.md", stage_page(stage))
        group = stage.func.__module__.removeprefix("selpath.stages.").split(".")[0]
        groups.setdefault(group, []).append(stage)
    index = ["# Stages", "", "Every registered stage, by the module that holds it. `selpath stages NAME` prints the "
             "same in a terminal.", ""]
    for group, members in groups.items():
        index += [f"## {group}", "", "| stage | what it does |", "|---|---|"]
        index += [f"| [`{s.name}`]({s.name}.md) | {_cell(s.summary)} |" for s in members]
        index.append("")
    index += ["```{toctree}", ":hidden:", "", *[s.name for s in registry], "```", ""]
    write(folder / "stages" / "index.md", "\n".join(index))
    kinds = registry.kinds
    for name, kind in kinds.items():
        write(folder / "kinds" / f"{name}.md", kind_page(kind, registry.makers(name)))
    index = ["# Cube kinds", "", "What each store holds: its variables with their dims and units, its coordinates' "
             "units and the attrs it must carry. `selpath kinds NAME` prints the same.", "",
             "| kind | what it holds |", "|---|---|"]
    index += [f"| [`{n}`]({n}.md) | {_cell(k.description or '')} |" for n, k in kinds.items()]
    index += ["", "```{toctree}", ":hidden:", "", *kinds, "```", ""]
    write(folder / "kinds" / "index.md", "\n".join(index))
    done = {name: read_run(name, runs, folder / "workflows" / "figures") if runs else None for name in workflows}
    for name, path in workflows.items():
        write(folder / "workflows" / f"{name}.md", workflow_page(name, path, registry, done[name]))
    index = ["# Gallery of workflows", "", "One page per shipped workflow: what it reproduces from the thesis, its "
             "steps and outputs, and (where the site's build ran it) its figures and time. `selpath workflows` lists "
             "them; `selpath workflows --copy DIR` copies them to run.", "",
             "| workflow | what it does | time |", "|---|---|---:|"]
    index += [f"| [{n}]({n}.md) | {_cell(_opening(p.read_text()).split('. ')[0])} | "
              f"{'—' if done[n] is None else f'{done[n].seconds:.0f} s'} |" for n, p in workflows.items()]
    index += ["", "```{toctree}", ":hidden:", "", *workflows, "```", ""]
    write(folder / "workflows" / "index.md", "\n".join(index))
    for name, (title, intro, model) in (formats or {}).items():
        write(folder / "formats" / f"{name}.md", model_page(title, intro, model))
    # what an earlier build wrote for a stage, kind, workflow or format that is gone (renamed, a plugin removed):
    # Sphinx would read it and warn that no toctree holds it
    kept = set(written) | {folder / "workflows" / "figures" / name for name, run in done.items() if run and run.figures}
    for part in ("stages", "kinds", "workflows", "formats"):
        for stale in sorted((folder / part).glob("*.md")) if (folder / part).is_dir() else ():
            if stale not in kept:
                stale.unlink()
    figures = folder / "workflows" / "figures"
    for stale in sorted(figures.iterdir()) if figures.is_dir() else ():
        if stale not in kept:
            shutil.rmtree(stale)
    return written
