"""Captures written frame by frame, so a killed acquisition loses at most the frame in flight and resumes.

A capture store is created whole from a template (:func:`create_capture`: every frame NaN, nothing written); each
frame lands with :func:`write_frame`, which sets ``written__<var>`` for it only after its pixels are stored;
:func:`missing_frames` lists what is still to capture and :func:`forget_frames` marks frames whose chunks are bad as
not captured, so the next run captures them again. The store's layout is :mod:`selpath.pipeline.store`'s.
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
import zarr

from selpath.pipeline.errors import Problem, SelpathError, StoreError
from selpath.pipeline.integrity import WRITTEN_PREFIX, BadChunk, drop_chunk_sizes, open_group, write_manifest
from selpath.pipeline.kinds import CubeKind
from selpath.pipeline.provenance import jsonable
from selpath.pipeline.registry import resolve_kind
from selpath.pipeline.store import open_store, stamp, writable


def create_capture(path: str | os.PathLike, template: xr.Dataset, kind: str | CubeKind) -> xr.Dataset:
    """Pre-allocate a store for frame-by-frame capture, or reopen a matching one to resume.

    ``template`` holds the full cube with lazy (dask) data that is never computed: only its metadata,
    dims, coords and attrs are used. Data variables are chunked one frame per chunk. If a store already
    exists at ``path`` with the same variables, dims, coords and attrs, it is kept untouched (so
    :func:`missing_frames` tells what to capture next); if it differs, nothing is overwritten.
    Returns the opened store with its ``written__*`` flags.
    """
    where = os.fspath(path)
    spec_kind = resolve_kind(kind)  # a StoreError for an unknown kind
    template = stamp(template, spec_kind)  # raises for a template that breaks its schema
    if Path(where).exists():
        existing = open_store(where, spec_kind, keep_flags=True)
        differences = _sweep_differences(existing, template)
        if differences:
            raise StoreError(
                [Problem(d, where=where) for d in differences]
                + [Problem("a different sweep is already stored here", where=where,
                           fix="choose another store path, or delete this one to start over")]
            )
        drop_chunk_sizes(where)  # frames may be written: the sizes are recorded anew once the capture is complete
        return existing
    flags = {}
    for name, var in template.data_vars.items():
        frame_dims = spec_kind.frame_dims(str(name))
        shape = tuple(template.sizes[d] for d in frame_dims)
        flags[f"{WRITTEN_PREFIX}{name}"] = (frame_dims, np.zeros(shape, dtype=bool))
        template[name] = var.chunk(dict.fromkeys(frame_dims, 1))
    template = writable(template.assign(flags))
    template.to_zarr(where, mode="w-", consolidated=False, compute=False, write_empty_chunks=True)
    # the flags are small numpy arrays: write them for real, so every frame starts as missing
    template[list(flags)].to_zarr(where, mode="r+", consolidated=False, write_empty_chunks=True)
    write_manifest(where, template, complete=False)  # complete is what the frame flags say
    return open_store(where, spec_kind, keep_flags=True)


def _sweep_differences(existing: xr.Dataset, template: xr.Dataset) -> list[str]:
    out = []
    for name, var in template.data_vars.items():
        if name not in existing:
            out.append(f"variable {name!r} is not in the existing store")
        elif existing[name].dims != var.dims or existing[name].shape != var.shape:
            out.append(f"variable {name!r} is {existing[name].dims}{existing[name].shape}, "
                       f"the new sweep {var.dims}{var.shape}")
    for name, coord in template.coords.items():
        if name not in existing.coords or not np.array_equal(existing[name].values, coord.values):
            out.append(f"coordinate {name!r} differs from the new sweep's")
    for key, value in template.attrs.items():
        if jsonable(existing.attrs.get(key)) != jsonable(value):
            out.append(f"attr {key!r} is {existing.attrs.get(key)!r} in the store, {value!r} in the new sweep")
    return out


def write_frame(path: str | os.PathLike, variable: str, index: Mapping[str, int], frame: np.ndarray) -> None:
    """Write one frame into a pre-allocated store, then mark it written.

    ``index`` gives an integer position for each frame dim of ``variable`` (e.g. ``{"angle": 12}``).
    The pixels land before the flag, so an interrupted write is seen as missing and captured again.
    """
    where = os.fspath(path)
    group = open_group(where, mode="r+")
    flag_name = f"{WRITTEN_PREFIX}{variable}"
    if variable not in group or flag_name not in group:
        raise StoreError(Problem(f"variable {variable!r} was not pre-allocated for capture", where=where,
                                 fix="create the store with create_capture first"))
    empty = {"write_empty_chunks": True}  # a frame equal to the fill value still lands, so a gone chunk is seen
    array, flags = group[variable].with_config(empty), group[flag_name].with_config(empty)
    frame_dims = tuple(array.metadata.dimension_names)[: flags.ndim]
    if set(index) != set(frame_dims):
        raise StoreError(Problem(f"index {dict(index)} must name exactly the frame dims {frame_dims}", where=where,
                                 path=variable))
    position = tuple(int(index[d]) for d in frame_dims)
    frame = np.asarray(frame)
    if frame.shape != array.shape[len(frame_dims):]:
        raise StoreError(Problem(f"frame has shape {frame.shape}; the store expects {array.shape[len(frame_dims):]}",
                                 where=where, path=f"{variable}{list(position)}"))
    array[position] = frame
    flags[position] = True


def missing_frames(path: str | os.PathLike) -> dict[str, list[dict[str, Any]]]:
    """For each captured variable, the frames not yet written, as ``{dim: coordinate value}`` dicts.

    A frame counts as written when its flag is set *and* its chunks are on disk. Stores written whole
    (without ``written__*`` flags) have no missing frames.
    """
    ds = open_store(path, keep_flags=True)  # flags already cleared where a frame's chunk is gone
    out: dict[str, list[dict[str, Any]]] = {}
    for name in ds.data_vars:
        if not str(name).startswith(WRITTEN_PREFIX):
            continue
        flags = ds[name].load()
        positions = np.argwhere(~flags.values)
        out[str(name)[len(WRITTEN_PREFIX):]] = [
            {dim: (ds[dim].values[i].item() if dim in ds.coords else int(i))
             for dim, i in zip(flags.dims, pos, strict=True)}
            for pos in positions
        ]
    return out


def _is_frame_variable(group: zarr.Group, name: str) -> bool:
    """True if ``name`` is a capture's frame variable: it has a readable ``written__`` flag array."""
    if name.startswith(WRITTEN_PREFIX):
        return False
    try:
        return isinstance(group[f"{WRITTEN_PREFIX}{name}"], zarr.Array)
    except Exception:  # noqa: BLE001 - absent (KeyError) or its metadata garbled: not a frame to capture again
        return False


def forget_frames(path: str | os.PathLike, bad: Iterable[BadChunk]) -> int:
    """Mark the frames holding ``bad`` chunks (from :func:`~selpath.pipeline.integrity.verify_store`) as not captured,
    so the acquisition captures them again when it next runs. Returns how many frames were marked.

    Only a frame can be captured again: a bad chunk of a coordinate, of a ``written__`` flag or of metadata
    raises StoreError naming it, and no flag is changed."""
    where = os.fspath(path)
    group = open_group(where, mode="r+")
    bad = list(bad)
    others = [chunk for chunk in bad if chunk.chunk is None or not _is_frame_variable(group, chunk.variable)]
    if others:
        listed = "; ".join(str(chunk) for chunk in others[:3]) + (" …" if len(others) > 3 else "")
        raise StoreError(Problem(f"{len(others)} bad chunk(s) of this capture are not frames and cannot be captured "
                                 f"again ({listed})", where=where,
                                 fix="restore the store from a backup, or move it "
                                 "away and run again to capture from the start"))
    frames = set()
    for chunk in bad:
        flags, array = group[f"{WRITTEN_PREFIX}{chunk.variable}"], group[chunk.variable]
        position = tuple(c * s for c, s in zip(chunk.chunk[: flags.ndim], array.chunks, strict=False))
        frames.add((chunk.variable, position))
    drop_chunk_sizes(where)  # the frames are written again: the sizes are recorded anew once it is complete
    for variable, position in sorted(frames):
        group[f"{WRITTEN_PREFIX}{variable}"][position] = False
    return len(frames)


def has_missing_frames(store: str) -> bool:
    """Whether a capture store has frames still to capture (or cannot say which: a store that does not read)."""
    try:
        return any(missing_frames(store).values())
    except SelpathError:
        return True
