"""Corruption never passes unseen: checksummed chunks, a manifest of what was written, and verification.

* Every numeric array is written with a ``crc32c`` codec after zstd (zarr v3's checksum codec), and
  every chunk is written even where it holds only the fill value (``write_empty_chunks``). A chunk whose
  bytes were changed or truncated fails to decode; :func:`checked` turns that failure into a
  :class:`~selpath.pipeline.errors.StoreError` naming the store, the variable and the chunk index. A chunk that
  is missing from a format-2 store that says it is complete is corruption too (found by listing the
  store, :func:`absent_chunks`).
* The ``manifest`` in the store's ``_selpath`` group is written after all data, just before a store is
  moved into place (:mod:`selpath.pipeline.outputs`): it says the store is complete and records the units of
  every coordinate and variable, so a units attr edited afterwards is refused rather than carried into
  results 1000× wrong.
* The manifest also records every chunk's size in bytes when the store is complete (:func:`record_chunk_sizes`):
  one listing of the store tells a chunk truncated or replaced by one of another size since (:func:`resized_chunks`),
  without reading any; ``selpath inspect`` and a workflow about to reuse the store check it. A chunk changed in place
  to bytes of the same size is found only by reading it.
* :func:`verify_store` reads every chunk and lists the bad ones (``selpath inspect --verify``).
"""

from __future__ import annotations

import itertools
import json
import os
import warnings
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import xarray as xr
import zarr
from zarr.codecs import Crc32cCodec, ZstdCodec

from selpath.pipeline import remote
from selpath.pipeline.errors import Problem, StoreError

PROVENANCE_GROUP = "_selpath"
MANIFEST = "manifest"
WRITTEN_PREFIX = "written__"
#: format from which chunks carry checksums, fill-valued chunks are written and a manifest marks completion
CHECKSUMMED_FORMAT = 2


def open_group(path: str | os.PathLike, mode: str = "r") -> zarr.Group:
    """The store's root group as its nodes' own ``zarr.json`` files say, never the consolidated copy in the
    root's: selpath reads and writes stores through this, so a copy made stale (a units attr edited with zarr,
    a store written by plain xarray) never decides what selpath sees."""
    return zarr.open_group(os.fspath(path), mode=mode, use_consolidated=False)


def consolidate(path: str | os.PathLike) -> None:
    """Copy the metadata of every node into the root ``zarr.json`` (zarr-python's consolidated metadata), so
    plain ``xr.open_zarr(path)`` opens the store at once, without its warning about missing consolidated
    metadata. Called last on every path that writes metadata (:func:`write_manifest`,
    :func:`selpath.pipeline.provenance.write_provenance`); chunk writes (frames) change no metadata and leave it valid.
    zarr replaces ``zarr.json`` atomically, so a kill here leaves the old root metadata, never a torn one."""
    with warnings.catch_warnings():  # zarr warns that v3 has no consolidated metadata in its spec; selpath knows
        warnings.filterwarnings("ignore", message="Consolidated metadata is currently not part",
                                category=UserWarning)
        zarr.consolidate_metadata(os.fspath(path))


def is_selpath_store(path: str | os.PathLike) -> bool:
    """True if ``path`` is a folder (or object-storage prefix) whose root ``zarr.json`` is a group carrying
    ``selpath_format``."""
    try:
        where = os.fspath(path)
        text = remote.read_text(where, "zarr.json") if remote.is_url(where) else (Path(where) / "zarr.json").read_text()
        doc = json.loads(text) if text is not None else None
    except (OSError, ValueError):
        return False
    return isinstance(doc, dict) and "selpath_format" in (doc.get("attributes") or {})


def compressors() -> tuple:
    """zstd at level 1 (1.5–1.7× faster writes than zarr's default level 3 for 1 % more bytes), then crc32c."""
    return (ZstdCodec(level=1), Crc32cCodec())


# -- manifest ------------------------------------------------------------------------------------------


def units_of(ds: xr.Dataset) -> dict[str, str | None]:
    """The ``units`` attr of every coordinate and data variable (None where there is none)."""
    return {str(name): var.attrs.get("units") for name, var in ds.variables.items()
            if not str(name).startswith(WRITTEN_PREFIX)}


def write_manifest(path: str | os.PathLike, ds: xr.Dataset, *, complete: bool = True) -> None:
    """Record that ``path`` holds ``ds`` completely (or, for captures filled frame by frame, that its frame
    flags say what is complete), with the units of every coordinate and variable as the store holds them
    (its kind's metadata applied when it was written: read back, not taken from ``ds``) and, when complete, the
    size of every chunk (:func:`chunk_sizes`)."""
    group = open_group(path, mode="r+")
    stored = {name: array.attrs.get("units") for name, array in group.arrays()}
    units = {name: stored.get(name, units) for name, units in units_of(ds).items()}
    record = {"complete": complete, "units": units} | ({CHUNK_BYTES: chunk_sizes(path)} if complete else {})
    group.require_group(PROVENANCE_GROUP).attrs[MANIFEST] = record
    consolidate(path)


#: the manifest's record of every chunk's size: ``{array: [bytes of each chunk, in C order of its chunk grid]}``,
#: −1 where a chunk was absent
CHUNK_BYTES = "chunk_bytes"


def chunk_sizes(path: str | os.PathLike) -> dict[str, list[int]]:
    """Every array's chunk sizes in bytes in C order of its chunk grid (−1: absent): one listing of the store (local: a
    directory walk; object storage: one listing per array), no chunk read."""
    where = os.fspath(path)
    return {name: chunk_files(where, name, array).ravel().tolist()
            for name, array in _readable_arrays(open_group(where), where)[0]}


def record_chunk_sizes(path: str | os.PathLike) -> None:
    """Record the store's chunk sizes in its manifest now (a capture, once its last frame is written), keeping the
    rest of the manifest."""
    _set_chunk_record(path, chunk_sizes(path))


def drop_chunk_sizes(path: str | os.PathLike) -> None:
    """Drop the record of the chunk sizes (a capture about to have frames written again: its chunks change; the record
    is made anew when it is complete)."""
    if CHUNK_BYTES in (read_manifest(path) or {}):
        _set_chunk_record(path, None)


def _set_chunk_record(path: str | os.PathLike, sizes: dict[str, list[int]] | None) -> None:
    manifest = {k: v for k, v in (read_manifest(path) or {}).items() if k != CHUNK_BYTES}
    open_group(path, mode="r+").require_group(PROVENANCE_GROUP).attrs[MANIFEST] = manifest | (
        {CHUNK_BYTES: sizes} if sizes is not None else {})
    consolidate(path)


def resized_chunks(path: str | os.PathLike, manifest: Mapping[str, Any] | None = None,
                   listed: Mapping[str, np.ndarray] | None = None) -> list[BadChunk] | None:
    """The chunks whose size differs from the one the manifest recorded (truncated, lengthened or replaced since), or
    that are gone; None where the manifest records no sizes (a store of selpath before 0.2, an unfinished capture). One
    listing (``listed``: the arrays' :func:`chunk_files` a caller already has); contents are not read
    (:func:`verify_store` reads them)."""
    where = os.fspath(path)
    manifest = read_manifest(where) if manifest is None else manifest
    recorded = (manifest or {}).get(CHUNK_BYTES)
    group = open_group(where)
    if not isinstance(recorded, dict) or group.attrs.get("selpath_format", 0) < CHECKSUMMED_FORMAT:
        return None  # (format 1 did not write chunks holding only the fill value: their absence says nothing)
    arrays = dict(_readable_arrays(group, where)[0])
    bad = []
    for name, sizes in sorted(recorded.items()):
        if not isinstance(sizes, list) or not all(isinstance(s, int) for s in sizes):
            bad.append(BadChunk(PROVENANCE_GROUP, None, f"its record of {name}'s chunk sizes is malformed"))
            continue
        if name not in arrays:
            bad.append(BadChunk(name, None, "missing (the manifest records it; no array of that name reads)"))
            continue
        now = listed[name] if listed is not None and name in listed else chunk_files(where, name, arrays[name])
        was = np.asarray(sizes, dtype=np.int64)
        if now.size != was.size:
            bad.append(BadChunk(name, None, f"its chunk grid has {now.size} chunks, written with {was.size}"))
            continue
        for flat in np.flatnonzero(now.ravel() != was):
            got, size = int(now.ravel()[flat]), int(was[flat])
            reason = ("missing" if got < 0 else
                      f"{got:,} bytes, written as {size:,}: changed since it was written (truncated or replaced)")
            bad.append(BadChunk(name, tuple(int(i) for i in np.unravel_index(flat, now.shape)), reason))
    return bad


def read_manifest(path: str | os.PathLike) -> dict[str, Any] | None:
    try:
        group = open_group(path)
        return dict(group[PROVENANCE_GROUP].attrs[MANIFEST])
    except (FileNotFoundError, KeyError, zarr.errors.GroupNotFoundError, zarr.errors.NodeTypeValidationError):
        return None
    except Exception as exc:  # noqa: BLE001 - torn or garbled metadata: JSON, UTF-8 and zarr's own errors
        raise unreadable_record(path, "manifest", exc) from exc


def unreadable_record(path: str | os.PathLike, what: str, exc: Exception) -> StoreError:
    """The error for a store whose ``_selpath`` record (provenance or manifest) exists but cannot be read: selpath
    then cannot tell who wrote the store, from what, or whether it is complete, so it neither trusts nor
    replaces it."""
    return StoreError(Problem(f"its {what} record ({PROVENANCE_GROUP}/zarr.json) cannot be read "
                              f"({decode_error(exc)})", where=os.fspath(path),
                              fix="restore the store from a backup; if it can be made again, delete it yourself "
                              "and run again (selpath never deletes a store it cannot identify)"))


def units_problems(ds: xr.Dataset, manifest: Mapping[str, Any] | None) -> list[Problem]:
    """Coordinates and variables whose units differ from those recorded when the store was written."""
    if not manifest:
        return []
    recorded = manifest.get("units", {})
    problems = []
    for name, units in units_of(ds).items():
        if name in recorded and recorded[name] != units:
            problems.append(Problem(f"{name!r} has units {units!r} but was written in {recorded[name]!r}; a units "
                                    "attr changed after writing would make every result wrong by that factor",
                                    path=name, fix=f"set {name}.attrs['units'] back to {recorded[name]!r}, or "
                                    "convert the values and write a new store"))
    return problems


# -- chunks ------------------------------------------------------------------------------------------


def _arrays(group: zarr.Group) -> Iterable[tuple[str, zarr.Array]]:
    for name, node in sorted(group.members()):
        if isinstance(node, zarr.Array):
            yield name, node


def chunk_files(path: str | os.PathLike, name: str, array: zarr.Array, *, sizes: bool = True) -> np.ndarray:
    """The size in bytes of each chunk of ``array`` over its chunk grid, −1 where its file (or object) is absent
    (``sizes=False``: 0 for every present one, no file's size asked for).

    One listing of the array's folder (or prefix, on object storage), each file name decoded to its chunk index
    by the array's own chunk key encoding (a store of 1 425 frame bands is one directory walk)."""
    where = os.fspath(path)
    out = np.full(array.cdata_shape, -1, dtype=np.int64)
    index = {array.metadata.encode_chunk_key(c): c for c in itertools.product(*(range(n) for n in out.shape))}
    if remote.is_url(where):  # one listing of the array's prefix
        found = ((key[len(name) + 1:], int(info.get("size", 0))) for key, info in
                 remote.list_objects(where, name).items())
    else:
        folder = Path(remote.local_path(where)) / name
        found = ((Path(entry.path).relative_to(folder).as_posix(), entry.stat().st_size if sizes else 0)
                 for entry in _files(folder))
    for key, size in found:
        coords = index.get(key)
        if coords is not None:
            out[coords] = size
    return out


def _files(folder: Path) -> Iterable[os.DirEntry]:
    """Every file under ``folder`` (none where it is absent), as directory entries."""
    try:
        entries = list(os.scandir(folder))
    except FileNotFoundError:
        return
    for entry in entries:
        if entry.is_dir(follow_symlinks=False):
            yield from _files(Path(entry.path))
        else:
            yield entry


def present_chunks(path: str | os.PathLike, name: str, array: zarr.Array) -> np.ndarray:
    """Boolean array over ``array``'s chunk grid: True where the chunk's file (or object) exists."""
    return chunk_files(path, name, array, sizes=False) >= 0


def written_frames(path: str | os.PathLike, variable: str, flags: np.ndarray) -> np.ndarray:
    """Frames flagged written whose chunks are all on disk: a deleted chunk makes its frame missing again."""
    group = open_group(path)
    array = group[variable]
    present = present_chunks(path, variable, array)
    frame_axes = flags.ndim
    if frame_axes == 0:  # a single frame (the dark frame): written if all its chunks are there
        return flags & present.all()
    whole = present.reshape(present.shape[:frame_axes] + (-1,)).all(axis=-1)
    size = array.chunks[:frame_axes]
    index = np.indices(flags.shape).reshape(frame_axes, -1)
    chunk_of = tuple(index[a] // size[a] for a in range(frame_axes))
    return flags & whole[chunk_of].reshape(flags.shape)


def absent_chunks(path: str | os.PathLike, variables: Iterable[str]) -> list[Problem]:
    """Chunks missing from a store that says it is complete (format ≥ 2 writes every chunk)."""
    group = open_group(path)
    problems = []
    for name in variables:
        array = group[name]
        present = present_chunks(path, name, array)
        if present.all():
            continue
        missing = [tuple(int(i) for i in c) for c in np.argwhere(~present)]
        problems.append(Problem(f"{len(missing)} of {present.size} chunks are missing, first {missing[0]}; they "
                                "would read as the fill value", path=f"variable {name}",
                                fix="restore the store from a backup or write it again; `selpath inspect --verify` "
                                "lists every bad chunk"))
    return problems


@dataclass(frozen=True)
class BadChunk:
    """A chunk of ``variable`` that is missing or does not decode; ``chunk`` None: the node's metadata
    (``variable/zarr.json``, or ``_selpath/zarr.json`` for the store's records) is unreadable."""

    variable: str
    chunk: tuple[int, ...] | None
    reason: str

    def __str__(self) -> str:
        return f"{self.variable} {'metadata' if self.chunk is None else f'chunk {self.chunk}'}: {self.reason}"


def decode_error(exc: Exception) -> str:
    text = str(exc).split("\n")[0][:160]
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def verify_store(path: str | os.PathLike) -> list[BadChunk]:
    """Read and decode every chunk of every array of the store; return the missing and corrupt ones, and those whose
    size differs from the manifest's record (:func:`resized_chunks`: a chunk replaced by one that decodes).

    A chunk is missing when its file is absent where the store promises it: everywhere in a complete
    format-2 store, and in a capture for every frame its ``written__`` flag says was captured.
    """
    where = os.fspath(path)
    try:
        group = open_group(where)
    except Exception as exc:  # noqa: BLE001 - absent, not zarr, or metadata unreadable
        raise StoreError(Problem(f"cannot be read as a zarr store ({type(exc).__name__}: {exc})", where=where,
                                 fix="check the path; a store whose metadata is gone cannot be verified")) from exc
    form = group.attrs.get("selpath_format", 0)
    bad = []
    try:
        manifest = read_manifest(where) or {}
    except StoreError as exc:
        manifest = {}
        bad.append(BadChunk(PROVENANCE_GROUP, None, f"unreadable ({decode_error(exc.__cause__ or exc)})"))
    arrays, garbled = _readable_arrays(group, where)
    bad.extend(BadChunk(name, None, f"unreadable ({decode_error(exc)})") for name, exc in garbled)
    # a variable the manifest records whose array is gone (its zarr.json deleted, or replaced by a group's)
    known = {name for name, _ in arrays} | {name for name, _ in garbled}
    bad.extend(BadChunk(name, None, "missing (the manifest records it; no array of that name reads)")
               for name in sorted(set(manifest.get("units", {})) - known))
    flags = {}
    for name, array in arrays:
        if name.startswith(WRITTEN_PREFIX):
            try:
                flags[name[len(WRITTEN_PREFIX):]] = np.asarray(array[...])
            except Exception:  # noqa: BLE001 - its bad chunks are listed below; its frames' chunks are then
                pass  # checked where present and not expected where absent
    data_vars = {name for name, array in arrays if _is_data(array, flags, name)}
    flagged = {name[len(WRITTEN_PREFIX):] for name, _ in arrays if name.startswith(WRITTEN_PREFIX)}
    listing: dict[str, np.ndarray] = {}
    for name, array in arrays:
        listing[name] = chunk_files(where, name, array)  # one listing: presence here, sizes below
        present = listing[name] >= 0
        for coords in itertools.product(*(range(n) for n in array.cdata_shape)):
            if not present[coords]:
                if form < CHECKSUMMED_FORMAT:  # format 1 skipped chunks holding only the fill value
                    expected = False
                elif name in flagged:  # a capture's frames: expected where flagged written
                    if name not in flags:  # the flags are unreadable (reported): which frames exist is unknown
                        continue
                    frame = tuple(c * s for c, s in zip(coords[: flags[name].ndim], array.chunks, strict=False))
                    expected = bool(flags[name][frame])
                else:  # coordinates and flags always; data once the store is complete
                    expected = name not in data_vars or bool(manifest.get("complete", False))
                if expected:
                    bad.append(BadChunk(name, coords, "missing"))
                continue
            try:
                array.get_block_selection(coords)
            except Exception as exc:  # noqa: BLE001 - zarr and its codecs raise many types for bad bytes
                bad.append(BadChunk(name, coords, f"corrupt ({decode_error(exc)})"))
    # a chunk replaced by another that decodes (another store's) changed its size: the record names it
    named = {(chunk.variable, chunk.chunk) for chunk in bad}
    bad.extend(chunk for chunk in resized_chunks(where, manifest, listing) or () if (chunk.variable, chunk.chunk)
               not in named)
    return bad


def _readable_arrays(group: zarr.Group, where: str) -> tuple[list[tuple[str, zarr.Array]],
                                                              list[tuple[str, Exception]]]:
    """The store's arrays, and the members whose metadata does not read (name, error). zarr lists members by
    reading every ``zarr.json`` and fails on the first garbled one, so on failure each is opened on its own."""
    try:
        return list(_arrays(group)), []
    except Exception:  # noqa: BLE001 - JSON, UTF-8 or zarr validation errors of some member
        pass
    names = remote.members(where) if remote.is_url(where) else sorted(
        entry.name for entry in os.scandir(remote.local_path(where)) if entry.is_dir())
    arrays, garbled = [], []
    for name in sorted(names):
        if name == PROVENANCE_GROUP:
            continue  # the records: read by read_manifest
        try:
            node = group[name]
        except KeyError:
            continue  # a folder that is no zarr node
        except Exception as exc:  # noqa: BLE001
            garbled.append((name, exc))
            continue
        if isinstance(node, zarr.Array):
            arrays.append((name, node))
    return arrays, garbled


def _is_data(array: zarr.Array, flags: Mapping[str, np.ndarray], name: str) -> bool:
    """A data variable filled after the store is made (a capture's frames), not a coordinate or a flag."""
    return name in flags or (not name.startswith(WRITTEN_PREFIX) and tuple(array.metadata.dimension_names or ())
                             != (name,))
