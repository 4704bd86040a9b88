"""Direct/global separation from shifted high-frequency checkerboards (Nayar et al. 2006; thesis §5.4.6).

Under a checkerboard that lights half the projector, a pixel's global light (inter-reflection, subsurface
scattering: light that reached it through other scene points) is half the floodlit global light when the
checkerboard's period is small against the global light's spread, whatever the board's phase; its direct light is
all or nothing. Over shifts that light every pixel once and darken it once, the brightest and the darkest frame
of each pixel are, with the projector's black level b (the share of its white a "black" pixel still emits)::

    L⁺ = L_d + (1 + b)·L_g / 2        L⁻ = b·L_d + (1 + b)·L_g / 2
    L_d = (L⁺ − L⁻) / (1 − b)         L_g = 2·(L⁻ − b·L⁺) / (1 − b²)

(b = 0: L_d = L⁺ − L⁻, L_g = 2·L⁻.) The same computation on a stack captured in epipolar mode (the rolling
shutter synchronised, t_d = 0, t_e = t_p) separates the epipolar image into its direct and its epipolar global
light (the thesis's epipolar-direct and epipolar-global images, Fig. 48): specular inter-reflections from other
epipolar planes, which Nayar's method keeps in its "direct" image (they are as sharp as direct light), are not in
the epipolar frames at all.

Known limits, stated rather than hidden: global light narrower than the board's period (subsurface scattering of
a few pixels) leaks into L_d; specular inter-reflection is counted as direct by the floodlit method.
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Fraction, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import FLAGS, CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables

#: bits of the separation's ``flags``
SATURATED, NONFINITE = 1, 2
FLAG_MASKS = [SATURATED, NONFINITE]
FLAG_MEANINGS = "saturated nonfinite"
#: below this share of pixels without a saturated or missing frame the separation means nothing
UNSATURATED_FLOOR = 0.5


def checkerboard_coverage(square: tuple[int, int], shifts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Over one period of a checkerboard of ``square`` = (rows, cols) projector pixels, whether each phase is lit
    by some shift and dark under some shift: ``(ever_lit, ever_dark)``, each (2·rows, 2·cols) boolean.

    A shift (r, c) moves the board by r rows and c columns (``selpath.devices.patterns.checkerboard``): phase (y, x) is
    lit when ``((y + r) // rows + (x + c) // cols)`` is odd.
    """
    rows, cols = square
    y, x = np.mgrid[: 2 * rows, : 2 * cols]
    lit = np.stack([((y + r) // rows + (x + c) // cols) % 2 == 1 for r, c in np.asarray(shifts, dtype=int)])
    return lit.any(axis=0), (~lit).any(axis=0)


def shift_problems(square: tuple[int, int], shifts: np.ndarray) -> list[str]:
    """Why a set of checkerboard shifts cannot separate every pixel (empty: it can)."""
    shifts = np.asarray(shifts)
    if shifts.ndim != 2 or shifts.shape[1] != 2:
        return [f"shifts must be (row, col) pairs; got shape {shifts.shape}"]
    if len(shifts) < 2:
        return [f"{len(shifts)} shift(s): the separation needs at least 2 (a board and its complement), so that "
                "every pixel is seen lit and dark"]
    ever_lit, ever_dark = checkerboard_coverage(square, shifts)
    problems = []
    for name, seen in (("lit", ever_lit), ("dark", ever_dark)):
        if not seen.all():
            y, x = np.argwhere(~seen)[0]
            problems.append(f"{(~seen).mean():.0%} of the board's phases are never {name} under these shifts "
                            f"(e.g. projector pixel ({y}, {x}) of a {2 * square[0]}×{2 * square[1]} period)")
    return problems


def separate(frames: xr.DataArray, *, black_level: float = 0.0, saturation_level: float = np.inf,
             dim: str = "shift") -> xr.Dataset:
    """L_d and L_g of every pixel from a stack of frames over ``dim`` (lazy): the formulas of the module doc, with
    pixels whose brightest frame is saturated, or which have a non-finite frame, flagged and NaN."""
    if not 0.0 <= black_level < 1.0:
        raise StageError(Problem(f"black_level is {black_level}; it is a share of white in [0, 1)",
                                 fix="measure the projector's black frame over its white frame"))
    brightest, darkest = frames.max(dim), frames.min(dim)
    nonfinite = (~np.isfinite(frames)).any(dim)
    saturated = brightest >= saturation_level
    flags = (saturated.astype(np.uint8) * SATURATED) | (nonfinite.astype(np.uint8) * NONFINITE)
    b = float(black_level)
    direct = ((brightest - darkest) / (1.0 - b)).where(flags == 0)
    global_ = (2.0 * (darkest - b * brightest) / (1.0 - b * b)).where(flags == 0)
    units = frames.attrs.get("units", "counts")
    return xr.Dataset({
        "direct": direct.drop_attrs(deep=False).assign_attrs(units=units),
        "global": global_.drop_attrs(deep=False).assign_attrs(units=units),
        "flags": flags.drop_attrs(deep=False).assign_attrs(flag_masks=FLAG_MASKS, flag_meanings=FLAG_MEANINGS),
        "unsaturated_fraction": usable_share(
            (flags == 0).mean(), floor=UNSATURATED_FLOOR,
            what="pixels whose frames are all finite and whose brightest frame is below saturation",
            fix="lower the exposure or the projector's power so that lit frames stay below saturation_counts; "
            "check for missing frames"),
    })


DIRECT_GLOBAL = CubeKind(
    name="direct_global",
    description="direct and global light per pixel from shifted checkerboards (§5.4.6, Nayar et al.)",
    variables={"direct": Variable(("row", "col"), units="counts", long_name="direct light L_d"),
               "global": Variable(("row", "col"), units="counts", long_name="global light L_g"),
               "flags": Variable(("row", "col"), required=False, **FLAGS)},
)


@stage("separate_direct_global", kind=DIRECT_GLOBAL)
def separate_direct_global(capture: xr.Dataset, /, *, black_level: Fraction | None = None,
                           saturation_level: Positive | None = None,
                           dark_level: NonNegative | None = None) -> xr.Dataset:
    """Direct and global light per pixel from shifted checkerboards (Nayar et al.; thesis §5.4.6, Fig. 48).

    On a floodlit (global-shutter) stack it gives Nayar's direct and global images; on a stack captured in epipolar
    mode, the epipolar-direct and epipolar-global images. Refused: fewer than 2 shifts, or shifts under which some
    phase of the board is never lit or never dark (it could not be separated).

    Parameters
    ----------
    capture : xr.Dataset
        ``image`` [counts] over (shift, row, col), with coordinates ``shift_row`` and ``shift_col`` along ``shift``
        (the board's shift [projector px], as ``selpath.devices.patterns.checkerboard`` takes it), attr ``square_px``
        ([rows, cols] of a square, projector px), ``saturation_counts`` and ``dark_level_counts`` (required of a
        checkerboard_capture store) and, where known, ``black_level``.
    black_level : float or None
        The projector's black level b: a dark pixel's light as a share of a lit one's [1], in [0, 1); None: the
        capture's ``black_level`` attr, else 0.
    saturation_level : float or None
        Raw count at or above which a frame is saturated [counts]; None: the capture's ``saturation_counts`` attr
        (an in-memory capture without it: nothing counts as saturated).
    dark_level : float or None
        The sensor's offset, subtracted from every frame before separating [counts]; None: the capture's
        ``dark_level_counts`` attr (an in-memory capture without it: 0).

    Returns
    -------
    xr.Dataset
        A ``direct_global`` cube: ``direct`` and ``global`` [counts] over (row, col), ``flags`` (saturated, nonfinite;
        flagged pixels are NaN) and the usable share ``unsaturated_fraction`` (floor 50 %).

    References
    ----------
    Thesis §5.4.6 Epipolar direct/global separation.
    """
    require_variables(capture, ("image",), "separate_direct_global")
    image = capture["image"]
    problems = []
    if "shift" not in image.dims or set(image.dims) != {"shift", "row", "col"}:
        problems.append(Problem(f"image has dims {image.dims}; expected (shift, row, col)", path="image",
                                fix="one frame per checkerboard shift"))
    missing = [c for c in ("shift_row", "shift_col") if c not in capture.coords]
    if missing or "square_px" not in capture.attrs:
        problems.append(Problem(f"the capture does not say which boards it holds (missing: "
                                f"{', '.join(missing + ([] if 'square_px' in capture.attrs else ['attr square_px']))})",
                                fix="give coordinates shift_row, shift_col along shift [projector px] and attr "
                                "square_px = [rows, cols]"))
    if problems:
        raise StageError(problems)
    square = tuple(int(v) for v in np.broadcast_to(np.asarray(capture.attrs["square_px"]), (2,)))
    shifts = np.stack([capture["shift_row"].values, capture["shift_col"].values], axis=1)
    reasons = shift_problems(square, shifts)
    if reasons:
        raise StageError([Problem(r, path="shift", fix="capture more shifts: e.g. the board and its complement "
                                  "(shift by one square), or the 4 half-square steps of the thesis's 128 shifts")
                          for r in reasons])
    b = black_level if black_level is not None else float(capture.attrs.get("black_level", 0.0))
    level = saturation_level if saturation_level is not None else float(
        capture.attrs.get("saturation_counts", np.inf))
    dark = dark_level if dark_level is not None else float(capture.attrs.get("dark_level_counts", 0.0))
    result = separate(image.astype(np.result_type(image.dtype, np.float32)) - dark, black_level=b,
                      saturation_level=level - dark)
    keep = {k: v for k, v in capture.attrs.items() if k not in ("selpath_kind", "saturation_counts")}
    return DIRECT_GLOBAL.label(result.assign_attrs(
        keep | {"black_level": b, "shifts": len(shifts), "dark_level_counts": dark}
        | ({"saturation_counts": level} if np.isfinite(level) else {})))
