"""Frames made elsewhere, read lazily as dask arrays for ``import_capture`` (:mod:`selpath.stages.importing`): a
folder or glob of TIFF or PNG files (natural name order), a multi-page TIFF, ``.npy`` (memory-mapped), an ``.npz``
member (``file.npz:member``; read whole unless stored uncompressed), an HDF5 dataset (``file.h5:/path``); one dask
task per frame, so a capture larger than memory imports frame by frame.
"""

from __future__ import annotations

import glob
import os
import re
import struct
import zipfile
from pathlib import Path

import dask
import dask.array as da
import numpy as np

from selpath.pipeline.errors import Problem, StageError

#: file suffixes read as one image per file (a folder or glob of them is a stack, in natural name order)
IMAGE_SUFFIXES = (".tif", ".tiff", ".png")
_ARRAY_SUFFIXES = (".npy", ".npz", ".h5", ".hdf5")


def _natural(name: str) -> list:
    """Sort key: frame_2 before frame_10."""
    return [int(part) if part.isdigit() else part for part in re.split(r"(\d+)", name)]


def frame_file_list(path: Path) -> list[Path]:
    if path.is_dir():
        found = [p for p in path.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES]
    else:
        found = [Path(p) for p in glob.glob(os.fspath(path)) if Path(p).suffix.lower() in IMAGE_SUFFIXES]
    return sorted(found, key=lambda p: _natural(p.name))


def _read_image(file: Path, page: int | None = None) -> np.ndarray:
    """One image file (or one page of a multi-page TIFF); a file that does not decode is named."""
    try:
        if file.suffix.lower() in (".tif", ".tiff"):
            import tifffile

            return tifffile.imread(file, key=page) if page is not None else tifffile.imread(file)
        import imageio.v3 as iio

        return np.asarray(iio.imread(file, plugin="pillow"))  # Pillow only: no guessing through other plugins
    except (OSError, ValueError, KeyError, IndexError) as exc:
        raise StageError(Problem(f"{file.name} cannot be read as an image ({type(exc).__name__}: {exc})",
                                 where=os.fspath(file))) from None


def _frame(file: Path, page: int | None, shape: tuple, dtype: np.dtype) -> np.ndarray:
    """A frame of a stack, checked against the first frame's shape and dtype (a folder mixing 8- and 16-bit
    files, or sizes, would otherwise be cast or broadcast silently)."""
    image = _read_image(file, page)
    if image.shape != shape or image.dtype != dtype:
        raise StageError(Problem(f"{file.name}{'' if page is None else f' page {page}'} is {image.dtype} "
                                 f"{image.shape}; the stack's first frame is {dtype} {shape}",
                                 where=os.fspath(file), fix="frames of one stack share their size and bit depth"))
    return image


def _tiff_pages(file: Path) -> int:
    import tifffile

    try:
        with tifffile.TiffFile(file) as tiff:
            return len(tiff.pages)
    except (OSError, ValueError) as exc:
        raise StageError(Problem(f"{file.name} cannot be read as a TIFF ({type(exc).__name__}: {exc})",
                                 where=os.fspath(file))) from None


class _HDF5Frames:
    """An HDF5 dataset as an array dask can read block by block (the file opened per read: picklable)."""

    def __init__(self, file: Path, key: str):
        import h5py

        self.file, self.key = os.fspath(file), key
        with h5py.File(self.file, "r") as handle:
            if key not in handle or not isinstance(handle[key], h5py.Dataset):
                raise KeyError(key)
            self.shape, self.dtype = handle[key].shape, handle[key].dtype
        self.ndim = len(self.shape)

    def __getitem__(self, index):
        import h5py

        with h5py.File(self.file, "r") as handle:
            return handle[self.key][index]


def split_source(source: str, base: str | os.PathLike) -> tuple[Path, str | None]:
    """(the file or folder, the ``.npz`` member or HDF5 dataset or None) a frames source names; relative paths
    resolve against ``base``."""
    text, key = source, None
    match = re.match(r"^(?P<path>.+?\.(?:npz|h5|hdf5)):(?P<key>.+)$", source, re.IGNORECASE)
    if match:
        text, key = match["path"], match["key"]
    return (Path(text) if Path(text).is_absolute() else Path(base) / text), key


def read_frames(source: str, base: str | os.PathLike = ".", *, field: str = "") -> da.Array:
    """The frames ``source`` names, lazily: ``path`` (a folder or glob of TIFF/PNG files, one frame each, in
    natural name order; a multi-page TIFF; ``.npy``), ``path.npz:member`` or ``path.h5:/dataset``. Relative paths
    resolve against ``base``. One chunk per frame (the leading axis); ``field`` names the spec field in errors."""
    where = f"import spec field {field}" if field else source
    path, key = split_source(source, base)
    suffix = path.suffix.lower()
    try:
        if suffix == ".npy":
            array = np.load(path, mmap_mode="r")
        elif suffix == ".npz":
            with np.load(path) as members:
                names = list(members)
                if key is None and len(names) == 1:
                    key = names[0]
                if key not in names:
                    named = source.rsplit(":", 1)[0] if key else source
                    raise StageError(Problem(f"{path.name} has members {names}; name one as {named}:<member>",
                                             where=where))
                stored = _npz_stored_member(path, key)  # np.savez: memory-mapped in place, read frame by frame
                array = stored if stored is not None else members[key]  # np.savez_compressed: read whole
        elif suffix in (".h5", ".hdf5"):
            if key is None:
                raise StageError(Problem(f"an HDF5 file needs its dataset: {source}:/path/to/dataset", where=where))
            try:
                array = _HDF5Frames(path, key)
            except KeyError:
                raise StageError(Problem(f"{path.name} has no dataset {key!r}", where=where)) from None
        else:
            files = [path] if path.is_file() else frame_file_list(path)
            if not files:
                raise StageError(Problem(f"no frames at {path} (a folder or glob of {', '.join(IMAGE_SUFFIXES)} "
                                         f"files, or one of {', '.join(_ARRAY_SUFFIXES)})", where=where,
                                         fix="check the path in the import spec; relative paths start at the "
                                             "spec's folder"))
            pages = (_tiff_pages(files[0]) if len(files) == 1 and files[0].suffix.lower() in (".tif", ".tiff")
                     else 0)
            if len(files) == 1 and pages <= 1:
                array = _read_image(files[0])  # one frame
            else:  # a stack: one file per frame, or the pages of one TIFF, each read in its own task
                parts = [(files[0], p) for p in range(pages)] if pages > 1 else [(f, None) for f in files]
                first = _read_image(*parts[0])
                frames = [da.from_delayed(dask.delayed(_frame)(f, p, first.shape, first.dtype), first.shape,
                                          first.dtype) for f, p in parts]
                return da.stack(frames)
    except FileNotFoundError as exc:
        raise StageError(Problem(f"no such file: {exc.filename or path}", where=where,
                                 fix="check the path in the import spec")) from None
    except (OSError, ValueError) as exc:
        raise StageError(Problem(f"{path} cannot be read ({type(exc).__name__}: {exc})", where=where)) from None
    chunks = (1, *array.shape[1:]) if len(array.shape) > 2 else array.shape
    return da.from_array(array, chunks=chunks, asarray=True)


def _npz_stored_member(path: Path, key: str) -> np.ndarray | None:
    """The member ``key`` of an ``.npz`` memory-mapped in place when it is stored uncompressed (``np.savez``), so
    frames are read one by one like a ``.npy``'s; None when it is compressed (``np.savez_compressed``: the zip must
    inflate it whole) or not a plain C/Fortran array. numpy cannot memory-map an ``.npz`` itself; the zip's local
    header says where the member's ``.npy`` bytes start, and numpy's own header reader says where its data does."""
    with zipfile.ZipFile(path) as archive:
        info = archive.getinfo(f"{key}.npy")
        if info.compress_type != zipfile.ZIP_STORED:
            return None
    with open(path, "rb") as file:
        file.seek(info.header_offset)
        local = file.read(30)
        if local[:4] != b"PK\x03\x04":
            return None
        name_length, extra_length = struct.unpack("<HH", local[26:30])
        start = info.header_offset + 30 + name_length + extra_length
        file.seek(start)
        version = np.lib.format.read_magic(file)
        read_header = {(1, 0): np.lib.format.read_array_header_1_0,
                       (2, 0): np.lib.format.read_array_header_2_0}.get(version)
        if read_header is None:  # a newer header (utf-8 field names): read whole
            return None
        shape, fortran, dtype = read_header(file)
        if dtype.hasobject:
            return None
        offset = file.tell()
    return np.memmap(path, dtype=dtype, mode="r", offset=offset, shape=shape, order="F" if fortran else "C")


def check_values(frames: da.Array, where: str) -> None:
    if frames.dtype.kind not in "uif":
        raise StageError(Problem(f"frames of dtype {frames.dtype}; expected numbers (raw counts)", where=where))
