"""Material recognition from delay profiles (thesis §5.4.9, Figs. 51–52).

A pixel's **delay profile** is its intensity over the sync delay t_d: light that scattered below the surface before
leaving through the pixel entered at other epipolar planes, so it arrives at other delays, and the more translucent
the material the broader the profile. Divided by its area (the sum over delays) a profile no longer depends on the
albedo or the light's power, only on how the material spreads light; materials that look alike under room light
(white milk, soap, toothpaste) then differ. Profiles come from a delay sweep at one exposure (the thesis's) or
from a demultiplexed plane-to-ray transport, whose offsets o are delays o/v_p.

A support vector machine with a radial (Gaussian) kernel, in a scikit-learn ``Pipeline`` after standardising each
delay, is trained on labelled pixels of one capture (C and γ by stratified cross-validation) and classifies the
pixels of another. A classifier of the same kind on the area alone (the regular image's brightness: this rig is
monochrome, so brightness is all its colour is) is trained beside it as the baseline that shows why colour fails.

The trained pair is stored in the classifier's store as a skops archive (``model``, bytes): skops rather than
joblib because loading a pickle runs whatever code it names, while skops loads only the types it trusts
(scikit-learn's; skops ≥ 0.12, which closed a hole in that check), so a classifier store received from someone else
is safe to open. The archive's sha256 is stored beside it: it catches corruption, not tampering (whoever edits the
model can edit the hash). The store's provenance (workflow, inputs, settings) is the model's.
"""

from __future__ import annotations

import hashlib
from typing import Annotated

import dask
import numpy as np
import pydantic
import xarray as xr

from selpath.pipeline.constraints import Count, Index, Positive, StorePath
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import FLAGS, TIME_UNITS, CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.procam import _material_features as features
from selpath.stages.procam._labels import Labels, label_identity, label_map, label_precheck

#: bits of the profiles' ``flags``
SATURATED, NONFINITE, NO_LIGHT = 1, 2, 4
FLAG_MASKS = [SATURATED, NONFINITE, NO_LIGHT]
FLAG_MEANINGS = "saturated nonfinite no_light"
#: below this share of pixels with a usable profile the profiles mean nothing
USABLE_FLOOR = 0.01

#: the dims of one frame
FRAME = ("row", "col")
DELAY_PROFILES = CubeKind(
    name="delay_profiles",
    description="per-pixel delay profiles normalised by their area, so albedo cancels (§5.4.9)",
    variables={"profile": Variable(("delay", *FRAME), units="1", long_name="delay profile / its area"),
               "area": Variable(FRAME, units="counts", long_name="area of the delay profile (the regular image)"),
               "rms_delay": Variable(FRAME, False, units="us", long_name="RMS delay of the profile about t_d = 0"),
               "flags": Variable(FRAME, **FLAGS)},
    coord_units={"delay": TIME_UNITS},
    attrs={"source_kind": "the kind the profiles were made from: a capture or a transport"},
)
MATERIAL_CLASSIFIER = CubeKind(
    name="material_classifier",
    description="an RBF-kernel SVM on delay profiles and its brightness-only baseline, a skops archive",
    variables={"model": Variable(("byte",), units=None,
                                 long_name="the profile and brightness classifiers, a skops archive"),
               "mean_profile": Variable(("material", "delay"), units="1", long_name="mean training profile"),
               "reference": Variable(("sample", "delay"), False, units="1",
                                     long_name="the training pixels' standardised profiles (novelty's neighbours)"),
               "window_cv_accuracy": Variable(("window",), False, units="1",
                                              long_name="cross-validated accuracy per window of delay")},
    coord_units={"delay": TIME_UNITS, "window": TIME_UNITS},
    attrs={"source_kind": "the kind of the training profiles' source",
           "svm_C": "the chosen SVM regularisation C", "svm_gamma": "the chosen RBF width γ"},
)
#: the default windows of delay to try, in shares of the sweep's largest |t_d|
WINDOW_FRACTIONS = (0.25, 0.5, 1.0)
#: the default grids of the cross-validation: C, and γ in units of 1/(number of delays) (scikit-learn's "scale"
#: after standardising)
C_GRID, GAMMA_GRID = (1.0, 10.0, 100.0), (0.1, 0.3, 1.0)

Grid = Annotated[tuple[Positive, ...], pydantic.Field(min_length=1)]


def profile_frames(source: xr.Dataset, exposure: float | None) -> tuple[xr.DataArray, xr.DataArray, dict]:
    """The source's frames over ``delay`` [counts above dark, µs], the pixels seen saturated, and what it was."""
    if "transport" in source.data_vars and "offset" in source["transport"].dims:
        speed = source.attrs.get("scan_speed_px_per_us")
        if not speed:
            raise StageError(Problem("the transport has no scan_speed_px_per_us: its offsets cannot be delays",
                                     fix="wire in the output of demux_plane_to_ray"))
        t = source["transport"].drop_vars("sync_delay", errors="ignore")
        # the delay from the direct plane, o / v_p: its sync delay less −t_o (offset 0 is the direct light)
        frames = t.assign_coords(offset=t["offset"] / float(speed)).rename(offset="delay")
        censored = (source["censored"] if "censored" in source.data_vars
                    else xr.zeros_like(t.isel(offset=0), dtype=bool))
        return frames, censored, {"source_kind": "plane_to_ray_transport"}
    if "image" in source.data_vars and set(source["image"].dims) == {"delay", "exposure", "row", "col"}:
        image = source["image"]
        exposures = source["exposure"].values
        if exposure is None and len(exposures) > 1:
            raise StageError(Problem(f"the capture has {len(exposures)} exposures {exposures.tolist()} µs; a delay "
                                     "profile is a sweep at one", fix="give exposure: one of them"))
        exposure = float(exposures[0]) if exposure is None else float(exposure)
        if not np.any(np.isclose(exposures, exposure)):
            raise StageError(Problem(f"exposure {exposure:g} µs is not in the capture",
                                     fix=f"choose one of {exposures.tolist()}"))
        frames = image.sel(exposure=exposure, method="nearest").drop_vars("exposure")
        level = float(source.attrs.get("saturation_counts", np.inf))
        dark = float(source.attrs.get("dark_level_counts", 0.0))
        return ((frames.astype(np.float32) - dark), (frames >= level).any("delay"),
                {"source_kind": "plane_to_ray_capture", "exposure_us": exposure})
    raise StageError(Problem(f"neither a plane-to-ray capture nor a plane-to-ray transport: variables "
                             f"{sorted(map(str, source.data_vars))}",
                             fix="wire in acquire_plane_to_ray's capture or demux_plane_to_ray's transport"))


@stage("delay_profiles", kind=DELAY_PROFILES)
def delay_profiles(source: xr.Dataset, /, *, exposure: Positive | None = None, fold: bool = False) -> xr.Dataset:
    """Per-pixel delay profiles normalised by their area, so albedo cancels (§5.4.9, Fig. 51b).

    Parameters
    ----------
    source : xr.Dataset
        A ``plane_to_ray_capture`` (``image`` over delay, exposure, row, col [counts]; attrs ``dark_level_counts``
        and ``saturation_counts`` where known) or a ``plane_to_ray_transport`` (``transport`` over offset, row,
        col, attr ``scan_speed_px_per_us``: offset o is delay o / v_p).
    exposure : float or None
        The capture's exposure whose delay sweep is the profile [µs]; None: the capture's only one.
    fold : bool
        Fold the profile about the direct light (p(t) + p(−t), over t ≥ 0; the delays must be symmetric about 0): a
        rectified rig lights rows s ± o alike in a homogeneous medium, so the two halves measure the same light and
        their sum halves the noise's variance (``selpath.stages.procam._material_features``). A capture's direct
        light must arrive at t_d = 0 (a sync offset t_o of 0; one recording another ``sync_offset_us`` is refused);
        a transport's is offset 0 whatever t_o.

    Returns
    -------
    xr.Dataset
        A ``delay_profiles`` cube: ``profile`` over (delay, row, col) [1, summing to 1 over delay], ``area`` [counts:
        the profile's sum, the regular image], ``rms_delay`` [µs: √(Σ profile·t_d²), the profile's spread about t_d = 0]
        and ``flags`` (saturated, nonfinite, no_light: area ≤ 0); flagged pixels' profiles are NaN.

    Raises
    ------
    StageError
        When under 1 % of the pixels have a usable profile.

    References
    ----------
    Thesis §5.4.9 Material Recognition of Subsurface Scattering.
    """
    frames, saturated, what = profile_frames(source, exposure)
    if fold:
        if what["source_kind"] == "plane_to_ray_capture" and float(source.attrs.get("sync_offset_us", 0.0)):
            raise StageError(Problem(f"fold: the capture's direct light arrives at t_d = −t_o = "
                                     f"{-float(source.attrs['sync_offset_us']):g} µs, not 0",
                                     fix="fold the profiles of its demultiplexed transport (offset 0 is the direct "
                                         "plane), or fold: false"))
        frames = _folded(frames)
        what = what | {"folded": True}
    frames = frames.chunk({"delay": -1}) if frames.chunks else frames
    area = frames.sum("delay")
    nonfinite = (~np.isfinite(frames)).any("delay")
    flags = (saturated.astype(np.uint8) * SATURATED) | (nonfinite.astype(np.uint8) * NONFINITE) | (
        (~(area > 0) & ~nonfinite).astype(np.uint8) * NO_LIGHT)
    profile = (frames / area.where(area > 0)).where(flags == 0)  # no 0/0 computed where there is no light
    delay = frames["delay"]
    spread = np.sqrt(np.maximum((profile * delay**2).sum("delay", skipna=False), 0.0))
    keep = {k: v for k, v in source.attrs.items() if k != "selpath_kind"}
    return DELAY_PROFILES.label(xr.Dataset(
        {"profile": profile.drop_attrs(deep=False), "area": area.where(~nonfinite).drop_attrs(deep=False),
         "rms_delay": spread.drop_attrs(deep=False),
         "flags": flags.drop_attrs(deep=False).assign_attrs(flag_masks=FLAG_MASKS, flag_meanings=FLAG_MEANINGS),
         "usable_fraction": usable_share(
             (flags == 0).mean(), floor=USABLE_FLOOR,
             what="pixels with a usable delay profile (light, finite, unsaturated)",
             fix="check that the projector lit the scene and the frames are not all dark, saturated or missing")},
        coords={"delay": ("delay", delay.values.astype(float), {"units": "us", "long_name": (
            "sync delay t_d" if what["source_kind"] == "plane_to_ray_capture"
            else "delay from the direct plane, o / v_p (the sync delay + t_o)")})},
        attrs=keep | what))


def _folded(frames: xr.DataArray) -> xr.DataArray:
    """Frames over delay folded onto t_d ≥ 0, p(t) + p(−t) (p(0) alone), lazily."""
    try:
        zero = features.zero_of(frames["delay"].values)
    except ValueError as exc:
        raise StageError(Problem(f"fold: {exc}", fix="sweep delays symmetric about 0, or fold: false")) from None
    later = frames.isel(delay=slice(zero, None))
    earlier = frames.isel(delay=slice(zero, None, -1) if zero else slice(0, 1)).assign_coords(
        delay=later["delay"].values)
    first = xr.DataArray((np.arange(later.sizes["delay"]) > 0).astype(frames.dtype), dims="delay")
    return later + earlier * first


# -- training ----------------------------------------------------------------------------------------------------


def _pixels(profiles: xr.Dataset, index: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Profiles (pixels, delays) and areas (pixels,) of flat pixel ``index``, read only where they lie."""
    flat = profiles["profile"].transpose("delay", "row", "col").data.reshape(profiles.sizes["delay"], -1)
    area = profiles["area"].data.reshape(-1)
    if dask.is_dask_collection(flat):
        flat, area = dask.compute(flat[:, index], area[index])
    else:
        flat, area = flat[:, index], area[index]
    return np.asarray(flat, np.float64).T, np.asarray(area, np.float64)


def _fit(values: np.ndarray, truth: np.ndarray, grid: dict, folds: int, blocks: np.ndarray, seed: int):
    """The RBF SVM (after standardising) whose C and γ score best over ``folds`` folds of spatial blocks."""
    from sklearn.model_selection import GridSearchCV
    from sklearn.pipeline import Pipeline
    from sklearn.preprocessing import StandardScaler
    from sklearn.svm import SVC

    search = GridSearchCV(Pipeline([("scale", StandardScaler()), ("svm", SVC(kernel="rbf"))]), grid,
                          cv=features.block_folds(folds, seed))
    search.fit(values, truth, groups=blocks)
    return search


def pooled_profiles(profiles: xr.Dataset, regions: np.ndarray, window: int) -> tuple[np.ndarray, np.ndarray]:
    """Profiles (delay, row, col) and areas pooled over ``window`` within ``regions``
    (:func:`selpath.stages.procam._material_features.pool` on the frames, profile × area, then normalised again)."""
    profile = np.asarray(profiles["profile"].transpose("delay", "row", "col").values, np.float64)
    area = np.asarray(profiles["area"].values, np.float64)
    frames = features.pool(profile * area[None], regions, window)
    total = frames.sum(axis=0)
    return frames / np.where(total > 0, total, np.nan)[None], total


def _training_values(profiles: xr.Dataset, codes: np.ndarray, flags: np.ndarray, index: np.ndarray,
                     pool_px: int) -> tuple[np.ndarray, np.ndarray]:
    """The training pixels' profiles (pixels, delays) and areas, pooled within their labels with ``pool_px`` > 1."""
    if pool_px <= 1:
        return _pixels(profiles, index)
    profile, total = pooled_profiles(profiles, np.where((codes > 0) & (flags == 0), codes, -1), pool_px)
    return profile.reshape(profile.shape[0], -1)[:, index].T, total.reshape(-1)[index]


def window_profiles(profiles: xr.Dataset, window_us: float | None) -> xr.Dataset:
    """``profiles`` kept over the delays |t_d| ≤ ``window_us`` [µs] and normalised again over them (area their sum;
    a pixel left without light flagged no_light); None, or a window wider than the sweep: unchanged. Lazy."""
    keep = features.kept_delays(profiles["delay"].values, window_us)
    if keep.all():
        return profiles
    frames = profiles["profile"].isel(delay=keep) * profiles["area"]
    area = frames.sum("delay")
    dark = (profiles["flags"] == 0) & ~(area > 0)
    flags = (profiles["flags"] | (dark.astype(np.uint8) * NO_LIGHT)).assign_attrs(profiles["flags"].attrs)
    return profiles.drop_vars(["rms_delay"], errors="ignore").isel(delay=keep).assign(
        profile=(frames / area.where(area > 0)).where(flags == 0), area=area.where(flags == 0, profiles["area"]),
        flags=flags).assign_attrs(window_us=float(window_us))


@stage("train_material_classifier", kind=MATERIAL_CLASSIFIER, precheck=label_precheck, identity=label_identity)
def train_material_classifier(profiles: xr.Dataset, /, *, labels: Labels = "scene",
                              label_image: StorePath = "", classes: tuple[str, ...] | None = None,
                              samples_per_class: Count = 1000,
                              folds: Annotated[int, pydantic.Field(ge=2, le=20)] = 5, seed: Index = 0,
                              c_grid: Grid = C_GRID, gamma_grid: Grid = GAMMA_GRID,
                              flag_rate: Annotated[float, pydantic.Field(gt=0.0, lt=0.5)] = 0.01,
                              pool_px: Count = 1, smooth_px: Index = 0,
                              window_grid_us: tuple[Positive, ...] | None = None) -> xr.Dataset:
    """Train an RBF-kernel SVM on labelled pixels' delay profiles, and the brightness-only baseline (§5.4.9).

    Hyper-parameters by cross-validation over ``folds`` folds of spatial blocks (2 × folds bands of rows over the
    training pixels' span: neighbouring pixels share light and noise, so random folds would leak).

    Parameters
    ----------
    profiles : xr.Dataset
        A ``delay_profiles`` store (``delay_profiles``).
    labels : str
        ``scene``: the objects of the simulated scene the capture records (attr ``simulated_scene``), by name;
        ``image``: the label image ``label_image``.
    label_image : str
        Path (relative to the workflow) of an integer label image (.npy, .png, .tif) of the frame's size: 0
        unlabelled, codes 1 … n named by ``classes``.
    classes : tuple of str or None
        The names of a label image's codes 1, 2, …; None with ``labels: scene``.
    samples_per_class : int
        Training pixels drawn per class (at most; all when a class has fewer) [1].
    folds : int
        Folds of the cross-validation over spatial blocks [1].
    seed : int
        Seed of the pixel draw and of the folds' shuffle.
    c_grid : tuple of float
        SVM regularisation C to try [1].
    gamma_grid : tuple of float
        RBF width γ to try, in units of 1/(number of delays) [1]: 1 is scikit-learn's ``gamma="scale"`` on
        standardised profiles (when no delay is constant over the training pixels).
    flag_rate : float
        The share of the trained materials' pixels (all together) the classifier may flag as unlike every trained
        class, on data like the training capture's [1]: a pixel is flagged when its mean distance to its 5 nearest
        training pixels (the SVM's standardised space) exceeds the (1 − flag_rate) quantile of the training pixels'
        own, each scored out of fold (split conformal; ``selpath.stages.procam._material_features``).
    pool_px : int
        Pool each labelled pixel's frames with its neighbours of the same label over a window of this many pixels
        a side before normalising (1: none) [px]; ``classify_materials`` then pools alike, within superpixels.
    smooth_px : int
        ``classify_materials`` filters the SVM's class probabilities with a guided filter of this radius (the
        regular image's log as the guide, so it stops at edges in brightness) before taking each pixel's most
        probable class (0: none, the SVM's own decision) [px]. Above 0 the model also holds the chosen SVM's
        class probabilities (Platt's sigmoids fitted on out-of-fold decisions over the same spatial blocks,
        scikit-learn's ``CalibratedClassifierCV``). On the materials dev set 4 px was chosen by
        cross-validation over row bands of the training placement (docs/results.md).
    window_grid_us : tuple of float or None
        The windows of delay to try: a profile keeps the delays |t_d| ≤ the window, normalised over them [µs].
        The widest window whose cross-validated accuracy lies within one standard error of the best window's is
        kept (a narrower window must earn its place: on the materials dev set the best-scoring one, better by
        0.002, lost 11 points on the other placement; docs/results.md) and ``classify_materials`` applies it.
        None: a quarter, half and all of the sweep's largest |t_d|. Each window costs one more cross-validated
        search.

    Returns
    -------
    xr.Dataset
        A ``material_classifier`` cube: the ``model`` (a skops archive, bytes), the mean and spread of each class's
        profiles (Fig. 51b), the pixels used and both classifiers' cross-validated accuracy; attrs the chosen C and γ
        and what the model was trained on.

    Raises
    ------
    StageError
        Fewer than 2 classes, a class with fewer usable labelled pixels than folds, no labelled pixel.

    References
    ----------
    Thesis §5.4.9 Material Recognition of Subsurface Scattering.
    """
    import sklearn
    import skops.io

    require_variables(profiles, ("profile", "area", "flags"), "train_material_classifier")
    codes, names = label_map(profiles, labels, label_image, classes, "profiles")
    reach = float(np.abs(profiles["delay"].values).max())
    windows = sorted({min(float(w), reach) for w in (window_grid_us or [f * reach for f in WINDOW_FRACTIONS])})
    keeps = [features.kept_delays(profiles["delay"].values, w) for w in windows]
    # usable in every window: the windows nest, so a pixel dark in one is dark in the narrowest
    flags = np.asarray(window_profiles(profiles, windows[0])["flags"].values)
    index = features.training_sample(codes, flags, names, samples_per_class, folds, seed)
    blocks = features.row_blocks(index // profiles.sizes["col"], features.BLOCKS_PER_FOLD * folds)
    if np.unique(blocks).size < folds:
        raise StageError(Problem(f"the training pixels span {np.unique(blocks).size} distinct bands of rows; "
                                 f"cross-validation over {folds} folds of bands needs as many",
                                 fix="label pixels over more rows, or lower folds"))
    # classes are indexed among those with training pixels (a label code no pixel carries is not a class): the
    # stored ``material`` coordinate and the SVMs' outputs then agree
    present, truth = np.unique(codes.ravel()[index] - 1, return_inverse=True)
    splits = list(features.block_folds(folds, seed).split(index, truth, groups=blocks)) if smooth_px > 0 else []
    if smooth_px > 0:  # a fold without a class would calibrate that class on placeholders (or fail inside sklearn)
        lacking = sorted({names[present[k]] for fit, _ in splits for k in set(range(present.size)) - set(truth[fit])})
        if lacking:
            raise StageError(Problem(f"smooth_px: calibrating the class probabilities needs every class in every "
                                     f"fold's training bands; {lacking} lie in too few bands of rows",
                                     fix="label them over more rows, lower folds, or smooth_px: 0"))
    whole, whole_area = _training_values(profiles, codes, flags, index, pool_px)  # read once, cut per window
    fits = []
    for keep in keeps:  # the window by the same cross-validation (pooling and cutting delays commute)
        values, area = whole, whole_area
        if not keep.all():
            frames = whole[:, keep] * whole_area[:, None]
            area = frames.sum(1)
            values = frames / area[:, None]
        fits.append((values, area, _fit(values, truth, {
            "svm__C": list(c_grid), "svm__gamma": [g / values.shape[1] for g in gamma_grid]}, folds, blocks, seed)))
    scores = [search.best_score_ for *_, search in fits]
    chosen = features.widest_within_error([search.cv_results_ for *_, search in fits],
                                          [search.best_index_ for *_, search in fits], folds)
    window, (values, area, search) = windows[chosen], fits[chosen]
    n_delay = values.shape[1]
    baseline = _fit(area[:, None], truth, {"svm__C": list(c_grid), "svm__gamma": list(gamma_grid)}, folds, blocks,
                    seed)
    models = {"profile": search.best_estimator_, "brightness": baseline.best_estimator_}
    if smooth_px > 0:  # class probabilities for the guided filter: Platt's sigmoids fitted out of fold, over blocks
        from sklearn.base import clone
        from sklearn.calibration import CalibratedClassifierCV

        models["probability"] = CalibratedClassifierCV(clone(search.best_estimator_), method="sigmoid",
                                                       ensemble=False, cv=splits).fit(values, truth)
    model = skops.io.dumps(models)
    kept = [names[k] for k in present]
    standard = search.best_estimator_.named_steps["scale"].transform(values)
    centre = np.stack([standard[truth == k].mean(0) for k in range(present.size)])
    novelty = features.novelty_threshold(standard, truth, blocks, folds, seed, flag_rate)
    mean = np.stack([values[truth == k].mean(0) for k in range(present.size)])
    spread = np.stack([values[truth == k].std(0) for k in range(present.size)])
    keep = {k: v for k, v in profiles.attrs.items() if k not in ("selpath_kind", "simulated_scene")}
    scene = profiles.attrs.get("simulated_scene", {})
    delay = profiles["delay"][keeps[chosen]]
    material = ("material", kept, {"long_name": "material class"})
    return MATERIAL_CLASSIFIER.label(xr.Dataset(
        {"model": ("byte", np.frombuffer(model, np.uint8),
                   {"format": "skops", "sha256": hashlib.sha256(model).hexdigest()}),
         "mean_profile": (("material", "delay"), mean),
         "profile_spread": (("material", "delay"), spread,
                            {"units": "1", "long_name": "standard deviation of the training profiles"}),
         "training_pixels": ("material", np.bincount(truth, minlength=present.size),
                             {"units": "1", "long_name": "training pixels"}),
         "class_centre": (("material", "delay"), centre,
                          {"units": "1", "long_name": "mean standardised training profile (the SVM's scaling)"}),
         "reference": (("sample", "delay"), standard.astype(np.float32)),
         "cv_accuracy": ((), search.best_score_, {"units": "1", "long_name": "cross-validated accuracy, profiles"}),
         "brightness_cv_accuracy": ((), baseline.best_score_,
                                    {"units": "1", "long_name": "cross-validated accuracy, brightness only"}),
         "window_cv_accuracy": ("window", scores, {"units": "1", "long_name": "cross-validated accuracy per window"})},
        coords={"material": material, "delay": ("delay", delay.values, dict(delay.attrs)),
                "window": ("window", windows, {"units": "us", "long_name": "window of delay tried, |t_d| ≤ it"})},
        attrs=keep | {"window_us": window, "svm_C": float(search.best_params_["svm__C"]),
                      "svm_gamma": float(search.best_params_["svm__gamma"]) * n_delay,
                      "svm_gamma_units": "1/(number of delays)",
                      "brightness_C": float(baseline.best_params_["svm__C"]),
                      "brightness_gamma": float(baseline.best_params_["svm__gamma"]),
                      "folds": folds, "seed": seed, "samples_per_class": samples_per_class,
                      "novelty_distance": novelty, "flag_rate": flag_rate, "pool_px": pool_px,
                      "smooth_px": smooth_px,
                      "labels": label_image if labels == "image" else labels, "training_scene": scene.get("scene", ""),
                      "scikit_learn_version": sklearn.__version__, "skops_version": skops.__version__}))
