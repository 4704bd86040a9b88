"""Zarr stores of capture cubes: open with a schema check, write lazily (frame by frame:
:mod:`selpath.pipeline.capture_store`).

Layout of a store (zarr v3 group; see ``docs/format.md``):

* the xarray variables and coords of the cube, with group attrs ``selpath_format`` (int) and
  ``selpath_kind`` plus the kind's required attrs;
* for stores filled frame by frame, one boolean variable ``written__<var>`` per data variable over its
  frame dims, set *after* the frame's pixels land, so a kill at any point loses at most the frame in
  flight and :func:`selpath.pipeline.capture_store.missing_frames` says exactly which frames to capture again;
* a child group ``_selpath`` whose attrs hold the manifest (complete, units; :mod:`selpath.pipeline.integrity`)
  and the provenance. Appends and region writes rewrite the root group's attrs (xarray #8755) but never
  touch a child group, and ``xr.open_zarr`` ignores it.

Every chunk carries a crc32c checksum; reading a corrupt one raises a StoreError naming store, variable
and chunk. Whole stores are written into a temporary sibling and moved into place when complete
(:mod:`selpath.pipeline.outputs`). Strings are written as zarr's variable-length UTF-8, never numpy's fixed-width
``<U`` (zarr v3 has no specification for it and warns). The root ``zarr.json`` carries consolidated metadata,
rewritten whenever the manifest or provenance is (:func:`selpath.pipeline.integrity.consolidate`), so plain
``xr.open_zarr(path)`` opens a store quietly; selpath itself always reads each node's own metadata.
"""

from __future__ import annotations

import itertools
import os
import warnings
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import dask
import numpy as np
import xarray as xr
from dask.base import tokenize

from selpath.pipeline import remote
from selpath.pipeline.errors import Problem, StoreError, environment_fault
from selpath.pipeline.integrity import (
    CHECKSUMMED_FORMAT,
    WRITTEN_PREFIX,
    absent_chunks,
    compressors,
    decode_error,
    open_group,
    read_manifest,
    units_problems,
    write_manifest,
    written_frames,
)
from selpath.pipeline.kinds import FORMAT_VERSION, CubeKind
from selpath.pipeline.migrations import MIGRATIONS
from selpath.pipeline.outputs import Staging
from selpath.pipeline.provenance import read_provenance
from selpath.pipeline.registry import StageRegistry, resolve_kind


class IncompleteCaptureWarning(UserWarning):
    """A capture store opened for processing still misses frames."""


class IncompleteStoreWarning(UserWarning):
    """A store opened for processing has no record that its writing finished."""


#: target size of the dask chunks a store is read in (a whole number of its on-disk chunks)
PROCESSING_CHUNK = "16MiB"


def processing_chunks(shape: tuple[int, ...], disk: tuple[int, ...], itemsize: int) -> tuple[int, ...]:
    """Dask chunks for reading an array stored in ``disk`` chunks: whole on-disk chunks grouped along the
    leading (frame) dims up to about PROCESSING_CHUNK; an on-disk chunk larger than that is kept whole.

    A capture is stored one frame per chunk for resumable writes (one task per frame would drown the
    scheduler in overhead); a transport store holds bands of rows. dask's ``chunks="auto"`` splits an on-disk
    chunk above its limit, and every piece then reads and decompresses the whole chunk: a 31 MB band of a
    75-frame stack became 4800 one-row tasks that each decoded all of it. Written by hand: dask's
    normalize_chunks("auto", previous_chunks=…) evens chunks out and splits on-disk ones (6 frames stored
    4 + 2 came back 3 + 3).
    """
    limit = dask.utils.parse_bytes(PROCESSING_CHUNK)
    chunks, nbytes = list(disk), int(np.prod(disk)) * itemsize
    for axis, (extent, size) in enumerate(zip(shape, disk, strict=True)):
        multiple = max(1, min(-(-extent // size), limit // max(nbytes, 1)))
        chunks[axis], nbytes = size * multiple, nbytes * multiple
        if chunks[axis] < extent:
            break
    return tuple(chunks)


class CheckedArray:
    """A lazily indexed store variable whose read errors name the store, variable and chunk.

    Handed to ``dask.array.from_array``: each task reads one block through xarray's decoding; if zarr or
    a codec fails (checksum mismatch, truncated zstd frame), the chunks under the block are read one by
    one to find the bad ones, and a StoreError names them.
    """

    def __init__(self, variable: xr.Variable, where: str, name: str, disk_chunks: tuple[int, ...]):
        self.variable, self.where, self.name, self.disk_chunks = variable, where, name, disk_chunks
        self.shape, self.dtype, self.ndim = variable.shape, variable.dtype, variable.ndim

    def __getitem__(self, key: tuple) -> np.ndarray:
        try:
            return np.asarray(self.variable[key].values)
        except StoreError:
            raise
        except Exception as exc:  # noqa: BLE001
            raise StoreError(self._problem(key, exc)) from exc

    def _problem(self, key: tuple, exc: Exception) -> Problem:
        ranges = []
        for axis, part in enumerate(key if isinstance(key, tuple) else (key,)):
            start, stop, _ = part.indices(self.shape[axis]) if isinstance(part, slice) else (part, part + 1, 1)
            size = self.disk_chunks[axis]
            ranges.append(range(start // size, max(start // size + 1, -(-stop // size))))
        bad = []
        group = open_group(self.where)
        for coords in itertools.product(*ranges):
            try:
                group[self.name].get_block_selection(coords)
            except Exception as inner:  # noqa: BLE001
                bad.append(f"{coords} ({decode_error(inner)})")
        chunks = ", ".join(bad) if bad else f"in {tuple((r.start, r.stop - 1) for r in ranges)} ({decode_error(exc)})"
        return Problem(f"chunk {chunks} cannot be read: the store is corrupt", where=self.where,
                       path=f"variable {self.name}", fix="restore it from a backup or write it again; "
                       "`selpath inspect --verify STORE` lists every bad chunk")


def _open_raw(path: str | os.PathLike) -> xr.Dataset:
    """The store's cube, each data variable a dask array read through :class:`CheckedArray`
    in processing chunks (whole on-disk chunks), so a corrupt chunk raises a StoreError naming it."""
    where = os.fspath(path)
    if not (remote.exists(where) if remote.is_url(where) else Path(where).exists()):
        raise StoreError(Problem("no store at this path" if not remote.is_url(where) else
                                 "no store at this URL (no zarr.json under it)", where=where,
                                 fix="check the path, or run the step that writes it; for object storage, the "
                                 "credentials and endpoint in the environment (AWS_PROFILE, AWS_ENDPOINT_URL …)"))
    try:
        ds = xr.open_dataset(where, engine="zarr", consolidated=False, decode_timedelta=False, chunks=None,
                             cache=False)
    except Exception as exc:  # zarr/xarray raise many types for a corrupt store; name it, keep the cause
        fault = environment_fault(exc, "reading the store")  # unreadable to this user: no corruption
        if fault is not None:
            raise fault from exc
        raise StoreError(
            Problem(f"cannot be read as a zarr store ({type(exc).__name__}: {exc})", where=where,
                    fix="the store is corrupt or not zarr v3; re-create it or restore it from a backup")
        ) from exc
    import dask.array as da  # with its scipy: on opening a store, not on reading a workflow

    stamp = _store_stamp(where)
    lazy = {}
    for name, var in ds.data_vars.items():
        disk = tuple(var.encoding.get("chunks") or var.shape)
        if var.dtype.kind in "OSUVT" or 0 in var.shape:  # strings (T: numpy's StringDType) are read as they are
            continue
        chunks = processing_chunks(var.shape, disk, var.dtype.itemsize) if var.ndim else ()
        data = da.from_array(CheckedArray(var.variable, where, str(name), disk), chunks=chunks, lock=False,
                             name=f"open-{name}-{tokenize(where, str(name), chunks, stamp)}",
                             meta=np.empty((0,) * var.ndim, dtype=var.dtype))
        lazy[name] = var.copy(data=data)
        lazy[name].encoding = var.encoding
    return ds.assign(lazy) if lazy else ds


def _store_stamp(where: str) -> str:
    """Changes whenever the store is rewritten (its root metadata file is replaced): part of dask key names."""
    if remote.is_url(where):
        return remote.stamp(where)
    try:
        meta = Path(where) / "zarr.json"
        return f"{meta.stat().st_mtime_ns}:{meta.stat().st_ino}"
    except OSError:
        return where


def _migrate(ds: xr.Dataset, where: str, kind: CubeKind) -> xr.Dataset:
    version = ds.attrs.get("selpath_format")
    if not isinstance(version, int | np.integer) or isinstance(version, bool):
        raise StoreError(
            Problem(f"attr selpath_format is {version!r}; expected an integer schema version", where=where,
                    fix=f"stores of this selpath carry selpath_format = {FORMAT_VERSION}")
        )
    if version > FORMAT_VERSION:
        raise StoreError(
            Problem(f"format {version} is newer than this selpath reads (format {FORMAT_VERSION})", where=where,
                    fix="upgrade selpath (pip install -U selpath)")
        )
    while version < FORMAT_VERSION:
        if version not in MIGRATIONS:
            raise StoreError(Problem(f"no migration from format {version}", where=where))
        ds = MIGRATIONS[version](ds, kind)
        version += 1
        ds.attrs["selpath_format"] = version
    return ds


def open_store(path: str | os.PathLike, kind: str | CubeKind | None = None, *, keep_flags: bool = False,
               registry: StageRegistry | None = None) -> xr.Dataset:
    """Open a store lazily, migrate it if old, and check it against its kind's schema.

    ``kind`` defaults to the store's ``selpath_kind`` attr; when both are given they must agree. A kind named by
    its name is looked up in ``registry`` (a workflow's), else among the installed stages' kinds.
    Every problem is reported at once in one :class:`StoreError`. The ``written__*`` frame flags
    are dropped unless ``keep_flags``; dropping them from an unfinished capture warns, naming how many
    frames of which variable are missing (they read as the fill value, NaN, and would pass unnoticed).
    """
    where = os.fspath(path)
    raw = _open_raw(path)
    manifest = read_manifest(where)
    edited = [Problem(p.message, where=where, path=p.path, fix=p.fix) for p in units_problems(raw, manifest)]
    checksummed = raw.attrs.get("selpath_format", 0) >= CHECKSUMMED_FORMAT  # format 2 writes every chunk
    stored_kind = raw.attrs.get("selpath_kind")
    if kind is None and stored_kind is None:
        raise StoreError(Problem("attr selpath_kind is missing and no kind was given", where=where,
                                 fix="set ds.attrs['selpath_kind'] to the name of its kind (`selpath kinds` lists "
                                 "them), or pass kind="))
    try:
        spec = resolve_kind(stored_kind if kind is None else kind, registry,
                            module=raw.attrs.get("selpath_kind_module"))  # where the kind was declared: a hint
    except StoreError as exc:
        raise StoreError([Problem(p.message, where=where, path=p.path, fix=p.fix) for p in exc.problems]) from None
    ds = _migrate(raw, where, spec)
    problems = edited + ([] if stored_kind in (None, spec.name) else [
        Problem(f"store holds a {stored_kind!r} cube, not a {spec.name!r} cube", where=where)
    ])
    problems += [Problem(p.message, where=where, path=p.path, fix=p.fix) for p in spec.check(ds)]
    flags = [v for v in ds.data_vars if str(v).startswith(WRITTEN_PREFIX)]
    if checksummed:  # coordinates and flags are written whole when a store is made; data once it is complete
        whole = [str(v) for v in raw.coords] + [str(v) for v in flags]
        if not flags and (manifest or {}).get("complete"):
            whole += [str(v) for v in raw.data_vars]
        problems += [Problem(p.message, where=where, path=p.path, fix=p.fix) for p in absent_chunks(where, whole)]
    if problems:
        raise StoreError(problems)
    if flags and checksummed:  # a frame flagged written whose chunk is gone is missing again (format 1 did not
        # write chunks holding only the fill value: there an absent chunk is no evidence)
        ds = ds.assign({name: ds[name].copy(data=written_frames(where, str(name)[len(WRITTEN_PREFIX):],
                                                                ds[name].values)) for name in flags})
    elif not is_complete(where, manifest):
        warnings.warn(f"{where}: no record that writing this store finished (a run killed while writing it, or a "
                      "store selpath did not write); its data may be partial. Write it again, or check it with "
                      "`selpath inspect --verify`", IncompleteStoreWarning, stacklevel=2)
    if not keep_flags:
        for name in flags:
            written = ds[name].values
            if not written.all():
                warnings.warn(f"{where}: {int((~written).sum())} of {written.size} frames of "
                              f"{str(name)[len(WRITTEN_PREFIX):]!r} were never captured and read as NaN; run the "
                              "acquisition again to capture them (it resumes)", IncompleteCaptureWarning,
                              stacklevel=2)
        ds = ds.drop_vars(flags)
    return ds


def is_complete(path: str | os.PathLike, manifest: Mapping[str, Any] | None = None) -> bool:
    """Whether a store records that its writing finished: a manifest saying so (format 2), or for stores of
    format 1 a provenance record. Captures filled frame by frame are complete when every frame is written."""
    manifest = read_manifest(path) if manifest is None else manifest
    return bool((manifest or {}).get("complete")) or read_provenance(path) is not None


def stamp(ds: xr.Dataset, kind: CubeKind) -> xr.Dataset:
    """``ds`` labelled as a ``kind`` cube (its ``selpath_kind`` attr and its variables' units and long names,
    :meth:`CubeKind.label`) with the ``selpath_format`` attr, after checking it against ``kind``."""
    ds = kind.label(ds)
    problems = kind.check(ds)
    if problems:
        raise StoreError(problems)
    return ds.assign_attrs(selpath_format=FORMAT_VERSION)


def _portable_strings(ds: xr.Dataset) -> xr.Dataset:
    """``ds`` with its fixed-width numpy strings (``<U…``) as Python ``str`` objects, which zarr writes as its
    variable-length UTF-8 type: zarr v3 has no specification for fixed-length UTF-32 and warns
    (``UnstableSpecificationWarning``) on every write of it. xarray reads them back as numpy ``StringDType``."""
    fixed = {name: var.astype(object) for name, var in ds.variables.items() if var.dtype.kind == "U"}
    if not fixed:
        return ds
    coords = {name: var for name, var in fixed.items() if name in ds.coords}
    return ds.assign_coords(coords).assign({name: var for name, var in fixed.items() if name not in coords})


def writable(ds: xr.Dataset) -> xr.Dataset:
    """A copy whose dask chunks zarr can take (regular but for the last), stale encodings dropped, strings
    variable-length (:func:`_portable_strings`) and numeric data and coordinates compressed and checksummed
    (:func:`selpath.pipeline.integrity.compressors`)."""
    ds = _portable_strings(ds.copy())
    for name, var in ds.variables.items():
        ds[name].encoding = {"compressors": compressors()} if var.dtype.kind in "fiub" else {}
    if not any(var.chunks for var in ds.variables.values()):
        return ds
    # variables cut differently along a dim (a result beside its input's flags) get one cut: zarr needs it, and
    # Dataset.chunks refuses to answer until they do
    try:
        _ = ds.chunks  # raises while variables are cut differently
    except ValueError:
        from dask.array.core import PerformanceWarning

        with warnings.catch_warnings():  # dask counts the product of every dim's chunks, as if one array spanned
            warnings.simplefilter("ignore", PerformanceWarning)  # them all: a false alarm for many-dim datasets
            ds = ds.unify_chunks()
    regular = {}
    for dim, chunks in ds.chunks.items():
        if len(chunks) > 1 and (len(set(chunks[:-1])) > 1 or chunks[-1] > chunks[0]):
            regular[dim] = max(chunks)
    return ds.chunk(regular) if regular else ds


def write_store(ds: xr.Dataset, path: str | os.PathLike, kind: CubeKind, *, compute: bool = True,
                replace: bool = False):
    """Write a whole cube (checked and stamped) into a new store at ``path``, every chunk checksummed and
    written (fill-valued ones too), without the manifest: the building block of :func:`to_store`, for writers
    that stage, check and commit themselves (the engine). ``compute=False`` returns the dask delayed write;
    ``replace`` writes over a store there (object storage, where nothing can be staged and renamed)."""
    return writable(stamp(ds, kind)).to_zarr(os.fspath(path), mode="w" if replace else "w-", consolidated=False,
                                             compute=compute, write_empty_chunks=True)


def _replace_problem(path: str | os.PathLike) -> Problem | None:
    """Why ``to_store`` must not replace what is at ``path`` without ``replace=True``: a workflow's output (its
    provenance names it) or a capture still being filled (frame flags); None for a store ``to_store`` wrote."""
    where = os.fspath(path)
    if "://" in where or not Path(where).is_dir():
        return None
    provenance = read_provenance(where)
    if provenance is not None and provenance.get("imported"):
        return Problem("holds a capture imported with `selpath import`; to_store does not replace it", where=where,
                       fix="write to another path, or pass replace=True to replace it")
    if provenance is not None:
        return Problem(f"holds output {provenance.get('output')!r} of workflow {provenance.get('workflow')!r}; "
                       "to_store does not replace a workflow's output", where=where,
                       fix="write to another path, or pass replace=True to replace it")
    if any(p.name.startswith(WRITTEN_PREFIX) for p in Path(where).iterdir()):
        return Problem("holds a capture (frame by frame, with frame flags); to_store does not replace it",
                       where=where, fix="write to another path, or pass replace=True to replace it")
    return None


def to_store(ds: xr.Dataset, path: str | os.PathLike, kind: str | CubeKind, *, compute: bool = True,
             replace: bool = False):
    """Write a whole cube (checked and stamped as a ``kind`` cube: a :class:`CubeKind`, or the name of an installed
    one) as a complete store at ``path``, replacing an older store that
    ``to_store`` wrote there; a workflow's output or a capture there is replaced only with ``replace=True``, and
    anything that is not a selpath store is refused, never deleted.

    The cube is written into a temporary sibling, its manifest added, and then moved into place, so a
    crash never leaves a half-written store under ``path``. With ``compute=False`` returns a dask delayed
    that writes and moves it when computed.
    """
    kind = resolve_kind(kind)
    problem = None if replace else _replace_problem(path)
    if problem is not None:
        raise StoreError(problem)
    staging = Staging(path)
    in_place = staging.path == staging.final
    if compute:
        try:
            write_store(ds, staging.path, kind, replace=in_place)
            write_manifest(staging.path, ds)
        except BaseException:
            staging.abort()
            raise
        staging.commit()
        return None
    write = write_store(ds, staging.path, kind, compute=False, replace=in_place)
    return dask.delayed(_finish)(write, staging, ds[[]])


def _finish(_written: Any, staging: Staging, metadata: xr.Dataset) -> None:
    write_manifest(staging.path, metadata)
    staging.commit()
