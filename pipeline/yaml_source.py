"""YAML files with locations: safe reading within budgets, and every problem at ``file:line``.

Workflows (:mod:`selpath.pipeline.spec`), scenes and rig files are read here: UTF-8 text only, PyYAML's safe
loader, a document whose aliases would expand past :data:`MAX_NODES` (a "billion laughs") or nest past
:data:`MAX_DEPTH` refused before anything walks it, and a map from each path in the document to its line,
so a pydantic error becomes ``scene.yaml:12: camera.rows: …``.
"""

from __future__ import annotations

import difflib
import os
import typing
from pathlib import Path
from typing import Any, TypeVar

import pydantic
import yaml

from selpath.pipeline.errors import ConfigError, Problem, SpecError

#: Largest document accepted, counting every node as often as aliases repeat it. A workflow has hundreds; nested
#: aliases ("billion laughs") expand a few hundred bytes into billions, which no check may walk.
MAX_NODES = 100_000
#: Deepest nesting accepted (PyYAML and pydantic recurse once per level).
MAX_DEPTH = 64


def _expanded_size(root: yaml.Node, source: str) -> int:
    """Nodes of the document with aliases expanded, counted without expanding them (each node once: linear);
    raises SpecError past MAX_NODES or MAX_DEPTH, or for a recursive alias."""
    sizes: dict[int, int] = {}
    on_path: set[int] = set()

    def size(node: yaml.Node, depth: int) -> int:
        key = id(node)
        if key in sizes:
            return sizes[key]
        if key in on_path:
            raise SpecError(Problem("an alias refers to a node that contains it (a recursive document)",
                                    f"{source}:{node.start_mark.line + 1}", fix="write the value out"))
        if depth > MAX_DEPTH:
            raise SpecError(Problem(f"nested deeper than {MAX_DEPTH} levels", f"{source}:{node.start_mark.line + 1}"))
        on_path.add(key)
        children = ([v for pair in node.value for v in pair] if isinstance(node, yaml.MappingNode)
                    else node.value if isinstance(node, yaml.SequenceNode) else [])
        total = 1 + sum(size(child, depth + 1) for child in children)
        on_path.discard(key)
        sizes[key] = total
        if total > MAX_NODES:
            raise SpecError(Problem(f"the document expands to more than {MAX_NODES:,} nodes through its aliases "
                                    "(a YAML bomb, or a file that is not a workflow)",
                                    f"{source}:{node.start_mark.line + 1}",
                                    fix="write the workflow without nested aliases"))
        return total

    return size(root, 0)


def _locations(node: yaml.Node, path: tuple = (), out: dict | None = None, seen: set | None = None
               ) -> dict[tuple, int]:
    """Map each path in the document (keys and list indices) to its 1-based line. A node reached again through
    an alias is not walked again (its paths resolve to the alias's line)."""
    out = {} if out is None else out
    seen = set() if seen is None else seen
    out[path] = node.start_mark.line + 1
    if id(node) in seen:
        return out
    seen.add(id(node))
    if isinstance(node, yaml.MappingNode):
        for key, value in node.value:
            out[(*path, key.value)] = key.start_mark.line + 1
            _locations(value, (*path, key.value), out, seen)
            out[(*path, key.value)] = key.start_mark.line + 1
    elif isinstance(node, yaml.SequenceNode):
        for i, item in enumerate(node.value):
            _locations(item, (*path, i), out, seen)
    return out


def format_path(path: tuple) -> str:
    text = ""
    for part in path:
        text += f"[{part}]" if isinstance(part, int) else (f".{part}" if text else str(part))
    return text


class Located:
    def __init__(self, source: str, lines: dict[tuple, int]):
        self.source, self.lines, self.problems = source, lines, []

    def add(self, path: tuple, message: str, fix: str = "") -> None:
        probe = path
        while probe and probe not in self.lines:
            probe = probe[:-1]
        self.problems.append(Problem(message, f"{self.source}:{self.lines.get(probe, 1)}", format_path(path), fix))


def read_source(path_or_text: str | os.PathLike, source: str | None, what: str = "workflow") -> tuple[str, str, Path]:
    candidate = Path(path_or_text) if not isinstance(path_or_text, str) or "\n" not in path_or_text else None
    if candidate is not None:
        if not candidate.is_file():
            raise SpecError(Problem(f"no such {what} file", where=str(candidate), fix="check the path"))
        data = candidate.read_bytes()
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as exc:
            line = data[: exc.start].count(b"\n") + 1
            raise SpecError(Problem(f"not UTF-8 text (byte {data[exc.start]:#04x} at offset {exc.start}): a {what} "
                                    "file is YAML text", where=f"{candidate}:{line}",
                                    fix="check that this is the right file; save it as UTF-8")) from None
        return text, source or str(candidate), candidate.resolve().parent
    return str(path_or_text), source or f"<{what}>", Path.cwd()


def parse_yaml(text: str, source: str) -> tuple[Any, Located]:
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is not None:
            _expanded_size(node, source)
        raw = loader.construct_document(node) if node is not None else None
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        line = f":{mark.line + 1}" if mark else ""
        raise SpecError(Problem(f"not valid YAML: {getattr(exc, 'problem', exc)}", where=f"{source}{line}")) from exc
    except RecursionError:
        raise SpecError(Problem(f"nested too deeply to read (over {MAX_DEPTH} levels)", where=source)) from None
    finally:
        loader.dispose()
    return raw, Located(source, _locations(node) if node is not None else {})


M = TypeVar("M", bound=pydantic.BaseModel)


def load_yaml_model(path_or_text: str | os.PathLike, model: type[M], *, what: str = "configuration") -> M:
    """Read a YAML file (or text) into a pydantic ``model``; one SpecError lists every problem with file:line.

    Used for every YAML file selpath reads besides workflows (scenes, rig configurations).
    """
    text, source, _ = read_source(path_or_text, None, what)
    raw, located = parse_yaml(text, source)
    try:
        return model.model_validate(raw)
    except pydantic.ValidationError as exc:
        for err in exc.errors():
            located.add(_document_path(raw, err["loc"]), pydantic_message(err), _suggestion(err, model))
        raise ConfigError(located.problems) from None


def field_names(model: type[pydantic.BaseModel]) -> set[str]:
    """Every field name (or alias) of ``model`` and of the models its fields hold, through lists, unions and dicts.

    >>> Inner = pydantic.create_model("Inner", pixel_centres=(str, "whole"))
    >>> Outer = pydantic.create_model("Outer", frames=(list[Inner] | None, None))
    >>> sorted(field_names(Outer))
    ['frames', 'pixel_centres']
    """
    seen, names = set(), set()

    def visit(annotation: Any) -> None:
        for argument in typing.get_args(annotation):
            visit(argument)
        if isinstance(annotation, type) and issubclass(annotation, pydantic.BaseModel) and annotation not in seen:
            seen.add(annotation)
            for name, field in annotation.model_fields.items():
                names.add(field.alias or name)
                visit(field.annotation)

    visit(model)
    return names


def _suggestion(err: dict, model: type[pydantic.BaseModel]) -> str:
    """For a field the model does not know, the known one its name is closest to (a misspelling), if any."""
    if err["type"] != "extra_forbidden" or not err["loc"]:
        return ""
    close = difflib.get_close_matches(str(err["loc"][-1]), sorted(field_names(model)), n=1, cutoff=0.75)
    return f"did you mean {close[0]!r}?" if close else ""


def _document_path(raw: Any, loc: tuple) -> tuple:
    """A pydantic error location as a path in the document: union tags (``kind: cylinder``) dropped."""
    path, node = [], raw
    for part in loc:
        if isinstance(node, dict) and part not in node and part in (node.get("kind"), node.get("model")):
            continue  # a discriminated union's tag, not a key of the file
        if str(part).startswith("function-"):
            continue
        path.append(part)
        if isinstance(node, dict):
            node = node.get(part)
        elif isinstance(node, list) and isinstance(part, int) and part < len(node):
            node = node[part]
        else:
            node = None
    return tuple(path)


def pydantic_message(err: dict) -> str:
    if err["type"] == "missing":
        return "is required but missing"
    if err["type"] == "extra_forbidden":
        return "is not a known field"
    message = err["msg"].removeprefix("Value error, ")
    if isinstance(err.get("input"), dict | list):
        return message
    return f"{message} (got {err['input']!r})"
