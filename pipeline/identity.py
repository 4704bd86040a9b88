"""What a step's identity is made of: its stage and where the stage's code lives, its settings (paths inside the
workflow's folder relative to it), the hashes of the steps it reads, the identity of external data it reads, and
selpath's version. A stored output whose provenance carries the same hash is reused, never recomputed
(:mod:`selpath.pipeline.engine`); :func:`why_changed` says which part differs when it is not.
"""

from __future__ import annotations

import hashlib
import json
import os
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import Any

from selpath.pipeline.spec import Workflow

_PACKAGES = ("selpath", "xarray", "dask", "zarr", "numpy", "jax")


def package_versions() -> dict[str, str]:
    out = {}
    for name in _PACKAGES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = "not installed"
    return out


def _digest(payload: Any) -> str:
    return hashlib.sha256(json.dumps(payload, sort_keys=True, default=str).encode()).hexdigest()[:32]


#: what a step record holds in place of the path of the store an acquisition fills (the output's location is not
#: part of what the step computes: the demo's folder, rerooted anywhere, keeps its captures)
OWN_STORE = "<its own output store>"


def portable(value: Any, folder: Path) -> Any:
    """``value`` with every absolute path inside ``folder`` written relative to it (POSIX, ``.`` for the folder
    itself), recursively through dicts and lists: what a step's identity holds, so that a workflow folder moved,
    copied or unpacked elsewhere has the same identities. Paths outside the folder stay absolute (the stages that
    read such files identify them by content as well)."""
    if isinstance(value, dict):
        return {k: portable(v, folder) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [portable(v, folder) for v in value]
    if isinstance(value, str) and os.path.isabs(value) and "://" not in value:
        path = Path(value)
        if path == folder or folder in path.parents:
            return path.relative_to(folder).as_posix()
    return value


def step_records(workflow: Workflow) -> dict[str, dict[str, Any]]:
    """For each step, what determines its result (stage, settings, inputs, external data) and its hash. Paths
    inside the workflow's folder are recorded relative to it (:func:`portable`): the identity of a step does not
    depend on where the folder lies."""
    records: dict[str, dict[str, Any]] = {}
    selpath_version = package_versions()["selpath"]
    folder = Path(workflow.base_dir).resolve()
    for step_id, step in workflow.steps.items():  # dependency order: inputs are already recorded
        settings = step.settings.model_dump(mode="json")
        if step.stage.writes is not None:  # where an acquisition writes is not what it captures
            own = step.stage.writes(step.settings)
            settings = {k: OWN_STORE if v == own else v for k, v in settings.items()}
        settings = portable(settings, folder)
        external = step.stage.identity(step.settings) if step.stage.identity else None
        record = {
            "stage": step.stage.name,
            "stage_source": step.stage.source,
            "selpath": selpath_version,
            "settings": settings,
            "inputs": {k: {"ref": str(r), "step_hash": records[r.step]["step_hash"]} for k, r in step.inputs.items()},
            "external": portable(external, folder),
        }
        record["step_hash"] = _digest(record)
        records[step_id] = record
    return records


def why_changed(stored: dict | None, record: dict, store: str) -> str:
    """Why a step runs: what of its record differs from the one its stored output was made with."""
    if stored is None:
        return f"no finished output at {store}"
    old = stored.get("step_record", {})
    changed = sorted(k for k in set(old.get("settings", {})) | set(record["settings"])
                     if old.get("settings", {}).get(k) != record["settings"].get(k))
    if changed:
        return "settings changed: " + ", ".join(
            f"{k} {old.get('settings', {}).get(k)!r} -> {record['settings'].get(k)!r}" for k in changed)
    if old.get("stage") != record["stage"] or old.get("stage_source") != record["stage_source"]:
        return "stage changed"
    if old.get("selpath") != record["selpath"]:
        return f"selpath version changed ({old.get('selpath')} -> {record['selpath']})"
    inputs = sorted(k for k in record["inputs"] if old.get("inputs", {}).get(k) != record["inputs"][k])
    if inputs:
        return "inputs changed: " + ", ".join(record["inputs"][k]["ref"] for k in inputs)
    return "input data changed"
