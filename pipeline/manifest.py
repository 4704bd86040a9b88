"""Which installed module declares each stage and each cube kind, kept on disk, so that a command needing a few stages
imports only their modules (the idea of napari's npe2 manifests, made here by importing every module once).

A manifest maps stage names and cube kind names to the module (one named by a ``selpath.stages`` entry point) that
declares them, with each stage's summary and kinds and each kind's description: enough to list them
(``selpath stages``, ``selpath kinds``) without importing any. The first full registry an installation builds
(:func:`~selpath.pipeline.registry.default_registry`) writes it to ``$XDG_CACHE_HOME/selpath/manifests``
(``~/.cache/selpath/manifests``; the environment variable ``SELPATH_MANIFEST_CACHE`` names another folder, or
``off``). Its file is named by a key made of the installed entry points, their distributions' versions, and the size
and modification time of every module they name: installing, removing or editing a stage module gives a new key and
so a new manifest. A kind declared in a module no entry point names, edited in place, can leave its description
stale until then; the modules are still only a hint: a stage the manifest does not name, or that its module no
longer declares, is looked for among every installed stage (:func:`~selpath.pipeline.registry.registry_for`).
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import os
import tempfile
from importlib.metadata import entry_points
from pathlib import Path

FORMAT = 2
#: the entry-point group whose modules declare stages (selpath's own and plugins')
GROUP = "selpath.stages"


def folder() -> Path | None:
    """Where manifests are kept; None when ``SELPATH_MANIFEST_CACHE=off`` or where no home folder is known."""
    setting = os.environ.get("SELPATH_MANIFEST_CACHE", "")
    if setting.lower() == "off":
        return None
    if setting:
        return Path(setting)
    try:
        return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "selpath" / "manifests"
    except RuntimeError:  # no HOME and no passwd entry: no cache, commands still work
        return None


def _module_stamp(module: str) -> list:
    """The module's file, size and modification time, found without importing it (only its parent packages)."""
    try:
        spec = importlib.util.find_spec(module)
    except Exception:  # noqa: BLE001 - a parent package fails to import: the full registry will say why
        return [module, "unfindable"]
    origin = getattr(spec, "origin", None)
    if not origin or not os.path.exists(origin):
        return [module, str(origin)]
    stat = os.stat(origin)
    return [module, origin, stat.st_size, stat.st_mtime_ns]


def key(group: str) -> str | None:
    """A digest of what the entry-point ``group`` installs (the entry points, their distributions and module files);
    None where that cannot be told (then no manifest is read or kept)."""
    try:
        points = sorted(entry_points(group=group), key=lambda e: (e.name, e.value))
        record = [[p.name, p.value, p.dist.name if p.dist else "", p.dist.version if p.dist else "",
                   _module_stamp(p.value.split(":")[0])] for p in points]
    except Exception:  # noqa: BLE001 - a cache never stops a command
        return None
    text = json.dumps([FORMAT, group, record], sort_keys=True)
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def _path(group: str, stamp: str | None = None) -> Path | None:
    where, stamp = folder(), stamp or key(group)
    return None if where is None or stamp is None else where / f"{group}-{stamp}.json"


def _valid(data) -> bool:
    """Whether ``data`` has the shape :func:`read` promises (a file edited by hand, or of another version, has not)."""
    if not isinstance(data, dict) or not all(isinstance(data.get(k), dict) for k in ("stages", "kinds")):
        return False
    stages = all(isinstance(v, dict) and isinstance(v.get("module"), str) and isinstance(v.get("summary"), str)
                 and isinstance(v.get("kinds"), list) and all(isinstance(k, str) for k in v["kinds"])
                 for v in data["stages"].values())
    kinds = all(isinstance(v, dict) and isinstance(v.get("module"), str) and isinstance(v.get("description"), str)
                for v in data["kinds"].values())
    return stages and kinds


def read(group: str, stamp: str | None = None) -> dict[str, dict[str, dict]] | None:
    """The manifest of what ``group`` installs now (or of the installation whose :func:`key` was ``stamp``):
    ``{"stages": {name: {"module", "summary", "kinds"}}, "kinds": {name: {"module", "description"}}}``; None when none
    is kept for it (never written, unreadable, malformed, or the cache is off)."""
    path = _path(group, stamp)
    try:
        data = json.loads(path.read_text(encoding="utf-8")) if path is not None else None
    except (OSError, ValueError):
        return None
    return {"stages": data["stages"], "kinds": data["kinds"]} if _valid(data) else None


def write(group: str, index: dict[str, dict[str, dict]], stamp: str | None = None) -> None:
    """Keep ``index`` (as :func:`read` returns it) as the manifest of ``group``, under ``stamp``: the :func:`key`
    taken *before* the modules were imported (a module edited meanwhile then gives another key, never a stale
    manifest under the new one). A cache: a folder that cannot be written (a read-only home) is passed over
    silently, and a manifest is replaced whole, never half-written."""
    path = _path(group, stamp)
    if path is None or read(group, stamp) == index:
        return
    text = json.dumps({"format": FORMAT} | index, indent=1, sort_keys=True, ensure_ascii=False)
    handle = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.NamedTemporaryFile("w", dir=path.parent, suffix=".tmp", delete=False,
                                         encoding="utf-8") as handle:
            handle.write(text)
        os.replace(handle.name, path)
    except OSError:
        if handle is not None:
            Path(handle.name).unlink(missing_ok=True)
