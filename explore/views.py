"""What the explorer shows of each store, as numbers: the data behind every view, apart from how it is drawn
(:mod:`selpath.explore.explorer` draws them with Panel and Bokeh), so a benchmark times and a test checks them
without a browser.

A full-size plane-to-ray transport (1600 × 1200 × 253 float32, 1.9 GB) cannot be read for every move of a slider,
and its zarr chunks hold every offset of a band of rows, so no view can read less than all of it. A
:class:`TransportView` reads it once, at start, into a preview whose columns are binned by an integer factor (the
mean of ``bin`` neighbouring columns, chosen so the preview fits :data:`PREVIEW_BYTES`). Every plane-to-ray view
(the ideal rig's frame, a relit image, the epipolar images) works on each column alone, so the binned view is
exactly the bin's mean of the full-resolution one; a clicked pixel's profile is read at full resolution.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import xarray as xr

from selpath.pipeline.integrity import is_selpath_store
from selpath.pipeline.provenance import archive_stores
from selpath.pipeline.store import open_store
from selpath.stages.procam._illumination import plane_to_ray_illumination
from selpath.stages.procam.relight import on_camera_rows, relight_weights
from selpath.stages.procam.virtual import Pattern

#: the largest in-memory preview of a transport, bytes (its columns are binned until it fits)
PREVIEW_BYTES = 512 * 2**20


def find_stores(paths: list[Path]) -> dict[str, Path]:
    """name → path of every selpath store given, or found under a given folder (names relative to it)."""
    found: dict[str, Path] = {}

    def add(name: str, path: Path) -> None:
        if path in found.values():
            return
        unique, k = name, 2
        while unique in found:  # the same name under two folders given
            unique, k = f"{name} ({k})", k + 1
        found[unique] = path

    for path in paths:
        path = Path(path).resolve()
        if is_selpath_store(path):
            add(path.name, path)
        elif path.is_dir():
            for entry in archive_stores(path):
                add(entry["store"], path / entry["store"])
        else:
            raise FileNotFoundError(f"{path} is neither a selpath store nor a folder")
    if not found:
        raise FileNotFoundError(f"no selpath store in {', '.join(map(str, paths))}")
    return found


def column_bin(cols: int, rows: int, offsets: int, itemsize: int = 4, budget: int | None = None) -> int:
    """The smallest number of neighbouring columns whose mean keeps a (offsets, rows, cols / bin) preview within
    ``budget`` bytes.

    >>> column_bin(1600, 1200, 253)   # 1.9 GB → four columns a bin, 486 MB
    4
    >>> column_bin(400, 300, 253)
    1
    """
    return max(1, math.ceil(offsets * rows * cols * itemsize / (budget or PREVIEW_BYTES)))


@dataclass
class TransportView:
    """A plane-to-ray transport store and its column-binned preview in memory (module docstring): a (row, offset,
    col) array, so each view is one batched product per row (BLAS) with the weights the accessor's functions give
    (:func:`~selpath.stages.procam.relight.relight_weights`, the illumination model), never a copy of the cube."""

    store: xr.Dataset
    capture: xr.Dataset | None = None
    bin: int = 1
    cube: np.ndarray = field(init=False, repr=False)
    floodlit: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        t = self.store["transport"]
        self.bin = column_bin(t.sizes["col"], t.sizes["row"], t.sizes["offset"], t.dtype.itemsize)
        # NaN cells (a rectified transport's edges) add nothing, as in every full-resolution view; the padded
        # columns of a last, narrower bin are left out of its mean
        t = t.fillna(0)
        binned = t.coarsen(col=self.bin, boundary="pad").mean() if self.bin > 1 else t
        # band by band into one (row, offset, col) array: never the store's whole cube and its transpose at once
        rows, offsets, cols = t.sizes["row"], t.sizes["offset"], binned.sizes["col"]
        self.cube = np.empty((rows, offsets, cols), dtype=t.dtype)
        step = max(1, (t.chunksizes.get("row") or (rows,))[0]) if t.chunks else rows
        for r0 in range(0, rows, step):
            band = binned.isel(row=slice(r0, r0 + step)).transpose("row", "offset", "col").values
            self.cube[r0:r0 + band.shape[0]] = band
        self.floodlit = self.cube.sum(axis=1)
        self.offsets = t["offset"].values

    @property
    def shape(self) -> tuple[int, int]:
        """(rows, cols) of the full-resolution frame."""
        return self.store.sizes["row"], self.store.sizes["col"]

    def delays(self) -> tuple[float, float]:
        """The delay range a slider offers [µs]: the capture's, else the transport's offsets' sync delays."""
        d = self.capture["delay"].values if self.capture is not None else self.store.selpath.sync_delay().values
        return float(d.min()), float(d.max())

    def exposures(self) -> list[float]:
        if self.capture is not None:
            return [float(e) for e in self.capture["exposure"].values]
        return [float(self.store.attrs.get("line_time_us", 17.0)) * 10]

    def projector_rows(self) -> int:
        shape = self.store.attrs.get("projector_shape")
        return int(shape[0]) if shape is not None else self.store.sizes["row"]

    def _weighted(self, weights: np.ndarray) -> np.ndarray:
        """Σ_o cube[s, o, :]·weights[o] (1-D) or ·weights[o, s] (2-D): (rows, cols)."""
        w = weights.T[:, None, :] if weights.ndim == 2 else weights[None, None, :]
        return np.matmul(w.astype(self.cube.dtype), self.cube)[:, 0, :]

    def image(self, mode: str, *, delay: float = 0.0, exposure: float = 170.0, line: int = 0, width: int = 1,
              band: int = 0) -> np.ndarray:
        """The preview image of ``mode``: ``ideal frame`` (at delay, exposure [µs]), ``relit`` (under projector rows
        line … line + width − 1), ``epipolar`` or ``non-epipolar`` (|offset| ≤ band or beyond)."""
        attrs = self.store.attrs
        if mode == "ideal frame":
            weights = plane_to_ray_illumination([delay], [exposure], self.offsets,
                                                scan_speed=float(attrs["scan_speed_px_per_us"]),
                                                line_time=float(attrs["line_time_us"]),
                                                sync_offset=float(attrs.get("sync_offset_us", 0.0)))[0]
            out = self._weighted(weights)
        elif mode == "relit":
            rows = self.projector_rows()
            pattern = Pattern(rows=tuple(range(max(line, 0), min(line + width, rows)))).array(rows)
            out = self._weighted(relight_weights(self.offsets, on_camera_rows(pattern, self.cube.shape[0], rows)))
        elif mode in ("epipolar", "non-epipolar"):
            epipolar = self.cube[:, np.abs(self.offsets) <= band, :].sum(axis=1)
            out = epipolar if mode == "epipolar" else self.floodlit - epipolar
        else:
            raise ValueError(f"unknown view {mode!r}")
        return np.asarray(out, dtype=np.float32)

    def profile(self, row: int, col: int) -> xr.DataArray:
        """The pixel's T over offset (with its sync delay), at full resolution."""
        return self.store.selpath.profile(row=row, col=col).load()

    def intensity(self, row: int, col: int) -> xr.DataArray | None:
        """The pixel's captured I(t_d) per exposure, where a capture of the same frame was given."""
        return None if self.capture is None else self.capture.selpath.intensity(row=row, col=col).load()


def pair_captures(stores: dict[str, xr.Dataset]) -> dict[str, str]:
    """transport name → the name of a plane-to-ray capture of the same frame size among the stores (the first)."""
    captures = {n: ds for n, ds in stores.items() if ds.attrs.get("selpath_kind") == "plane_to_ray_capture"}
    pairs = {}
    for name, ds in stores.items():
        if ds.attrs.get("selpath_kind") != "plane_to_ray_transport":
            continue
        same = [n for n, c in captures.items() if (c.sizes["row"], c.sizes["col"]) == (ds.sizes["row"],
                                                                                      ds.sizes["col"])]
        if same:
            pairs[name] = same[0]
    return pairs


def truth_of(stores: dict[str, xr.Dataset], name: str) -> str | None:
    """The name of a true σ (a ``reconstruction`` store with ``method: truth``) on the reconstruction's grid."""
    recon = stores[name]
    for other, ds in stores.items():
        if other != name and ds.attrs.get("method") == "truth" and "sigma" in ds.data_vars \
                and ds.sizes.get("x") == recon.sizes.get("x") and ds.sizes.get("y") == recon.sizes.get("y"):
            return other
    return None


def open_stores(paths: dict[str, Path]) -> dict[str, xr.Dataset]:
    """Every store opened lazily, checked against its kind (never written)."""
    return {name: open_store(path) for name, path in paths.items()}
