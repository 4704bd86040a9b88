"""What plane-to-ray and full transport are for (§5.4.1, §5.4.2): relighting under any row pattern, epipolar and
non-epipolar images (Eq. 35–36) and the frame an ideal rig records at any (delay, exposure) from
``T(offset, row, col)``, and relighting under any 2-D pattern from full ``T(du, dv, row, col)``. Lazy
(xarray/dask); each result is labelled (``units`` the transport's, a ``long_name`` of its own and a ``description``
of how it was made). :mod:`selpath.stages.procam.figures` draws them; the ``relight`` and ``epipolar_images``
stages (:mod:`selpath.stages.procam.virtual`) store them from a workflow.

Patterns are on camera-rectified rows, as the transport is: the sync pairs projector row p with camera row
(p + ½)·C/P − ½ (P, C the row counts; :func:`selpath.stages.procam.rectify.paired_camera_row`), so a pattern drawn
on the projector's P rows is first averaged onto the C camera rows (:func:`on_camera_rows`): each camera row gets
the mean of the projector rows it covers, as a camera row integrates them.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.devices.patterns import checkerboard
from selpath.stages.procam._illumination import plane_to_ray_illumination


def labelled(image: xr.DataArray, transport: xr.DataArray, long_name: str, description: str) -> xr.DataArray:
    """``image`` with the transport's units (counts where it names none), its own long name and how it was made."""
    return image.assign_attrs({"units": transport.attrs.get("units", "counts"), "long_name": long_name,
                               "description": description})


def on_camera_rows(pattern, camera_rows: int, projector_rows: int | None = None) -> np.ndarray:
    """A row pattern b(v) (1-D) or a 2-D pattern P(v, u) (rows first) on camera-rectified rows: as is when it has
    ``camera_rows`` rows and ``projector_rows`` is None or equal to it; else, having ``projector_rows`` rows, each
    camera row s gets the mean of the projector rows its cell [(s)·P/C − ½, (s + 1)·P/C − ½] covers (partial rows
    weighted by their share).

    >>> on_camera_rows([1, 1, 0, 0, 0, 1], camera_rows=3, projector_rows=6).tolist()
    [1.0, 0.0, 0.5]
    >>> on_camera_rows([1, 0], camera_rows=4, projector_rows=2).tolist()
    [1.0, 1.0, 0.0, 0.0]
    """
    pattern = np.asarray(pattern, dtype=float)
    if pattern.ndim not in (1, 2):
        raise ValueError(f"a pattern is 1-D (rows) or 2-D (rows, columns); this one has shape {pattern.shape}")
    rows = pattern.shape[0]
    if projector_rows is None or projector_rows == camera_rows:
        if rows != camera_rows:
            raise ValueError(f"the pattern has {rows} rows; expected {camera_rows} camera-rectified rows"
                             + ("" if projector_rows is None else " (the projector has as many)")
                             + " or, with projector_rows, the projector's rows")
        return pattern
    if rows != projector_rows:
        raise ValueError(f"the pattern has {rows} rows; the projector has {projector_rows}")
    scale = projector_rows / camera_rows
    centres = (np.arange(camera_rows) + 0.5) * scale - 0.5
    table = cell_average(pattern.reshape(rows, -1).T, centres, scale).T  # (camera rows, columns)
    return table.reshape((camera_rows, *pattern.shape[1:]))


def relight_weights(offsets: np.ndarray, row_pattern: np.ndarray) -> np.ndarray:
    """The weight b(s + o) of each (offset, camera row) under a row pattern b on camera-rectified rows (0 where
    s + o leaves the pattern): I(s, t) = Σ_o T(o, s, t)·weight[o, s].

    >>> relight_weights(np.array([-1, 0, 1]), np.array([0.0, 1.0, 0.5])).tolist()
    [[0.0, 0.0, 1.0], [0.0, 1.0, 0.5], [1.0, 0.5, 0.0]]
    """
    rows = row_pattern.shape[0]
    v = np.arange(rows)[None, :] + np.asarray(offsets)[:, None]
    return np.where((v >= 0) & (v < rows), row_pattern[np.clip(v, 0, rows - 1)], 0.0)


def relight(transport: xr.DataArray, row_pattern: np.ndarray) -> xr.DataArray:
    """The image under a virtual pattern of projector rows b(v) (rectified onto camera rows, 1 = lit for a
    whole line time; :func:`on_camera_rows` takes it there from the projector's rows): I(s, t) = Σ_o T(o, s, t) ·
    b(s + o); rows outside the pattern are dark."""
    rows = transport.sizes["row"]
    row_pattern = np.asarray(row_pattern, dtype=float)
    if row_pattern.shape != (rows,):
        raise ValueError(f"row pattern has shape {row_pattern.shape}; expected ({rows},) camera-rectified rows "
                         "(on_camera_rows maps a pattern of the projector's rows onto them)")
    weights = xr.DataArray(relight_weights(transport["offset"].values, row_pattern).astype(transport.dtype),
                           dims=("offset", "row"))
    lit_rows = int(np.count_nonzero(row_pattern))
    return labelled((transport * weights).sum("offset"), transport, "image relit under a virtual row pattern",
                    f"Σ_o T(o, s, t)·b(s + o) over {transport.sizes['offset']} offsets, {lit_rows} of {rows} "
                    "camera-rectified rows lit (1 = a row lit for its whole line time)")


def epipolar_image(transport: xr.DataArray, half_width: int = 0) -> xr.DataArray:
    """Light from the pixel's own epipolar plane (Eq. 35), or from the 2·half_width + 1 planes around it:
    the *sharpened* epipolar image of §5.4.5, as narrow as the transport's resolution allows."""
    image = transport.isel(offset=np.flatnonzero(np.abs(transport["offset"].values) <= half_width)).sum("offset")
    return labelled(image, transport, "epipolar image" if half_width == 0 else f"epipolar image, |offset| ≤ "
                    f"{half_width}", f"Σ_o T(o, s, t) over |o| ≤ {half_width} rows (Eq. 35)")


def non_epipolar_image(transport: xr.DataArray, half_width: int = 0) -> xr.DataArray:
    """Light from every other plane (Eq. 36): every offset beyond ``half_width`` rows of the pixel's own."""
    image = transport.isel(offset=np.flatnonzero(np.abs(transport["offset"].values) > half_width)).sum("offset")
    return labelled(image, transport, "non-epipolar image" if half_width == 0 else f"non-epipolar image, |offset| > "
                    f"{half_width}", f"Σ_o T(o, s, t) over |o| > {half_width} rows (Eq. 36)")


def ideal_frame(transport: xr.DataArray, delay: float, exposure: float, *, scan_speed: float, line_time: float,
                sync_offset: float = 0.0) -> xr.DataArray:
    """The frame an ideal rig (no noise, no clipping, no jitter) records at sync delay ``delay`` and exposure
    ``exposure`` [µs] under a white pattern: Σ_o T(o, s, t)·w(o; t_d, t_e), w the illumination model the
    demultiplexer inverts (:func:`~selpath.stages.procam._illumination.plane_to_ray_illumination`: Eq. 33's box,
    ``scan_speed`` v_p [rows per µs], ``line_time`` t_p [µs], ``sync_offset`` t_o [µs]). Offsets the transport
    does not hold add nothing; NaN cells (a rectified transport's edges) count as 0."""
    offsets = transport["offset"].values
    weight = plane_to_ray_illumination([delay], [exposure], offsets, scan_speed=scan_speed, line_time=line_time,
                                       sync_offset=sync_offset)[0]
    lit = np.flatnonzero(weight)  # the offsets the exposure sees: a few of them, read alone
    weights = xr.DataArray(weight[lit].astype(transport.dtype), dims="offset")
    return labelled((transport.isel(offset=lit) * weights).sum("offset"), transport,
                    f"ideal frame at t_d = {delay:g} µs, t_e = {exposure:g} µs",
                    f"Σ_o T(o)·w(o; t_d, t_e), v_p = {scan_speed:g} rows/µs, t_p = {line_time:g} µs, t_o = "
                    f"{sync_offset:g} µs (Eq. 33; no noise or clipping)")


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
    image = xr.map_blocks(band, ds, kwargs={"table": table}, template=template)
    return labelled(image, transport["transport"], "image relit under a virtual 2-D pattern",
                    f"Σ T(du, dv, s, t)·P̄(t + dv, u₀ + du) over {ds.sizes['du']} × {ds.sizes['dv']} cells, "
                    f"{int(np.count_nonzero(pattern))} of {pattern.size} pattern pixels lit")


def pattern_rows(transport: xr.Dataset, space: str, projector_rows: int | None = None) -> int:
    """The rows a pattern in ``space`` has: the transport's camera-rectified rows (``camera``), or the projector's
    (``projector``: ``projector_rows``, else the store's ``projector_shape``; ValueError where neither says)."""
    if space not in ("projector", "camera"):
        raise ValueError(f"space is {space!r}; expected 'projector' or 'camera'")
    if space == "camera":
        return transport.sizes["row"]
    shape = transport.attrs.get("projector_shape")
    if projector_rows is None and shape is None:
        raise ValueError("the transport does not record the projector's rows (attr projector_shape): give "
                         "projector_rows, or patterns on camera-rectified rows (space: camera)")
    return int(projector_rows if projector_rows is not None else shape[0])


def relight_pattern(transport: xr.Dataset, pattern, *, projector_rows: int | None = None) -> xr.DataArray:
    """The image under ``pattern`` from a ``plane_to_ray_transport`` or ``full_transport`` store: a row pattern
    (1-D) or rows × projector columns (2-D), on camera-rectified rows, or on the projector's ``projector_rows``
    rows (:func:`on_camera_rows`). A plane-to-ray transport holds no projector column, so it takes a 2-D pattern
    only where each row is constant (ValueError otherwise); a full transport lights every column of a row pattern
    (``projector_shape``'s columns, else up to the last u-cell's edge)."""
    t = transport["transport"]
    on_rows = on_camera_rows(pattern, t.sizes["row"], projector_rows)
    if "offset" in t.dims:
        if on_rows.ndim == 2:
            if not np.allclose(on_rows, on_rows[:, :1]):
                raise ValueError("the pattern varies along its rows, and a plane-to-ray transport sums over "
                                 "projector columns: relight 2-D patterns from a full transport (demux_full)")
            on_rows = on_rows[:, 0]
        return relight(t, on_rows)
    if on_rows.ndim == 1:
        shape = transport.attrs.get("projector_shape")
        step, cells = float(transport.attrs["cell_width_px"]), transport.attrs["cells_px"]
        cols = int(shape[1]) if shape is not None else int(np.ceil(cells[-1] + step / 2))
        on_rows = np.repeat(on_rows[:, None], cols, axis=1)
    return relight_full(transport, on_rows)


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
