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

from pipeline.integrity import PROVENANCE_GROUP, consolidate, open_group


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


def store_identity(path: str | os.PathLike) -> dict[str, Any]:
    """What identifies a store's content for provenance: its own provenance hash if selpath made it,
    else a fingerprint of its metadata and (for local stores) file sizes and modification times."""
    where = os.fspath(path)
    prov = read_provenance(where)
    if prov and "step_hash" in prov:
        return {"store": where, "step_hash": prov["step_hash"]}
    digest = hashlib.sha256()
    root = Path(where)
    if root.is_dir():
        for file in sorted(root.rglob("*")):
            if file.is_file():
                stat = file.stat()
                digest.update(f"{file.relative_to(root)}:{stat.st_size}:{stat.st_mtime_ns}\n".encode())
                if file.name == "zarr.json":
                    digest.update(file.read_bytes())
    return {"store": where, "fingerprint": digest.hexdigest()}
