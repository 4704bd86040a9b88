"""The ``.selpath`` accessor: selpath's cubes in the thesis's terms, on any store's Dataset and its variables.

``import selpath`` registers it (once xarray is imported). Every method reads lazily and returns a labelled result
(``units``, ``long_name`` and a ``description`` of how it was made); nothing writes. What a store cannot know (a v_p
for a transport made outside selpath, the projector's rows) is an explicit argument.

One rule addresses pixels everywhere: ``row``/``col`` are array indices; ``x``/``y`` are the workflows' image
fractions, each in [0, 1], and name the pixel ``row = min(⌊y·rows⌋, rows − 1)``, ``col = min(⌊x·cols⌋, cols − 1)``
(as the figure stages' ``pixels`` setting does).

>>> import numpy as np, xarray as xr, selpath
>>> T = xr.Dataset({"transport": (("offset", "row", "col"), np.ones((3, 4, 5)))},
...                coords={"offset": [-1, 0, 1]}, attrs={"scan_speed_px_per_us": 0.05, "sync_offset_us": 0.0})
>>> T.selpath.pixel(x=0.5, y=1.0)
(3, 2)
>>> T.selpath.profile(x=0.5, y=1.0)["sync_delay"].values.tolist()
[-20.0, 0.0, 20.0]
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
import xarray as xr

if TYPE_CHECKING:
    from selpath.stages.procam._illumination import RigTiming

# The stages each method calls are imported by the method: this module is imported the moment xarray is (to register
# the accessor), so it imports nothing of selpath's at its top (selpath/_after_import.py)

#: the variable each kind is about, where a method needs one and none is named
MAIN = {"plane_to_ray_transport": "transport", "full_transport": "transport", "plane_to_ray_capture": "image",
        "full_transport_capture": "image", "sinogram": "absorption", "reconstruction": "sigma"}


def _note(result: xr.DataArray, long_name: str, description: str, units: str | None = None) -> xr.DataArray:
    """``result`` labelled: its long name, how it was made, and ``units`` where given (else those it kept)."""
    return result.assign_attrs({"long_name": long_name, "description": description,
                                **({"units": units} if units is not None else {})})


class _Common:
    """What every cube answers: its kind, its pixels, a region's statistics, a figure."""

    def __init__(self, obj: xr.Dataset | xr.DataArray) -> None:
        self._obj = obj

    @property
    def kind(self) -> str | None:
        """The store's cube kind (its ``selpath_kind`` attr), None for a cube selpath did not label."""
        return self._obj.attrs.get("selpath_kind")

    def pixel(self, row: int | None = None, col: int | None = None, *, x: float | None = None,
              y: float | None = None) -> tuple[int, int]:
        """(row, col) of a pixel named by indices, or by image fractions ``x``, ``y`` (the module's one rule)."""
        sizes = self._obj.sizes
        if "row" not in sizes or "col" not in sizes:
            raise ValueError(f"this cube has no (row, col) frame; its dims are {tuple(sizes)}")
        if (row is None) != (col is None) or (x is None) != (y is None) or (row is None) == (x is None):
            raise ValueError("name a pixel by row and col (indices) or by x and y (image fractions in [0, 1])")
        if x is not None:
            if not (0 <= x <= 1 and 0 <= y <= 1):
                raise ValueError(f"x = {x}, y = {y}: image fractions are in [0, 1]")
            from selpath.stages._common import pixel_at

            return pixel_at(self._obj, (x, y))
        if not (0 <= row < sizes["row"] and 0 <= col < sizes["col"]):
            raise ValueError(f"pixel (row {row}, col {col}) is outside the {sizes['row']} × {sizes['col']} frame")
        return int(row), int(col)

    def _array(self, variable: str | None = None) -> xr.DataArray:
        obj = self._obj
        if isinstance(obj, xr.DataArray):
            return obj
        name = variable or MAIN.get(self.kind or "")
        if name is None:
            framed = [v for v in obj.data_vars if {"row", "col"} <= set(obj[v].dims)]
            if len(framed) != 1:
                raise ValueError(f"name the variable: one of {list(obj.data_vars)}")
            name = framed[0]
        if name not in obj.data_vars:
            raise ValueError(f"no variable {name!r}; this {self.kind or 'cube'} has {list(obj.data_vars)}")
        return obj[name]

    def region(self, rows: tuple[int, int] | None = None, cols: tuple[int, int] | None = None, *,
               x: tuple[float, float] | None = None, y: tuple[float, float] | None = None,
               variable: str | None = None) -> xr.Dataset:
        """Statistics of a rectangle of pixels, NaN skipped, per remaining dim (a region's mean delay profile, a
        region's mean over delay and exposure): ``mean``, ``std``, ``min``, ``max`` and ``count``. The rectangle is
        rows [r0, r1) × cols [c0, c1), or image fractions ``x`` = (x0, x1), ``y`` = (y0, y1) (r0 =
        ⌊y0·rows⌋, r1 = ⌈y1·rows⌉)."""
        a = self._array(variable)
        if x is not None or y is not None:
            x, y = x or (0.0, 1.0), y or (0.0, 1.0)
            rows = (int(np.floor(y[0] * a.sizes["row"])), int(np.ceil(y[1] * a.sizes["row"])))
            cols = (int(np.floor(x[0] * a.sizes["col"])), int(np.ceil(x[1] * a.sizes["col"])))
        rows, cols = rows or (0, a.sizes["row"]), cols or (0, a.sizes["col"])
        if not (0 <= rows[0] < rows[1] <= a.sizes["row"] and 0 <= cols[0] < cols[1] <= a.sizes["col"]):
            raise ValueError(f"region rows {rows}, cols {cols} is empty or outside the "
                             f"{a.sizes['row']} × {a.sizes['col']} frame")
        part = a.isel(row=slice(*rows), col=slice(*cols))
        where = f"rows {rows[0]}–{rows[1] - 1}, cols {cols[0]}–{cols[1] - 1}"
        name = a.attrs.get("long_name", a.name or "values")
        units = a.attrs.get("units")
        stats = {label: _note(getattr(part, label)(("row", "col")), f"{label} of {name} over {where}",
                              f"{label} over the region, NaN skipped", units)
                 for label in ("mean", "std", "min", "max")}
        stats["count"] = _note(part.count(("row", "col")), f"finite pixels of {name} over {where}", "", "1")
        return xr.Dataset(stats, attrs={"region": where})

    def plot(self, variable: str | None = None, **kwargs):
        """A matplotlib figure of the cube (an image, a profile, a sinogram with its unobserved bins, flags with a
        categorical key): :func:`selpath.explore.plots.plot`."""
        from selpath.explore import plots  # matplotlib, when a figure is asked for

        obj = self._obj
        if isinstance(obj, xr.Dataset) and self.kind == "sinogram" and variable is None:
            return plots.sinogram(obj, **kwargs)
        return plots.plot(self._array(variable), **kwargs)


@xr.register_dataarray_accessor("selpath")
class SelpathArray(_Common):
    """``da.selpath``: pixels, regions and a figure of one variable."""


@xr.register_dataset_accessor("selpath")
class SelpathDataset(_Common):
    """``ds.selpath``: a store's cube in the thesis's terms (module docstring)."""

    # -- plane-to-ray and full transport (chapter 5) ------------------------------------------------------------
    def _transport(self) -> xr.DataArray:
        if "transport" not in self._obj.data_vars:
            raise ValueError(f"this is a {self.kind or 'cube'}, not a transport: it has no variable 'transport'")
        return self._obj["transport"]

    def _offset_dim(self) -> str:
        t = self._transport()
        return "offset" if "offset" in t.dims else "dv"

    def _timing(self, scan_speed: float | None, sync_offset: float | None,
                line_time: float | None = 0.0) -> RigTiming:
        from selpath.stages.procam._illumination import RigTiming

        attrs = self._obj.attrs
        timing = {"scan_speed": scan_speed if scan_speed is not None else attrs.get("scan_speed_px_per_us"),
                  "sync_offset": sync_offset if sync_offset is not None else attrs.get("sync_offset_us", 0.0),
                  "line_time": line_time if line_time is not None else attrs.get("line_time_us")}
        missing = [k for k, v in timing.items() if v is None]
        if missing:
            raise ValueError(f"the store does not record {', '.join(missing)} (attrs scan_speed_px_per_us, "
                             f"line_time_us): give {', '.join(missing)} [rows per µs, µs]")
        return RigTiming(**{k: float(v) for k, v in timing.items()})

    def sync_delay(self, *, scan_speed: float | None = None, sync_offset: float | None = None) -> xr.DataArray:
        """The sync delay t_d [µs] at which each offset's light is centred in the exposure, t_d = o / v_p − t_o:
        the store's ``sync_delay`` coordinate, or computed from ``scan_speed`` v_p [rows/µs] and ``sync_offset``
        t_o [µs] (default: the store's attrs)."""
        from selpath.stages.procam._illumination import SYNC_DELAY_ATTRS, offset_delay

        dim = self._offset_dim()
        if "sync_delay" in self._obj.coords and scan_speed is None and sync_offset is None:
            return self._obj["sync_delay"]
        timing = self._timing(scan_speed, sync_offset)
        values = offset_delay(self._obj[dim].values, scan_speed=timing.scan_speed, sync_offset=timing.sync_offset)
        return xr.DataArray(values, dims=dim, coords={dim: self._obj[dim]}, name="sync_delay",
                            attrs=dict(SYNC_DELAY_ATTRS))

    def profile(self, row: int | None = None, col: int | None = None, *, x: float | None = None,
                y: float | None = None, scan_speed: float | None = None,
                sync_offset: float | None = None) -> xr.DataArray:
        """A pixel's transport: T over offset with its ``sync_delay`` [µs] beside it (plane-to-ray), or the 2-D
        T(du, dv) (full transport), in the transport's units. The sync delay needs v_p and t_o: the store's, else
        ``scan_speed`` [rows/µs] and ``sync_offset`` [µs]; a transport that records neither and is given neither
        gets no ``sync_delay`` (its description says so)."""
        r, c = self.pixel(row, col, x=x, y=y)
        out = self._transport().isel(row=r, col=c)
        try:
            out = out.assign_coords(sync_delay=self.sync_delay(scan_speed=scan_speed, sync_offset=sync_offset))
            how = "sync_delay = offset / v_p − t_o [µs]"
        except ValueError:
            how = "no sync_delay: the store records no scan_speed_px_per_us (give scan_speed)"
        what = "T(offset)" if self._offset_dim() == "offset" else "T(du, dv)"
        return _note(out, f"transport {what} of pixel (row {r}, col {c})", f"the transport at one pixel; {how}")

    def ideal_frame(self, delay: float, exposure: float, *, scan_speed: float | None = None,
                    line_time: float | None = None, sync_offset: float | None = None) -> xr.DataArray:
        """The frame an ideal rig records at sync delay ``delay`` and exposure ``exposure`` [µs] (no noise,
        clipping or jitter), through the illumination model the demultiplexer inverts
        (:func:`selpath.stages.procam.relight.ideal_frame`); timing from the store's attrs unless given."""
        from selpath.stages.procam.relight import ideal_frame

        t = self._transport()
        if "offset" not in t.dims:
            raise ValueError("ideal_frame needs a plane-to-ray transport (dims offset, row, col)")
        timing = self._timing(scan_speed, sync_offset, line_time)
        return ideal_frame(t, delay, exposure, **timing.keywords())

    def epipolar(self, band: int = 0) -> xr.DataArray:
        """Light from the epipolar planes |offset| ≤ ``band`` [rows] (Eq. 35; 0: the sharpened epipolar image)."""
        from selpath.stages.procam.relight import epipolar_image

        return epipolar_image(self._plane_to_ray(), band)

    def non_epipolar(self, band: int = 0) -> xr.DataArray:
        """Light from the planes |offset| > ``band`` [rows] (Eq. 36)."""
        from selpath.stages.procam.relight import non_epipolar_image

        return non_epipolar_image(self._plane_to_ray(), band)

    def _plane_to_ray(self) -> xr.DataArray:
        from selpath.stages.procam.relight import labelled

        t = self._transport()
        if "du" in t.dims:
            t = labelled(t.sum("du").rename(dv="offset"), t, "transport summed over du", "")
        return t

    def relight(self, pattern=None, *, line: int | None = None, rows=None, space: str = "projector",
                projector_rows: int | None = None) -> xr.DataArray:
        """The image under a virtual pattern: a projector row ``line``, a set of ``rows``, or a ``pattern`` (1-D
        over rows, or rows × projector columns; values in [0, 1], 1 = lit for a whole line time). ``space``
        ``projector``: on the projector's rows (``projector_rows``, else the store's ``projector_shape``), averaged
        onto the camera rows each covers; ``camera``: on the transport's camera-rectified rows. A plane-to-ray
        transport takes row patterns (it holds no column); a full transport any 2-D pattern."""
        from selpath.stages.procam.relight import pattern_rows, relight_pattern

        self._transport()
        n_rows = pattern_rows(self._obj, space, projector_rows)
        given = [pattern is not None, line is not None, rows is not None]
        if sum(given) != 1:
            raise ValueError("give exactly one of pattern, line or rows")
        if pattern is None:
            from selpath.stages.procam.virtual import Pattern  # the stage's rule for rows lit

            pattern = Pattern(rows=(line,) if line is not None else tuple(int(r) for r in rows)).array(n_rows)
        return relight_pattern(self._obj, pattern, projector_rows=None if space == "camera" else n_rows)

    # -- captures (chapter 5) ------------------------------------------------------------------------------------
    def intensity(self, row: int | None = None, col: int | None = None, *, x: float | None = None,
                  y: float | None = None) -> xr.DataArray:
        """A capture's pixel over its sweep: I(t_d) per exposure (and per line of a full-transport capture), in
        the capture's counts."""
        if "image" not in self._obj.data_vars or "delay" not in self._obj["image"].dims:
            raise ValueError(f"this is a {self.kind or 'cube'}, not a delay sweep: it has no image over delay")
        r, c = self.pixel(row, col, x=x, y=y)
        return _note(self._obj["image"].isel(row=r, col=c), f"I(t_d) of pixel (row {r}, col {c})",
                     "the captured counts over the sync delay, per exposure")

    # -- tomography (chapter 4) ----------------------------------------------------------------------------------
    def sinogram(self, slice: int | None = None) -> xr.DataArray:
        """The sinogram's absorption with the bins no ray observed set to NaN (the ``observed`` mask), one slice
        (by index) or all."""
        ds = self._obj
        if "absorption" not in ds.data_vars or "observed" not in ds.data_vars:
            raise ValueError(f"this is a {self.kind or 'cube'}, not a sinogram (absorption and observed)")
        out = ds["absorption"].where(ds["observed"])
        if slice is not None and "slice" in out.dims:
            out = out.isel(slice=slice)
        return _note(out, "total absorption A, unobserved bins NaN", "absorption where observed is True")

    def volume(self) -> xr.DataArray:
        """A reconstruction's σ over (z, y, x), every axis in the store's length unit (slices by their height z)."""
        sigma = self._array("sigma")
        if "slice" not in sigma.dims or "z" not in sigma.coords:
            raise ValueError("this reconstruction's slices carry no height z (reconstruct from a sinogram binned "
                             "by this version's bin_sinogram)")
        return sigma.swap_dims(slice="z")

    def compare(self, truth: xr.Dataset | xr.DataArray) -> xr.Dataset:
        """A reconstruction beside its truth (a ``reconstruction`` store of the true σ on the same grid, e.g.
        ``phantom_truth``'s; one slice serves every slice): ``sigma``, ``truth`` and ``error`` = sigma − truth."""
        sigma = self._array("sigma")
        expected = truth["sigma"] if isinstance(truth, xr.Dataset) else truth
        if "slice" in expected.dims and expected.sizes["slice"] == 1:
            expected = expected.isel(slice=0, drop=True)
        for dim in ("y", "x"):
            if expected.sizes.get(dim) != sigma.sizes.get(dim) or not np.allclose(expected[dim], sigma[dim]):
                raise ValueError(f"the truth's {dim} grid is not the reconstruction's (rasterise it on the same "
                                 "grid: phantom_truth with the reconstruction's sinogram)")
        expected = expected.assign_coords(y=sigma["y"], x=sigma["x"])
        units = sigma.attrs.get("units")
        return xr.Dataset({"sigma": sigma, "truth": _note(expected, "true absorption coefficient σ", "", units),
                           "error": _note(sigma - expected, "error σ − σ_true", "reconstruction minus truth",
                                          units)})
