"""Calibration of tomography frames: dark/background subtraction, reference normalisation, absorption.

Total absorption follows thesis Eq. 3 with the reference object of §4.4.2 as the unattenuated
intensity: ``A = log I_reference − log I_target`` (dark-subtracted), so that ``A = ∫σ dz ≥ 0`` for an
absorbing inclusion and the skin's BTDF cancels. (Eq. 3 as printed, ``log I_o − log I_i`` with
``I_o`` the transmitted light, is the negative of this; we keep the sign in which σ ≥ 0.)

Pixels where the log is meaningless are never silently NaN/inf: each output carries a ``flags``
variable (CF ``flag_masks``/``flag_meanings``) whose bits say why, and flagged pixels hold NaN.
When the capture has ``backlit`` frames, pixels off the object (outside the silhouette of the backlit
frame at that angle, :func:`selpath.stages.tomography.hull.object_masks`) are flagged ``background`` (bit 64):
there target and reference are both the dark level, and their log difference is the sensor's noise.
All stages are elementwise xarray operations on dask arrays, hence lazy and tile-parallel (the
silhouettes one task per angle chunk, on whole frames).
"""

from __future__ import annotations

import numpy as np
import xarray as xr

from selpath.geometry.rig import saturation_counts
from selpath.pipeline.constraints import Fraction, NonNegative, Positive
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import ANGLE_UNITS, FLAGS, CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables, sorted_sweep
from selpath.stages.tomography._pair_docs import pair_docs
from selpath.stages.tomography.acquire import TOMOGRAPHY_CAPTURE
from selpath.stages.tomography.hull import SILHOUETTE_FLOOR, object_masks

#: bits of ``flags``; target bits are shifted by 0, reference bits by 3; BACKGROUND: not on the object
SATURATED, NO_SIGNAL, NONFINITE = 1, 2, 4
BACKGROUND = 64
FLAG_MASKS = [1, 2, 4, 8, 16, 32, 64]
FLAG_MEANINGS = ("target_saturated target_no_signal target_nonfinite "
                 "reference_saturated reference_no_signal reference_nonfinite background")
FRAME_VARIABLES = ("target", "reference", "backlit")

_FRAMES = ("angle", "row", "col")
#: what absorption and normalise_reference report of the object's pixels beside their usable shares
_SHARES = {
    "object_valid_fraction": Variable((), False, units="1",
                                      long_name="share of the object's pixels (not flagged background) that are valid"),
    "background_fraction": Variable((), False, units="1",
                                    long_name="share of pixels flagged background (off the object in the backlit "
                                    "frames)"),
}
ABSORPTION = CubeKind(
    name="absorption",
    description="total absorption A = log I_reference − log I_target per pixel, with flags",
    variables={"absorption": Variable(_FRAMES, units="1",
                                      long_name="total absorption A = log I_reference − log I_target"),
               "flags": Variable(_FRAMES, description="CF flag bits; 0 means valid", **FLAGS), **_SHARES},
    coord_units={"angle": ANGLE_UNITS},
)
TRANSMITTANCE = CubeKind(
    name="transmittance",
    description="I_target / I_reference per pixel, with flags",
    variables={"transmittance": Variable(_FRAMES, units="1", long_name="transmittance I_target / I_reference"),
               "flags": Variable(_FRAMES, description="CF flag bits; 0 means valid", **FLAGS), **_SHARES},
    coord_units={"angle": ANGLE_UNITS},
)


def _float_dtype(array: xr.DataArray) -> np.dtype:
    return np.result_type(array.dtype, np.float32)


@stage("subtract_background", kind=TOMOGRAPHY_CAPTURE)
def subtract_background(capture: xr.Dataset, /, *, background: str = "dark",
                        variables: tuple[str, ...] = FRAME_VARIABLES) -> xr.Dataset:
    """Subtract a background frame (dark by default) from the frame variables, lazily.

    The background variable is kept and named in attr ``background_subtracted``, so later stages can
    still judge saturation on the raw counts (raw = corrected + background).

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` store (frames over (angle, row, col) [counts] and the background frame).
    background : str
        Variable holding the background frame (dims ``row, col``), e.g. ``dark``.
    variables : list of str
        Frame variables to correct; those absent from the capture are skipped.

    Returns
    -------
    xr.Dataset
        A ``tomography_capture`` cube: the capture with the background subtracted from its frame variables (lazy; the
        same kind).

    References
    ----------
    Thesis §4.2.1 Distribution of the absorption coefficient and total absorption.
    """
    require_variables(capture, (background,), "subtract_background")
    if capture.attrs.get("background_subtracted"):
        raise StageError(Problem(f"background {capture.attrs['background_subtracted']!r} was already subtracted",
                                 fix="subtract it once"))
    present = [v for v in variables if v in capture.data_vars]
    corrected = {v: (capture[v].astype(_float_dtype(capture[v])) - capture[background]).assign_attrs(capture[v].attrs)
                 for v in present}
    return capture.assign(corrected).assign_attrs(background_subtracted=background)


@stage("subtract_dark", kind=TOMOGRAPHY_CAPTURE)
def subtract_dark(capture: xr.Dataset, /) -> xr.Dataset:
    """Subtract the ``dark`` frame from target, reference and backlit frames (see subtract_background).

    Parameters
    ----------
    capture : xr.Dataset
        A ``tomography_capture`` store with a ``dark`` frame (row, col) [counts].

    Returns
    -------
    xr.Dataset
        A ``tomography_capture`` cube: the capture with ``dark`` subtracted from ``target``, ``reference`` and
        ``backlit`` (lazy; the same kind).

    References
    ----------
    Thesis §4.2.1 Distribution of the absorption coefficient and total absorption.
    """
    return subtract_background(capture, background="dark")


def _saturation_level(capture: xr.Dataset, saturation_level: float | None) -> float:
    if saturation_level is not None:
        return float(saturation_level)
    recorded = saturation_counts(capture.attrs)
    if recorded is not None:
        return recorded
    dtype = capture["target"].dtype
    if np.issubdtype(dtype, np.integer):
        return float(np.iinfo(dtype).max)
    raise StageError(Problem("cannot tell saturated pixels of float frames",
                             fix="set the capture's attr saturation_counts or the stage's saturation_level"))


def frame_flags(raw: np.ndarray, corrected: np.ndarray, *, saturation_level: float,
                min_signal: float) -> np.ndarray:
    """Per-pixel bits: SATURATED (raw ≥ level), NO_SIGNAL (corrected ≤ min_signal), NONFINITE (NaN/inf)."""
    nonfinite = ~np.isfinite(raw) | ~np.isfinite(corrected)
    saturated = (raw >= saturation_level) & ~nonfinite
    no_signal = (corrected <= min_signal) & ~nonfinite
    return (saturated * SATURATED + no_signal * NO_SIGNAL + nonfinite * NONFINITE).astype(np.uint8)


def _pair_kernel(target, reference, background, min_signal, on_object, *, subtracted: bool, level: float, dtype,
                 absorption: bool):
    """One tile, one pass: flags of both frames (and BACKGROUND where not ``on_object``), then log difference
    (or ratio) of the valid pixels.

    Fused by hand into a single NumPy function: the same arithmetic as ~15 separate lazy xarray
    operations ran at 60 Mpx/s on 2 cores, this kernel at 80 Mpx/s (benchmarks/absorption_throughput.py; the
    kernel alone: the background flag's silhouettes bring the stage to about 20 Mpx/s).
    ``min_signal`` is a scalar or per-frame thresholds broadcast against the tile.
    """
    def split(frames):
        frames = frames.astype(dtype, copy=False)
        return (frames + background, frames) if subtracted else (frames, frames - background)

    (raw_t, cor_t), (raw_r, cor_r) = split(target), split(reference)
    flags = (frame_flags(raw_t, cor_t, saturation_level=level, min_signal=min_signal)
             | (frame_flags(raw_r, cor_r, saturation_level=level, min_signal=min_signal) << 3)
             | np.where(on_object, 0, BACKGROUND)).astype(np.uint8)
    valid = flags == 0
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        value = np.log(cor_r) - np.log(cor_t) if absorption else cor_t / cor_r
    return np.where(valid, value, np.nan).astype(dtype, copy=False), flags


def _same_frames(capture: xr.Dataset, background: str | None, stage_name: str) -> None:
    """Target and reference must be frames of the same sweep; the background one frame of their size."""
    target, reference = capture["target"], capture["reference"]
    problems = []
    if target.dims != reference.dims or target.shape != reference.shape:
        problems.append(Problem(f"stage {stage_name!r}: reference has dims {reference.dims} and shape "
                                f"{reference.shape}, target {target.dims} and {target.shape}; they must match",
                                path="reference", fix="film the reference object at the same angles with the same "
                                "camera, and store both with dims (angle, row, col)"))
    if background is not None:
        frame = capture[background]
        pixels = {d: target.sizes[d] for d in target.dims if d in ("row", "col", "channel")}
        if set(frame.dims) - set(target.dims) or any(frame.sizes[d] != n for d, n in pixels.items() if d in frame.dims):
            problems.append(Problem(f"stage {stage_name!r}: background {background!r} has dims {frame.dims} and "
                                    f"shape {frame.shape}; the frames are {target.dims} {target.shape}",
                                    path=background, fix="use one frame of the same camera, dims (row, col)"))
    if problems:
        raise StageError(problems)


def frame_peak(frames: xr.DataArray, background: xr.DataArray, *, subtracted: bool, level: float) -> xr.DataArray:
    """Per frame, the brightest dark-subtracted pixel that is finite and below saturation (lazy)."""
    raw = frames + background if subtracted else frames
    corrected = frames if subtracted else frames - background
    pixel_dims = [d for d in frames.dims if d in ("row", "col", "channel")]
    return corrected.where((raw < level) & np.isfinite(corrected)).max(dim=pixel_dims)


#: floors of the usable shares (:mod:`selpath.pipeline.quality`): a beam rig's reference lights much of the frame
#: (86 % of pixels are valid in the demo), so under 0.1 % with signal is a wrong scale or a dark capture
SIGNAL_FLOOR, USABLE_FLOOR, DARK_FLOOR = 0.001, 0.05, 0.05


#: a backlit frame shows a silhouette when its lit pixels stand this many noise widths (the two classes' standard
#: deviations added) above the object's: a failed backlight (noise only) splits at about 1.3, a real one at hundreds,
#: a translucent object (a grape passing 30 % of the light) at about 3
SILHOUETTE_CONTRAST = 2.0


def _silhouette_share(lit: xr.DataArray, mask: xr.DataArray) -> xr.DataArray:
    """The usable share of backlit frames whose silhouette stands out of the noise (lazy): its two classes are
    both present and their means differ by :data:`SILHOUETTE_CONTRAST` times their spreads added."""
    pixels = ("row", "col")
    finite = np.isfinite(lit)
    values = lit.where(finite, 0.0).astype(np.float64)

    def moments(cls: xr.DataArray) -> tuple[xr.DataArray, xr.DataArray]:  # (mean, std); an empty class gives 0, 0
        n = np.maximum((cls & finite).sum(pixels), 1)
        mean = values.where(cls, 0.0).sum(pixels) / n
        return mean, np.sqrt(np.maximum((values**2).where(cls, 0.0).sum(pixels) / n - mean**2, 0.0))

    (inside, inside_std), (outside, outside_std) = moments(mask), moments(~mask)
    contrast = (outside - inside) / (outside_std + inside_std + 1e-30)
    share = ((contrast > SILHOUETTE_CONTRAST) & (mask.mean(pixels) > 0) & (mask.mean(pixels) < 1)).mean()
    return usable_share(share, floor=SILHOUETTE_FLOOR, what="backlit frames whose silhouette stands out of the noise "
                        f"(backlight more than {SILHOUETTE_CONTRAST:g} noise widths above the object)",
                        fix="the backlit frames show no backlight (a failed or unplugged backlight, or frames of "
                        "another camera): check them, or set flag_background: false to keep the background unflagged")


def _given_silhouettes(capture: xr.Dataset, silhouettes: xr.Dataset, stage_name: str, flag_background: bool,
                       threshold: float | None) -> xr.DataArray:
    """The ``silhouettes`` store's masks, checked against the capture's frames: one per angle, the same angles. (The
    silhouettes stage subtracts the capture's ``dark``: give it the raw capture, as the shipped workflows do.)"""
    problems = []
    if not flag_background:
        problems.append(Problem("silhouettes are wired in but flag_background is false",
                                fix="drop the silhouettes input, or set flag_background: true"))
    if threshold is not None:
        problems.append(Problem("silhouette_threshold is set, but the silhouettes wired in were thresholded by the "
                                "silhouettes stage", fix="set the threshold there (its `threshold`) and drop it here"))
    if "silhouette" not in silhouettes.data_vars:
        raise StageError([*problems, Problem(f"the silhouettes input has no `silhouette` variable (it has "
                                             f"{sorted(map(str, silhouettes.data_vars))})", path="silhouettes",
                                             fix="wire in the silhouettes stage's output")])
    mask = sorted_sweep(silhouettes, "angle", stage_name)["silhouette"]
    frames = capture["target"]
    if set(mask.dims) != set(frames.dims) or any(mask.sizes[d] != frames.sizes[d] for d in frames.dims):
        problems.append(Problem(f"the silhouettes are {dict(mask.sizes)}, the target frames {dict(frames.sizes)}",
                                path="silhouettes", fix="make the silhouettes from this capture"))
    elif not np.allclose(mask["angle"].values, frames["angle"].values):
        problems.append(Problem("the silhouettes' angles are not the capture's", path="silhouettes",
                                fix="make the silhouettes from this capture"))
    if problems:
        raise StageError(problems)
    return mask.astype(bool).drop_vars([c for c in mask.coords if c not in mask.dims]).assign_coords(
        {d: frames[d] for d in frames.dims if d in frames.coords})


def _checked_pair(capture: xr.Dataset, stage_name: str, saturation_level: float | None, min_signal: float,
                  min_signal_relative: float, *, absorption: bool, flag_background: bool = True,
                  silhouette_threshold: float | None = None, silhouettes: xr.Dataset | None = None
                  ) -> tuple[xr.DataArray, xr.DataArray, dict, dict]:
    """Absorption (or transmittance) and flags of dark-subtracted target and reference, lazily per tile, the
    usable shares of the input (:mod:`selpath.pipeline.quality`) and the object's shares (plain 0-d variables)."""
    capture = sorted_sweep(capture, "angle", stage_name)
    background_name = capture.attrs.get("background_subtracted") or ("dark" if "dark" in capture else None)
    require_variables(capture, ("target", "reference") + ((background_name,) if background_name else ()), stage_name)
    _same_frames(capture, background_name, stage_name)
    given = None if silhouettes is None else _given_silhouettes(capture, silhouettes, stage_name, flag_background,
                                                                silhouette_threshold)
    level = _saturation_level(capture, saturation_level)
    subtracted = bool(capture.attrs.get("background_subtracted"))
    background = capture[background_name] if background_name else xr.DataArray(0.0)
    dtype = np.result_type(_float_dtype(capture["target"]), _float_dtype(capture["reference"]))
    threshold = xr.DataArray(float(min_signal))
    if min_signal_relative > 0:
        peak = frame_peak(capture["reference"].astype(dtype), background, subtracted=subtracted, level=level)
        threshold = np.maximum(threshold, min_signal_relative * peak.fillna(np.inf))
    object_mask = xr.DataArray(True)  # without backlit frames (or flag_background off) every pixel is the object's
    backlit = capture["backlit"] if "backlit" in capture else None
    mask = given
    if given is None and flag_background and backlit is not None:
        if set(backlit.dims) != set(capture["target"].dims):
            raise StageError(Problem(f"stage {stage_name!r}: backlit has dims {backlit.dims}, target "
                                     f"{capture['target'].dims}; they must match to flag the background",
                                     path="backlit", fix="film a backlit frame at every angle of the target, or set "
                                     "flag_background: false"))
        mask = object_masks(backlit, None if subtracted or not background_name else background,
                            threshold=silhouette_threshold)
    if mask is not None:
        object_mask = mask
        if backlit is not None:
            # backlit frames were dark-subtracted with the others (subtract_background's default variables); a pixel
            # whose backlit value is missing (NaN, inf: e.g. a frame never filmed) is not known to be off the object
            dark = None if subtracted or not background_name else background
            object_mask = mask | ~np.isfinite(backlit)
            silhouette_share = _silhouette_share(backlit if dark is None else backlit - dark, mask)
    value, flags = xr.apply_ufunc(
        _pair_kernel, capture["target"], capture["reference"], background, threshold, object_mask,
        kwargs=dict(subtracted=subtracted, level=level, dtype=dtype, absorption=absorption),
        output_core_dims=[[], []], dask="parallelized", output_dtypes=[dtype, np.uint8],
    )
    value = value.transpose(*capture["target"].dims).drop_attrs(deep=False)  # (apply_ufunc copied the frames' attrs)
    flags = flags.transpose(*capture["target"].dims).drop_attrs(deep=False)
    flags.attrs.update(flag_masks=FLAG_MASKS, flag_meanings=FLAG_MEANINGS)
    attrs = {k: v for k, v in capture.attrs.items() if k != "selpath_kind"}
    attrs.pop("saturation_level", None)  # the old name of saturation_counts
    attrs.update(saturation_counts=level, min_signal=min_signal, min_signal_relative=min_signal_relative,
                 background_flagged=int(object_mask.ndim > 0))  # 1: pixels off the object carry BACKGROUND
    if object_mask.ndim and silhouette_threshold is not None:
        attrs["silhouette_threshold"] = float(silhouette_threshold)
    on_object = (flags & BACKGROUND) == 0
    objects = np.maximum(on_object.sum(), 1)
    lit = on_object & (((flags >> 3) & 7) == 0)  # on the object, the reference is finite, unsaturated, above min_signal
    shares = {
        "signal_fraction": usable_share(
            lit.sum() / objects, floor=SIGNAL_FLOOR, what="reference pixels with usable signal (finite, below "
            "the clip level saturation_counts, above min_signal) among the object's pixels (not flagged background)",
            fix="check the frames' scale: min_signal is in counts above dark (for data on another scale set "
            "min_signal_relative, e.g. 0.01 of each frame's brightest reference pixel); check the dark frame, "
            "the clip level (attr saturation_counts, or the stage's saturation_level) and NaN frames; if the "
            "backlit frames show no object, set flag_background: false"),
        "usable_fraction": usable_share(
            (flags == 0).sum() / np.maximum(lit.sum(), 1), floor=USABLE_FLOOR,
            what="lit reference pixels on the object whose target is usable too (finite, below saturation_counts, "
            "above min_signal)",
            fix="most target frames are saturated, NaN or dark where the reference is lit: check them and the clip "
            "level (attr saturation_counts, or the stage's saturation_level)"),
        "object_valid_fraction": ((flags == 0).sum() / objects).astype(np.float64),
        "background_fraction": (~on_object).mean().astype(np.float64),
    }
    if object_mask.ndim and "backlit" in capture:
        shares["silhouette_fraction"] = silhouette_share
    if background_name and not subtracted:
        shares["dark_fraction"] = usable_share(
            (capture[background_name] >= 0).mean(), floor=DARK_FLOOR,
            what=f"{background_name} pixels at or above 0 counts",
            fix=f"{background_name!r} must be the sensor's offset (counts ≥ 0) in the frames' units: is it already "
            "subtracted from the frames, or from another camera?")
    return value, flags, attrs, shares


@stage("normalise_reference", kind=TRANSMITTANCE)
@pair_docs
def normalise_reference(capture: xr.Dataset, silhouettes: xr.Dataset | None = None, /, *,
                        saturation_level: Positive | None = None, min_signal: NonNegative = 0.0,
                        min_signal_relative: Fraction = 0.0, flag_background: bool = True,
                        silhouette_threshold: Positive | None = None) -> xr.Dataset:
    """Transmittance I_target / I_reference per pixel (dark-subtracted), with flags for unusable pixels.

    {pair}

    Returns
    -------
    xr.Dataset
        A ``transmittance`` cube: ``transmittance`` I_target / I_reference over (angle, row, col) [1] (lazy), NaN where
        ``flags`` (CF flag bits) says why; {shares}

    References
    ----------
    Thesis §4.2.1 Distribution of the absorption coefficient and total absorption.
    """
    value, flags, attrs, shares = _checked_pair(capture, "normalise_reference", saturation_level, min_signal,
                                                min_signal_relative, absorption=False,
                                                flag_background=flag_background,
                                                silhouette_threshold=silhouette_threshold,
                                                silhouettes=silhouettes)
    return TRANSMITTANCE.label(xr.Dataset({"transmittance": value, "flags": flags, **shares}, attrs=attrs))


@stage("absorption", kind=ABSORPTION)
@pair_docs
def absorption(capture: xr.Dataset, silhouettes: xr.Dataset | None = None, /, *,
               saturation_level: Positive | None = None, min_signal: NonNegative = 0.0,
               min_signal_relative: Fraction = 0.0, flag_background: bool = True,
               silhouette_threshold: Positive | None = None) -> xr.Dataset:
    """Total absorption A = log I_reference − log I_target per pixel (thesis Eq. 3), with flags.

    Computed as a difference of logs, never as the log of a ratio, so float32 frames spanning
    1e-8…1e8 cannot under- or overflow.

    {pair}

    Returns
    -------
    xr.Dataset
        An ``absorption`` cube: ``absorption`` A over (angle, row, col) [1] (lazy), NaN where ``flags`` (CF flag bits)
        says why; {shares}

    References
    ----------
    Thesis §4.2.1 Distribution of the absorption coefficient and total absorption.
    """
    value, flags, attrs, shares = _checked_pair(capture, "absorption", saturation_level, min_signal,
                                                min_signal_relative, absorption=True,
                                                flag_background=flag_background,
                                                silhouette_threshold=silhouette_threshold,
                                                silhouettes=silhouettes)
    return ABSORPTION.label(xr.Dataset({"absorption": value, "flags": flags, **shares}, attrs=attrs))
