"""How a store was made: provenance in its ``_selpath`` child group, and store identities.

The provenance (step hash, workflow text, upstream settings, input identities, versions, usable shares) is
written by the engine once an output is complete; it sits in a child group because appends rewrite the root
group's attrs (xarray #8755) and never touch a child group. ``store_identity`` is what a step that reads a
store records of it, so the step reruns when the store changes.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import zarr

from selpath.pipeline import remote
from selpath.pipeline.errors import StoreError
from selpath.pipeline.integrity import PROVENANCE_GROUP, consolidate, is_selpath_store, open_group, unreadable_record


def jsonable(value: Any) -> Any:
    return json.loads(json.dumps(value, default=_json_default, sort_keys=True))


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"{type(value).__name__} is not JSON serialisable")


def write_provenance(path: str | os.PathLike, provenance: Mapping[str, Any]) -> None:
    """Record how a store was made, in its ``_selpath`` child group (safe from appends), and consolidate the
    store's metadata again (written last, provenance would otherwise be missing from the consolidated copy)."""
    group = open_group(path, mode="r+")
    child = group.require_group(PROVENANCE_GROUP)
    child.attrs["provenance"] = jsonable(dict(provenance))
    consolidate(path)


def read_provenance(path: str | os.PathLike) -> dict[str, Any] | None:
    """The provenance recorded by :func:`write_provenance`, or None if the store has none (or is absent)."""
    try:
        group = open_group(path)
        return dict(group[PROVENANCE_GROUP].attrs["provenance"])
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError, zarr.errors.NodeTypeValidationError):
        return None
    except Exception as exc:  # noqa: BLE001 - torn or garbled metadata: JSON, UTF-8 and zarr's own errors
        raise unreadable_record(path, "provenance", exc) from exc


#: bytes read at a time when a store is identified by its content
_BLOCK = 1 << 20


def content_digest(path: str | os.PathLike) -> str:
    """SHA-256 of a local store's content: every file's path relative to the store, size and bytes, in sorted
    order. Modification times, inodes and the store's own location play no part, so a copy (``cp``, ``rsync``,
    an unpacked tarball) has the digest of its original, and any changed byte changes it. Reads the whole store
    (hashlib's SHA-256 runs at about 1–2 GB/s on one core: seconds for a large capture)."""
    digest = hashlib.sha256()
    root = Path(path)
    for file in sorted(p for p in root.rglob("*") if p.is_file()):
        hash_file(digest, file, file.relative_to(root).as_posix())
    return digest.hexdigest()


def hash_file(digest, file: Path, name: str) -> None:
    """Feed ``name``, the file's size and every byte of ``file`` into ``digest`` (a hashlib object)."""
    digest.update(f"{name}:{file.stat().st_size}\n".encode())
    with file.open("rb") as handle:
        while block := handle.read(_BLOCK):
            digest.update(block)


def store_identity(path: str | os.PathLike) -> dict[str, Any]:
    """What identifies a store's content for a step that reads it, wherever the store lies: the provenance hash
    of a store a workflow wrote (the same computation gives the same data; its chunks carry checksums, so a
    changed byte is found when read), else (:func:`selpath.pipeline.store.to_store` or other writers) the SHA-256 of
    its content (:func:`content_digest`). Never its path or modification times: a moved or copied archive keeps
    its identity. A remote store (``scheme://…``) that no workflow wrote is identified by its objects' keys, sizes
    and ETags (:func:`selpath.pipeline.remote.object_identity`: one listing, no bytes read)."""
    where = os.fspath(path)
    prov = read_provenance(where)
    if prov and "step_hash" in prov:
        return {"step_hash": prov["step_hash"]}
    if remote.is_url(where):
        return {"objects_sha256": remote.object_identity(where)}
    return {"content_sha256": content_digest(where)}


def archive_stores(folder: str | os.PathLike) -> list[dict[str, Any]]:
    """Every selpath store under ``folder`` (not descending into stores, skipping staging leftovers), with what
    its provenance says: path relative to the folder, kind, workflow, output, stage, creation time and whether a
    workflow or another writer made it (``problem``: why its provenance record cannot be read, else None). Reads
    metadata only."""
    root = Path(folder)
    found: list[dict[str, Any]] = []

    def visit(path: Path) -> None:
        if is_selpath_store(path):
            attrs = json.loads((path / "zarr.json").read_text()).get("attributes") or {}
            try:
                prov, problem = read_provenance(path) or {}, None
            except StoreError as exc:  # one garbled record: listed as such, the others still listed
                prov, problem = {}, exc.problems[0].message
            found.append({"store": path.relative_to(root).as_posix() or ".", "kind": attrs.get("selpath_kind"),
                          "workflow": "(selpath import)" if prov.get("imported") else prov.get("workflow"),
                          "output": prov.get("output"),
                          "stage": (prov.get("step_record") or {}).get("stage"), "created": prov.get("created"),
                          "problem": problem})
            return
        for child in sorted(path.iterdir()):
            if child.is_dir() and not child.is_symlink() and not child.name.startswith("."):
                visit(child)

    visit(root)
    return found
