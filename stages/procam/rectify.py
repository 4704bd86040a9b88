"""Are the sync rows epipolar? Gray-code correspondences, the rig's row misalignment, and rectified transport.

The synchronised rig rests on one assumption (§5.2, §6.1): projector and camera are a rectified stereo pair, so the
light a camera row receives directly comes from the projector row the sync pairs with it. A projector rolled or
shifted against the camera breaks it: pixel (s, c)'s direct light comes from δ(s, c) rows off, the epipolar frames
lose it once |δ| exceeds the lit line's height, and the plane-to-ray transport's direct peak sits at offset δ
instead of 0, a different δ in every column.

- ``decode_gray_code``: from a ``gray_code_capture`` (white, black, every column and row bit with its inverse,
  ``cv2.structured_light``'s codes), the projector column and row that light each pixel directly, to sub-pixel
  (neighbouring codes differ in one bit, whose contrast says how the pixel's light splits between the two; see
  ``_axis``); pixels in shadow (white − black below a share of the sensor's range) or with two bits whose pattern
  and inverse are too close (global light, clipping) are left undecoded (NaN). Vectorised over row bands by hand:
  OpenCV's ``getProjPixel`` answers one pixel per call and whole pixels only (tested as the peer).
- ``epipolar_alignment``: δ = decoded row, in camera rows, minus the camera row (the sync pairs camera row s with
  projector row (s + ½)·P/C − ½, P and C their row counts), and a robust fit δ = shift + tan(roll)·(c − c₀) + slope·
  (s − s₀), which averages the codes' whole-row quantisation away. Warns when the rows are not epipolar: when the
  fitted |δ| of one pixel in ten exceeds half the lit line's height (v_p·t_p rows).
- ``rectify_transport``: the plane-to-ray transport re-indexed per pixel, T'(o) = T(o + δ(s, c)) (linear
  interpolation along the offset; NaN where o + δ leaves the solved window), so the direct peak is back at offset 0.
  The projector's scan cannot be re-rowed after the fact: this rectifies the measured transport, and the fit says
  how to turn the projector (−roll) to rectify the rig itself.
"""

from __future__ import annotations

import warnings

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Fraction, Index, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.procam._gray_code import check_code_count, decode_band, resolved_drop
from selpath.stages.procam.demux import PLANE_TO_RAY_TRANSPORT

_FRAME = ("row", "col")
PROJECTOR_CORRESPONDENCE = CubeKind(
    name="projector_correspondence",
    description="the projector column and row that light each camera pixel directly (decode_gray_code)",
    variables={"projector_col": Variable(_FRAME, units="px", long_name="projector column lighting the pixel"),
               "projector_row": Variable(_FRAME, units="px", long_name="projector row lighting the pixel"),
               "code_sharpness": Variable(_FRAME, False, units="1", long_name="smallest contrast of the bits no "
                                          "neighbour shares: 1 direct light only, less with global light")},
    attrs={"projector_shape": "[rows, cols] of the projector"},
)
EPIPOLAR_ALIGNMENT = CubeKind(
    name="epipolar_alignment",
    description="how far each pixel's direct light is off its epipolar row, measured and fitted (epipolar_alignment)",
    variables={"measured": Variable(_FRAME, units="px", long_name="decoded row offset δ, camera rows"),
               "model": Variable(_FRAME, units="px", long_name="fitted row offset δ, camera rows")},
    attrs={"shift_rows": "fitted δ at the image centre, camera rows",
           "roll_deg": "fitted rotation of the projector's rows against the camera's, degree",
           "median_abs_rows": "median |δ| of the model over the decoded pixels, camera rows",
           "tolerance_rows": "|δ| above which the rows are not epipolar (default half the lit line's height), camera "
           "rows"},
)

#: below this share of decoded pixels a correspondence map means nothing
DECODED_FLOOR = 0.05
#: fit rounds, each dropping pixels more than TRIM robust deviations off the previous fit
FIT_ROUNDS, TRIM = 4, 4.0


@stage("decode_gray_code", kind=PROJECTOR_CORRESPONDENCE)
def decode_gray_code(capture: xr.Dataset, /, *, min_lit: Fraction = 0.02, min_contrast: Fraction = 0.2,
                     unresolved_bits: tuple[Index, Index] | None = None) -> xr.Dataset:
    """The projector column and row lighting each camera pixel directly, from Gray codes (lazy, per row band).

    A camera with fewer pixels than the projector along an axis cannot resolve that axis's finest stripes: those bits
    are left out (:func:`resolved_drop`; attr ``bits_unresolved`` [rows, cols]) and positions are found in blocks of
    2^dropped projector pixels.

    Parameters
    ----------
    capture : xr.Dataset
        A ``gray_code_capture`` (``acquire_gray_code``): ``image`` [counts] over (pattern, row, col): white, black,
        then each column bit and its inverse (most significant first), then each row bit likewise; attrs
        ``column_bits``, ``row_bits``, ``projector_shape`` [rows, cols], ``saturation_counts`` and
        ``dark_level_counts`` [counts].
    min_lit : float
        A pixel is in shadow below this share of the sensor's range (saturation − dark) between white and black [1].
    min_contrast : float
        A bit is clear when |pattern − inverse| reaches this share of the pixel's white − black [1]. One unclear bit
        per axis is the edge the pixel lies on (its contrast gives the sub-pixel position); two or more (global light
        as strong as direct, clipped frames) leave the pixel undecoded.
    unresolved_bits : [rows, cols] or None
        Least significant bits per axis to leave out; None: those finer than the camera's pixels if it saw the whole
        projector (:func:`resolved_drop` of the two sizes). Give it for a camera that sees part of the projector
        magnified (none unresolved: [0, 0]).

    Returns
    -------
    xr.Dataset
        A ``projector_correspondence`` cube: ``projector_col`` and ``projector_row`` [projector px, pixel centres at
        whole numbers, sub-pixel] over (row, col), NaN where undecoded, and the usable share ``decoded_fraction`` (floor
        5 %).

    References
    ----------
    Thesis §5.2.1 Epipolar geometry and light transport.
    """
    require_variables(capture, ("image",), "decode_gray_code")
    attrs = capture.attrs
    missing = [a for a in ("column_bits", "row_bits", "projector_shape", "saturation_counts", "dark_level_counts")
               if a not in attrs]
    if missing:
        raise StageError(Problem(f"the capture does not say which codes it holds or its sensor's range (missing "
                                 f"attrs: {', '.join(missing)})", fix="capture it with acquire_gray_code"))
    column_bits, row_bits = int(attrs["column_bits"]), int(attrs["row_bits"])
    shape = (int(attrs["projector_shape"][0]), int(attrs["projector_shape"][1]))
    image = capture["image"]
    if tuple(image.dims) != ("pattern", "row", "col"):
        raise StageError(Problem(f"image has dims {image.dims}; expected (pattern, row, col)", path="image",
                                 fix="capture it with acquire_gray_code"))
    check_code_count(image.sizes["pattern"], column_bits, row_bits)
    full_scale = float(attrs["saturation_counts"]) - float(attrs["dark_level_counts"])
    drop = (tuple(int(b) for b in unresolved_bits) if unresolved_bits is not None else
            (resolved_drop(shape[0], image.sizes["row"]), resolved_drop(shape[1], image.sizes["col"])))
    if drop[1] >= column_bits or drop[0] >= row_bits:
        raise StageError(Problem(f"unresolved_bits {list(drop)} leave no row or column bit of {row_bits} and "
                                 f"{column_bits}", fix="leave out fewer bits"))
    band = image.chunk({"pattern": -1, "row": min(64, image.sizes["row"]), "col": -1})
    both = xr.apply_ufunc(
        decode_band, band, input_core_dims=[["pattern"]], output_core_dims=[["axis"]], dask="parallelized",
        output_dtypes=[np.float64], dask_gufunc_kwargs={"output_sizes": {"axis": 3}},
        kwargs={"column_bits": column_bits, "row_bits": row_bits, "shape": shape, "min_lit": min_lit * full_scale,
                "min_contrast": min_contrast, "drop": drop})
    col = both.isel(axis=0, drop=True).drop_attrs(deep=False)
    row = both.isel(axis=1, drop=True).drop_attrs(deep=False)
    sharpness = both.isel(axis=2, drop=True).drop_attrs(deep=False)
    out = xr.Dataset({
        "projector_col": col, "projector_row": row, "code_sharpness": sharpness,
        "decoded_fraction": usable_share(
            np.isfinite(col).mean(), floor=DECODED_FLOOR, what="pixels whose projector column and row were decoded",
            fix="light the scene brighter or lower min_lit; a scene dominated by global light needs a lower "
            "min_contrast"),
    }, attrs={"projector_shape": list(shape),
              "min_lit": min_lit, "min_contrast": min_contrast, "bits_unresolved": [drop[0], drop[1]],
              **{k: attrs[k] for k in ("scan_speed_px_per_us", "line_time_us") if k in attrs}})
    return PROJECTOR_CORRESPONDENCE.label(out)


def row_offsets(projector_row: np.ndarray, projector_rows: int) -> np.ndarray:
    """δ [camera rows] of decoded projector rows (rows, cols): the decoded row on the camera's row scale minus the
    camera row (the sync pairs camera row s with projector row (s + ½)·P/C − ½).

    Two camera rows lit by one projector row: its centre lies between them.

    >>> row_offsets(np.array([[0.0], [0.0]]), 1)
    array([[ 0.5],
           [-0.5]])
    """
    rows = projector_row.shape[0]
    return paired_camera_row(projector_row, projector_rows, rows) - np.arange(rows)[:, None]


def paired_camera_row(projector_row, projector_rows: int, camera_rows: int):
    """The camera row the sync pairs with (sub-pixel) projector row p: (p + ½)·C/P − ½, rows as unit cells with
    centres at whole numbers.

    >>> float(paired_camera_row(359.5, 720, 1200))
    599.5
    """
    return (np.asarray(projector_row, float) + 0.5) * camera_rows / projector_rows - 0.5


def fit_misalignment(delta: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust least squares δ ≈ b₀ + b₁·(c − c₀) + b₂·(s − s₀) over the finite δ (rows, cols), c₀ and s₀ the image
    centre: rounds of a fit that drop pixels more than TRIM robust deviations (1.4826·MAD) off the previous one.
    Returns the coefficients and their standard errors (cluster-robust, one cluster per camera row)."""
    rows, cols = delta.shape
    s, c = np.nonzero(np.isfinite(delta))
    y = delta[s, c]
    design = np.stack([np.ones_like(y), c - (cols - 1) / 2, s - (rows - 1) / 2], axis=1)
    keep = np.ones(y.size, bool)
    for _ in range(FIT_ROUNDS):
        _require_spread(s[keep], c[keep])
        coef, *_ = np.linalg.lstsq(design[keep], y[keep], rcond=None)
        residual = y - design @ coef
        centre = np.median(residual[keep])  # one-sided outliers pull the fit: trim around the bulk, not around 0
        spread = 1.4826 * np.median(np.abs(residual[keep] - centre))
        keep = np.abs(residual - centre) <= TRIM * max(spread, 1e-9)
    _require_spread(s[keep], c[keep])
    coef, *_ = np.linalg.lstsq(design[keep], y[keep], rcond=None)
    # the codes' quantisation errs alike along a camera row (its pixels see the same rows), so the covariance is
    # the cluster-robust sandwich with one cluster per camera row, not σ²(XᵀX)⁻¹ (which was 4× too small)
    x, e, g = design[keep], y[keep] - design[keep] @ coef, s[keep]
    bread = np.linalg.inv(x.T @ x)
    scores = np.zeros((rows, 3))
    np.add.at(scores, g, x * e[:, None])
    clusters = np.count_nonzero(np.any(scores != 0, axis=1))
    meat = scores.T @ scores * clusters / max(clusters - 1, 1)
    return coef, np.sqrt(np.diag(bread @ meat @ bread))


def _require_spread(rows: np.ndarray, cols: np.ndarray) -> None:
    """A shift, a roll and a row slope need decoded pixels in at least two rows and two columns (and 3 of them)."""
    if rows.size < 3 or np.unique(rows).size < 2 or np.unique(cols).size < 2:
        raise StageError(Problem(f"{rows.size} decoded pixel(s) in {np.unique(rows).size} row(s) and "
                                 f"{np.unique(cols).size} column(s): a shift, a roll and a row slope need pixels in at "
                                 "least two rows and two columns", fix="see decode_gray_code's decoded_fraction; "
                                 "light more of the scene"))


@stage("epipolar_alignment", kind=EPIPOLAR_ALIGNMENT)
def epipolar_alignment(correspondence: xr.Dataset, /, *, tolerance_rows: Positive | None = None,
                       min_sharpness: Fraction = 0.75) -> xr.Dataset:
    """How far each pixel's direct light is off its epipolar row, decoded and fitted, and whether the rows are epipolar.

    A UserWarning gives the numbers when they are not.

    Parameters
    ----------
    correspondence : xr.Dataset
        A ``projector_correspondence`` (``decode_gray_code``): ``projector_row`` [projector px] over (row, col),
        attr ``projector_shape``; ``scan_speed_px_per_us`` and ``line_time_us`` where known.
    tolerance_rows : float or None
        |δ| the epipolar frames tolerate [camera rows]; None: half the lit line's height, v_p·t_p / 2 (half a row
        without the rig's timing).
    min_sharpness : float
        The fit uses the pixels whose code is at least this sharp (``code_sharpness`` [1]: global light such as
        subsurface scattering blurs a code and biases its sub-pixel position, by up to 0.2 rows in the tests); all
        decoded pixels when fewer than 100 are. Attr ``fit_pixels`` says how many were used.

    Returns
    -------
    xr.Dataset
        An ``epipolar_alignment`` cube: ``measured`` (δ of each decoded pixel, NaN elsewhere) and ``model`` (the fit at
        every pixel) [camera rows] over (row, col); attrs ``shift_rows``, ``roll_deg`` (the projector's rows turned
        against the camera's: turn it by −roll to rectify the rig), ``row_slope`` (δ per camera row: a row-scale
        mismatch), their standard errors (``*_std``), ``median_abs_rows`` and ``p90_abs_rows`` (of the model over the
        decoded pixels), ``residual_rows`` (robust spread of measured − model: the codes' quantisation) and
        ``tolerance_rows``.

    References
    ----------
    Thesis §5.2.1 Epipolar geometry and light transport.
    """
    require_variables(correspondence, ("projector_row",), "epipolar_alignment")
    attrs = correspondence.attrs
    if "projector_shape" not in attrs:
        raise StageError(Problem("attr projector_shape is missing; the projector's rows set the row scale",
                                 fix="decode the correspondence with decode_gray_code"))
    if tolerance_rows is None:
        speed, line = attrs.get("scan_speed_px_per_us"), attrs.get("line_time_us")
        tolerance_rows = float(speed) * float(line) / 2 if speed and line else 0.5
    decoded = correspondence["projector_row"].transpose("row", "col")
    delta = row_offsets(np.asarray(decoded.values, float), int(attrs["projector_shape"][0]))
    sharp = np.isfinite(delta)
    if "code_sharpness" in correspondence:
        sharpness = np.asarray(correspondence["code_sharpness"].transpose("row", "col").values, float)
        if np.count_nonzero(sharp & (sharpness >= min_sharpness)) >= 100:
            sharp &= sharpness >= min_sharpness
    coef, std = fit_misalignment(np.where(sharp, delta, np.nan))
    rows, cols = delta.shape
    s, c = np.mgrid[:rows, :cols]
    model = coef[0] + coef[1] * (c - (cols - 1) / 2) + coef[2] * (s - (rows - 1) / 2)
    seen = np.isfinite(delta)
    magnitude = np.abs(model[seen])
    spread = 1.4826 * np.median(np.abs((delta - model)[seen] - np.median((delta - model)[seen])))
    fitted = {"shift_rows": float(coef[0]), "shift_rows_std": float(std[0]),
              "roll_deg": float(np.rad2deg(np.arctan(coef[1]))),
              "roll_deg_std": float(np.rad2deg(std[1] / (1 + coef[1] ** 2))),
              "row_slope": float(coef[2]), "row_slope_std": float(std[2]),
              "median_abs_rows": float(np.median(magnitude)), "p90_abs_rows": float(np.quantile(magnitude, 0.9)),
              "residual_rows": float(spread), "tolerance_rows": float(tolerance_rows),
              "fit_pixels": int(np.count_nonzero(sharp))}
    if fitted["p90_abs_rows"] > tolerance_rows:
        warnings.warn(f"epipolar_alignment: the sync rows are not epipolar: the direct light of one pixel in ten is "
                      f"{fitted['p90_abs_rows']:.2f} rows or more off its row (median {fitted['median_abs_rows']:.2f}; "
                      f"shift {fitted['shift_rows']:.2f} rows, roll {fitted['roll_deg']:.3f}°), beyond the "
                      f"{tolerance_rows:.2f} rows the epipolar frames tolerate: they lose direct light and the "
                      "transport's direct peak leaves offset 0. Rectify the transport (rectify_transport) or turn "
                      f"the projector by {-fitted['roll_deg']:.3f}° about its axis", UserWarning, stacklevel=2)
    dims = ("row", "col")
    coords = {d: correspondence[d] for d in dims if d in correspondence.coords}
    out = xr.Dataset({
        "measured": (dims, delta), "model": (dims, model),
    }, coords=coords, attrs={**fitted, "projector_shape": list(attrs["projector_shape"])})
    return EPIPOLAR_ALIGNMENT.label(out)


def _shift_offsets(transport: np.ndarray, delta: np.ndarray, *, offsets: np.ndarray) -> np.ndarray:
    """(..., offset) transport → the same re-indexed at offsets + δ (linear; NaN outside the grid), all pixels at
    once (``np.searchsorted`` of every query on the shared grid)."""
    n = offsets.size
    flat = transport.reshape(-1, n).astype(np.float64)
    want = offsets[None, :] + np.asarray(delta, float).reshape(-1, 1)
    inside = (want >= offsets[0]) & (want <= offsets[-1])
    left = np.clip(np.searchsorted(offsets, want, side="right") - 1, 0, max(n - 2, 0))
    right = np.minimum(left + 1, n - 1)
    span = np.where(right > left, offsets[right] - offsets[left], 1.0)
    weight = np.where(right > left, (want - offsets[left]) / span, 0.0)
    lower, upper = np.take_along_axis(flat, left, axis=1), np.take_along_axis(flat, right, axis=1)
    # (a query on a grid point takes that point alone: a NaN beside it does not spread)
    value = np.where(weight == 0, lower, np.where(weight == 1, upper, lower * (1 - weight) + upper * weight))
    return np.where(inside, value, np.nan).reshape(transport.shape).astype(transport.dtype)


@stage("rectify_transport", kind=PLANE_TO_RAY_TRANSPORT)
def rectify_transport(transport: xr.Dataset, alignment: xr.Dataset, /) -> xr.Dataset:
    """A plane-to-ray transport re-indexed so that each pixel's epipolar row is offset 0: T'(o) = T(o + δ(s, c)).

    Lazy; linear interpolation along the offset, NaN where o + δ leaves the solved offsets.

    Parameters
    ----------
    transport : xr.Dataset
        A ``plane_to_ray_transport`` (``demux_plane_to_ray``): ``transport`` over (offset, row, col), offsets
        [camera rows] evenly or unevenly spaced, increasing.
    alignment : xr.Dataset
        An ``epipolar_alignment`` of the same rig and sensor: ``model`` δ [camera rows] over (row, col).

    Returns
    -------
    xr.Dataset
        A ``plane_to_ray_transport`` cube: the transport re-indexed so that offset 0 is each pixel's epipolar row (T'(o)
        = T(o + δ)), lazily; the same kind.

    References
    ----------
    Thesis §5.2.1 Epipolar geometry and light transport.
    """
    require_variables(transport, ("transport",), "rectify_transport")
    require_variables(alignment, ("model",), "rectify_transport")
    t = transport["transport"]
    sizes = {d: t.sizes[d] for d in ("row", "col")}
    if {d: alignment["model"].sizes.get(d) for d in ("row", "col")} != sizes:
        raise StageError(Problem(f"the transport is {sizes['row']} × {sizes['col']} px, the alignment "
                                 f"{dict(alignment['model'].sizes)}", fix="align the rig with the same sensor"))
    if t.chunks is not None:
        t = t.chunk({"offset": -1})
    offsets = np.asarray(transport["offset"].values, float)
    if offsets.size < 2 or np.any(np.diff(offsets) <= 0):
        raise StageError(Problem("the transport's offsets must increase (at least two of them)", path="offset",
                                 fix="a plane_to_ray_transport from demux_plane_to_ray"))
    delta = alignment["model"].drop_vars([d for d in ("row", "col") if d in alignment.coords])
    moved = xr.apply_ufunc(
        _shift_offsets, t, delta, input_core_dims=[["offset"], []], output_core_dims=[["offset"]],
        dask="parallelized", output_dtypes=[t.dtype], kwargs={"offsets": offsets})
    out = transport.copy()
    out["transport"] = moved.transpose(*t.dims).assign_attrs(t.attrs)
    out.attrs = {**transport.attrs, "rectified_shift_rows": alignment.attrs.get("shift_rows"),
                 "rectified_roll_deg": alignment.attrs.get("roll_deg")}
    return out
