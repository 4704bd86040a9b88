"""What plane-to-ray and full transport are for (§5.4.1, §5.4.2): relighting under any row pattern, epipolar and
non-epipolar images (Eq. 35–36) from ``T(offset, row, col)``, and relighting under any 2-D pattern from full
``T(du, dv, row, col)``. Lazy (xarray/dask); :mod:`selpath.stages.procam.figures` draws them.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.devices.patterns import checkerboard


def relight(transport: xr.DataArray, row_pattern: np.ndarray) -> xr.DataArray:
    """The image under a virtual pattern of projector rows b(v) (rectified onto camera rows, 1 = lit for a
    whole line time): I(s, t) = Σ_o T(o, s, t) · b(s + o); rows outside the pattern are dark."""
    rows = transport.sizes["row"]
    row_pattern = np.asarray(row_pattern, dtype=float)
    if row_pattern.shape != (rows,):
        raise ValueError(f"row pattern has shape {row_pattern.shape}; expected ({rows},) camera-rectified rows")
    v = np.arange(rows)[None, :] + transport["offset"].values[:, None]
    lit = np.where((v >= 0) & (v < rows), row_pattern[np.clip(v, 0, rows - 1)], 0.0)
    weights = xr.DataArray(lit.astype(transport.dtype), dims=("offset", "row"))
    return (transport * weights).sum("offset")


def epipolar_image(transport: xr.DataArray, half_width: int = 0) -> xr.DataArray:
    """Light from the pixel's own epipolar plane (Eq. 35), or from the 2·half_width + 1 planes around it:
    the *sharpened* epipolar image of §5.4.5, as narrow as the transport's resolution allows."""
    return transport.where(abs(transport["offset"]) <= half_width, 0).sum("offset")


def non_epipolar_image(transport: xr.DataArray) -> xr.DataArray:
    """Light from every other plane (Eq. 36)."""
    return transport.where(transport["offset"] != 0, 0).sum("offset")


def cell_average(pattern: np.ndarray, centres: np.ndarray, width: float) -> np.ndarray:
    """The mean of each row of ``pattern`` (pixel u covers columns [u − ½, u + ½)) over the part of each cell
    [c − width/2, c + width/2] that lies on the projector (a cell's light can only come from real columns);
    0 for cells wholly off it. (rows, len(centres))."""
    pattern = np.asarray(pattern, dtype=float)
    edges = np.arange(pattern.shape[1] + 1) - 0.5
    integral = np.concatenate([np.zeros((pattern.shape[0], 1)), np.cumsum(pattern, axis=1)], axis=1)

    def at(x):  # ∫ from the first edge to x, piecewise linear between edges (constant pixels)
        return np.stack([np.interp(x, edges, row) for row in integral])

    low = np.clip(centres - width / 2, edges[0], edges[-1])
    high = np.clip(centres + width / 2, edges[0], edges[-1])
    real = high - low
    return np.where(real > 0, (at(high) - at(low)) / np.where(real > 0, real, 1.0), 0.0)


def relight_full(transport: xr.Dataset, pattern: np.ndarray) -> xr.DataArray:
    """The image under any 2-D projector pattern P(v, u) from full transport (§5.4.2): rows rectified onto
    camera rows (as :func:`relight`), columns in projector pixels, 1 = lit for a whole line time:

        I(s, t) = Σ_{du, dv} T(du, dv, s, t) · P̄(t + dv, u₀(s, t) + du),

    P̄ the pattern's mean over each u-cell. Cells the sweep never lit (NaN) and pixels without a direct
    correspondence contribute nothing. Lazy: one task per chunk of rows."""
    rows = transport.sizes["row"]
    pattern = np.asarray(pattern, dtype=float)
    if pattern.ndim != 2 or pattern.shape[0] != rows:
        raise ValueError(f"pattern has shape {pattern.shape}; expected ({rows}, projector columns), rows rectified")
    step, first = float(transport.attrs["cell_width_px"]), float(transport.attrs["cells_px"][0])
    du = np.round(transport["du"].values / step).astype(int)
    # every cell a pixel can point at: u₀ is a sweep cell, u₀ + du reaches |du| beyond either end
    n_cells = len(transport.attrs["cells_px"])
    ks = np.arange(du.min(), n_cells + du.max())
    table = cell_average(pattern, first + step * ks, step)  # (rows, cells)
    dv = transport["dv"].values.astype(int)

    def band(block: xr.Dataset, table: np.ndarray) -> xr.DataArray:
        t, r = block["transport"].values, block["row"].values  # (du, dv, r, c), the block's camera rows
        k0 = np.round((block["u_direct"].values - first) / step)  # (r, c), NaN where unknown
        known = np.isfinite(k0)
        k = np.where(known, k0, 0).astype(int)[None] + du[:, None, None] - ks[0]  # (du, r, c)
        v = r[None, :] + dv[:, None]  # (dv, r)
        inside = (v >= 0) & (v < rows)
        lit = table[np.clip(v, 0, rows - 1)[None, :, :, None], k[:, None, :, :]]  # (du, dv, r, c)
        lit = np.where(inside[None, :, :, None] & known[None, None], lit, 0.0)
        image = np.nansum(t * lit, axis=(0, 1))
        return xr.DataArray(image.astype(t.dtype), dims=("row", "col"), coords=block["u_direct"].coords)

    ds = transport[["transport", "u_direct"]].assign_coords(row=np.arange(rows))
    # one task per band of T's rows, u_direct cut alike (a store may chunk the two differently)
    bands = ds["transport"].chunksizes.get("row", -1) if ds["transport"].chunks else -1
    ds = ds.chunk({"du": -1, "dv": -1, "row": bands, "col": -1})
    template = ds["u_direct"].astype(ds["transport"].dtype)
    # the table goes in as an argument, so dask's task names depend on the pattern (a closure's would not)
    return xr.map_blocks(band, ds, kwargs={"table": table}, template=template)


def checkerboard_relight(transport: xr.Dataset, square_px: int, projector_cols: int,
                         square_rows: int | None = None) -> xr.Dataset:
    """The scene relit from full transport under a checkerboard of ``square_px`` projector columns ×
    ``square_rows`` camera-rectified rows (None: square_px) over ``projector_cols`` columns, its complement and
    white (the two boards sum to it); lazy."""
    square_rows = square_px if square_rows is None else square_rows
    board = checkerboard((transport.sizes["row"], projector_cols), (square_rows, square_px))
    return xr.Dataset({name: relight_full(transport, pattern) for name, pattern in
                       (("checkerboard", board), ("complement", 1.0 - board), ("white", np.ones_like(board)))},
                      attrs={"square_px": square_px, "square_rows": square_rows, "projector_cols": projector_cols})
