"""Classifying a capture's pixels by material with a trained classifier (thesis §5.4.9, Figs. 51c, 52), and the
accuracy against a label image or the simulated scene's objects.

The classifier (``train_material_classifier``, :mod:`selpath.stages.procam.materials`) is a skops archive: loaded
here with skops's trusted types only. With ``pool_px`` the profiles are pooled within superpixels first
(:mod:`selpath.stages.procam._material_features`); a pixel unlike every training pixel is flagged
``unlike_training``.
"""

from __future__ import annotations

import hashlib

import numpy as np
import xarray as xr

from selpath.pipeline.constraints import Count, Index, StorePath
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import CubeKind, Variable
from selpath.pipeline.quality import usable_share
from selpath.pipeline.registry import stage
from selpath.stages._common import require_variables
from selpath.stages.procam import _material_features as features
from selpath.stages.procam._labels import Labels, label_identity, label_map, label_precheck
from selpath.stages.procam.materials import FRAME, pooled_profiles, window_profiles

_CLASS_INDEX = "class index into material (−1: no usable profile)"
MATERIAL_CLASSIFICATION = CubeKind(
    name="material_classification",
    description="pixels classified by delay profile and by brightness, and their accuracy (Figs. 51–52)",
    variables={"label": Variable(FRAME, units=None, long_name=_CLASS_INDEX),
               "brightness_label": Variable(FRAME, units=None, long_name=_CLASS_INDEX + ", brightness only"),
               "object": Variable(FRAME, required=False, units=None,
                                  long_name="object code (0: background, −1: no usable profile), with objects"),
               "accuracy": Variable(("material",), required=False, units="1",
                                    long_name="share of the class's pixels classified right")},
)
#: scikit-learn's own types a calibrated classifier holds, which skops 0.16 does not list as trusted (plain
#: estimators, their parameters as arrays: nothing that runs code on load)
ALSO_TRUSTED = ("sklearn.calibration._CalibratedClassifier", "sklearn.calibration._SigmoidCalibration")
#: how far from every object's core the background's seeds lie, with ``objects`` [px] (chosen on the materials dev
#: set's training placement: docs/results.md)
OBJECT_MARGIN_PX = 4
#: the normal quantile of the accuracies' 95 % confidence intervals
Z95 = 1.959963984540054


def load_classifiers(classifier: xr.Dataset) -> dict:
    """The profile and brightness classifiers (and with ``smooth_px`` the calibrated one) of a ``material_classifier``
    store, loaded with skops's trusted types and :data:`ALSO_TRUSTED` only (a store that names any other type is
    refused)."""
    import skops.io

    data = np.asarray(classifier["model"].values, np.uint8).tobytes()
    if hashlib.sha256(data).hexdigest() != classifier["model"].attrs.get("sha256"):
        raise StageError(Problem("the classifier's model does not match its recorded sha256: the store is "
                                 "corrupt or was edited", where="classifier", fix="train it again"))
    untrusted = sorted(set(skops.io.get_untrusted_types(data=data)) - set(ALSO_TRUSTED))
    if untrusted:
        raise StageError(Problem(f"the classifier's model names types skops does not trust: {untrusted}",
                                 where="classifier", fix="train the classifier with train_material_classifier"))
    return skops.io.loads(data, trusted=list(ALSO_TRUSTED))


def _predict(model, features: np.ndarray) -> np.ndarray:
    """Class index per pixel of (…, features), −1 where a feature is NaN."""
    flat = features.reshape(-1, features.shape[-1])
    ok = np.isfinite(flat).all(axis=1)
    out = np.full(flat.shape[0], -1, np.int16)
    if ok.any():
        out[ok] = model.predict(flat[ok])
    return out.reshape(features.shape[:-1])


def _smoothed_labels(model, profile: xr.DataArray, area: np.ndarray, usable: np.ndarray, radius: int) -> np.ndarray:
    """Class index per pixel: the most probable class after the class probabilities of ``profile`` (row, col,
    delay) are guided-filtered over ``radius`` px (guide: log ``area``); −1 where the profile is not finite."""
    values = np.asarray(profile.transpose("row", "col", "delay").values, np.float64)
    flat = values.reshape(-1, values.shape[-1])
    ok = np.isfinite(flat).all(axis=1)
    scores = np.zeros((flat.shape[0], len(model.classes_)), np.float32)
    if ok.any():
        scores[ok] = model.predict_proba(flat[ok])
    ok = ok.reshape(values.shape[:2])
    smooth = features.guided_smooth(scores.reshape(*values.shape[:2], -1), area, ok & usable, radius)
    return np.where(ok, np.asarray(model.classes_)[smooth.argmax(axis=-1)], -1).astype(np.int16)


def _distance(model, values: np.ndarray, measure) -> np.ndarray:
    """``measure`` of each pixel's profile standardised as the SVM's pipeline does (NaN where a value is NaN)."""
    flat = values.reshape(-1, values.shape[-1])
    ok = np.isfinite(flat).all(axis=1)
    out = np.full(flat.shape[0], np.nan, np.float32)
    if ok.any():
        out[ok] = measure(model.named_steps["scale"].transform(flat[ok]))
    return out.reshape(values.shape[:-1])


def _novelty_measure(classifier: xr.Dataset):
    """(distance of standardised profiles, its long name, the flag's long name) of the classifier's novelty rule:
    the mean distance to the 5 nearest training pixels (#55), or, for a classifier trained before, the distance to
    the nearest class mean; None for a classifier with neither."""
    if "novelty_distance" not in classifier.attrs:
        return None
    if "reference" in classifier.data_vars:
        from sklearn.neighbors import NearestNeighbors

        neighbours = NearestNeighbors(n_neighbors=features.NEIGHBOURS).fit(
            np.asarray(classifier["reference"].values, np.float64))
        return (lambda z: neighbours.kneighbors(z)[0].mean(axis=1),
                "mean distance of the standardised profile to its 5 nearest training pixels",
                "farther from the training pixels than the classifier's flag_rate allows")
    if "class_centre" in classifier.data_vars:
        centre = np.asarray(classifier["class_centre"].values, np.float64)

        def nearest(z):
            squared = (z**2).sum(1)[:, None] - 2 * z @ centre.T + (centre**2).sum(1)[None, :]
            return np.sqrt(np.maximum(squared.min(axis=1), 0.0))

        return (nearest, "distance of the standardised profile from the nearest class mean",
                "farther from every class than the training pixels' quantile novelty_quantile (before #55)")
    return None


def _by_object(label: xr.DataArray, distance: xr.DataArray, threshold: float, profiles: xr.Dataset, margin: int,
               flag: str) -> tuple[xr.DataArray, xr.DataArray, xr.DataArray]:
    """(labels voted per object, the objects, the flag: an object's median distance beyond ``threshold``, outside
    every object the pixel's own) — ``classify_materials``'s ``objects``. Lazy: the objects are found when the
    result is computed, over the whole frame at once (a watershed has no tiles)."""

    def segment(label, distance, area, flags):
        from scipy import ndimage

        distance = np.asarray(distance, np.float64)
        regions = features.objects(distance, threshold, np.asarray(area, np.float64), flags == 0, margin)
        count = int(regions.max(initial=0))
        median = np.zeros(count + 1)
        if count:
            median[1:] = ndimage.median(np.nan_to_num(distance, nan=np.inf), regions, np.arange(1, count + 1))
        unlike = np.where(regions > 0, median[np.maximum(regions, 0)] > threshold, distance > threshold)
        return features.vote(label, regions, voters=distance <= threshold), regions.astype(np.int32), unlike

    whole = [a.chunk({"row": -1, "col": -1}) if a.chunks else a
             for a in (label, distance, profiles["area"], profiles["flags"])]
    voted, regions, unlike = xr.apply_ufunc(segment, *whole, input_core_dims=[list(FRAME)] * 4,
                                            output_core_dims=[list(FRAME)] * 3, dask="parallelized",
                                            output_dtypes=[label.dtype, np.int32, bool])
    return voted, regions, unlike.assign_attrs(long_name=flag + "; within an object, the object's median")


def wilson_interval(successes, trials, z: float = Z95):
    """Wilson score interval (low, high) of a binomial proportion (element-wise; NaN where trials is 0)."""
    n = trials.where(trials > 0) if isinstance(trials, xr.DataArray) else np.where(trials > 0, trials, np.nan)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * np.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return centre - half, centre + half


def _scores(truth: xr.DataArray, predicted: xr.DataArray, n: int, prefix: str) -> dict:
    """Confusion matrix, per-class accuracy and its 95 % interval, and the overall accuracy (lazy)."""
    labelled = (truth >= 0) & (predicted >= 0)
    code = xr.where(labelled, truth.astype(np.int64) * n + predicted, n * n).data.reshape(-1)
    counts = np.bincount(code, minlength=n * n + 1)[: n * n].reshape(n, n)  # numpy or dask alike (array protocol)
    confusion = xr.DataArray(counts, dims=("true_material", "material"))
    right = xr.DataArray(np.diagonal(counts), dims="material")
    total = confusion.sum("material").rename(true_material="material")
    low, high = wilson_interval(right, total)
    return {f"{prefix}confusion": confusion.assign_attrs(units="1", long_name="pixels by true and predicted class"),
            f"{prefix}accuracy": (right / total.where(total > 0)).assign_attrs(
                units="1", long_name="share of the class's pixels classified right"),
            f"{prefix}accuracy_low": low.assign_attrs(units="1", long_name="95 % Wilson interval, low end"),
            f"{prefix}accuracy_high": high.assign_attrs(units="1", long_name="95 % Wilson interval, high end"),
            f"{prefix}overall_accuracy": (right.sum() / total.sum()).assign_attrs(
                units="1", long_name="share of labelled pixels classified right")}


@stage("classify_materials", kind=MATERIAL_CLASSIFICATION, precheck=label_precheck, identity=label_identity)
def classify_materials(profiles: xr.Dataset, classifier: xr.Dataset, /, *, labels: Labels | None = None,
                       label_image: StorePath = "", classes: tuple[str, ...] | None = None,
                       pool_px: Count | None = None, superpixel_px: Count = 300,
                       smooth_px: Index | None = None, objects: bool = False,
                       object_margin_px: Index = OBJECT_MARGIN_PX) -> xr.Dataset:
    """Classify every pixel of a capture by its delay profile, and by brightness alone (§5.4.9, Figs. 51c, 52).

    Parameters
    ----------
    profiles : xr.Dataset
        A ``delay_profiles`` store of the capture to classify (never the training capture's pixels: a new capture);
        kept over the classifier's window of delay (attr ``window_us``, chosen in training) and normalised over it.
    classifier : xr.Dataset
        A ``material_classifier`` store (``train_material_classifier``, or ``load_store`` of a saved one).
    labels : str or None
        The truth to score against, as ``train_material_classifier`` takes it (``scene``, or ``image`` with
        ``label_image``); its classes must be among the classifier's. None: classify only.
    label_image : str
        Path of the label image with ``labels: image``.
    classes : tuple of str or None
        The names of a label image's codes 1, 2, ….
    pool_px : int or None
        Pool each pixel's frames with its neighbours over a window of this many pixels a side, within its
        superpixel (never across an edge where the profile's shape changes), before classifying [px]; None: the
        classifier's own ``pool_px`` (1: none). Pooling reads the whole profile cube into memory (delays × rows ×
        cols × 8 bytes) and classifies it at once; without it the classification is lazy, band by band.
    superpixel_px : int
        The superpixels' size when pooling (SLIC on the standardised profiles) [px].
    smooth_px : int or None
        Filter the class probabilities with a guided filter of this radius, guided by the log of the regular image,
        before each pixel takes its most probable class [px] (``selpath.stages.procam._material_features``); None:
        the classifier's own ``smooth_px`` (0: none). Needs a classifier trained with ``smooth_px`` > 0 (it carries
        Platt probabilities); like pooling it reads the whole frame's profiles into memory.
    objects : bool
        Find the objects of trained materials and give each one class, for a capture of separate objects before a
        background (``selpath.stages.procam._material_features.objects``). Pixels within the classifier's novelty
        distance form the objects' cores; a watershed on the regular image's brightness edges gives the pixels
        between to a core or to the background; every pixel of an object takes the class most of its pixels within
        the novelty distance take. ``unlike_training`` is then the object's (its pixels' median distance beyond the
        threshold) and, outside every object, the pixel's own. Objects that touch with no edge in brightness between
        them merge and take one class. Needs a classifier with a novelty threshold, and one that holds on the new
        capture: where most of the trained materials' pixels are flagged (``unlike_training``) the cores are few
        and misplaced, and objects lower the accuracy (the dev set's demultiplexed route: 54 → 40 %). Reads the
        frame into memory. Off by default; on the materials dev set's delay sweep it lifts the smoothed pipeline
        from 76.7 to 90.8 % per pixel (docs/results.md).
    object_margin_px : int
        With ``objects``: the background's seeds are the pixels more than this far from every core (Euclidean);
        the band between goes to whichever side the brightness edge puts it on [px].

    Returns
    -------
    xr.Dataset
        A ``material_classification`` cube: ``label`` and ``brightness_label`` over (row, col) (index into ``material``;
        −1: no usable profile), the regular image ``image`` [counts], and ``unlike_training`` (a pixel whose mean
        distance to its 5 nearest training pixels exceeds the classifier's calibrated ``novelty_distance``, the (1 −
        ``flag_rate``) quantile of the training pixels' own out of fold: no trained material, e.g. the background; its
        label is still the SVM's) with that distance ``novelty_distance``; with pooling, ``pooled_area``; with
        ``objects``, ``object`` (row, col: 1 … n, 0 background, −1 unusable); with
        ``labels``, the truth ``true_label``, ``confusion`` over (true_material, material), per-class ``accuracy`` with
        its 95 % Wilson interval and ``overall_accuracy``, and the same for the brightness baseline (``brightness_``
        prefix).

    Raises
    ------
    StageError
        Profiles over other delays, another source kind or exposure than the classifier's, a model store whose hash does
        not match.

    References
    ----------
    Thesis §5.4.9 Material Recognition of Subsurface Scattering.
    """
    require_variables(profiles, ("profile", "area", "flags"), "classify_materials")
    require_variables(classifier, ("model", "mean_profile"), "classify_materials")
    regular = profiles["area"]
    if "window_us" in classifier.attrs:  # the window of delay the training chose
        profiles = window_profiles(profiles, float(classifier.attrs["window_us"]))
    trained = classifier["delay"].values
    delays = profiles["delay"].values
    problems = []
    if trained.shape != delays.shape or not np.allclose(trained, delays, atol=1e-6):
        problems.append(Problem(f"the classifier was trained on {trained.size} delays {trained[0]:g} … "
                                f"{trained[-1]:g} µs; these profiles have {delays.size} ({delays[0]:g} … "
                                f"{delays[-1]:g} µs)", fix="capture the same delay sweep as the training capture"))
    for key in ("source_kind", "exposure_us"):
        if classifier.attrs.get(key) != profiles.attrs.get(key):
            problems.append(Problem(f"the classifier's {key} is {classifier.attrs.get(key)!r}, the profiles' "
                                    f"{profiles.attrs.get(key)!r}", fix="classify profiles made as the training ones"))
    if problems:
        raise StageError(problems)
    novelty = _novelty_measure(classifier)
    if objects and novelty is None:
        raise StageError(Problem("objects are grown from the pixels within the classifier's novelty distance; this "
                                 "classifier has none", where="classifier",
                                 fix="train it again with train_material_classifier, or objects: false"))
    models = load_classifiers(classifier)
    names = [str(v) for v in classifier["material"].values]
    pool_px = int(classifier.attrs.get("pool_px", 1)) if pool_px is None else pool_px
    area = profiles["area"]
    profile = profiles["profile"].transpose("row", "col", "delay")
    if pool_px > 1:
        usable = np.asarray(profiles["flags"].values) == 0
        cube = np.asarray(profiles["profile"].transpose("delay", "row", "col").values, np.float64)
        pooled, total = pooled_profiles(profiles, features.superpixels(cube, superpixel_px, usable), pool_px)
        profile = xr.DataArray(np.moveaxis(pooled, 0, -1), dims=("row", "col", "delay"))
        area = xr.DataArray(np.where(usable, total, np.nan), dims=("row", "col"))
    profile = profile.chunk({"delay": -1}) if profile.chunks else profile
    out = dict(output_dtypes=[np.int16], dask="parallelized")
    smooth_px = int(classifier.attrs.get("smooth_px", 0)) if smooth_px is None else smooth_px
    if smooth_px > 0:
        if "probability" not in models:
            raise StageError(Problem(f"smooth_px {smooth_px} filters class probabilities; this classifier was "
                                     "trained without them", where="classifier",
                                     fix="train it with smooth_px > 0, or classify with smooth_px: 0"))
        usable = np.asarray(profiles["flags"].values) == 0
        profile = profile.load()  # read once: the probabilities and the novelty distance below both use it
        label = xr.DataArray(_smoothed_labels(models["probability"], profile, np.asarray(profiles["area"].values),
                                              usable, smooth_px), dims=FRAME)
    else:
        label = xr.apply_ufunc(lambda x: _predict(models["profile"], x), profile, input_core_dims=[["delay"]],
                               **out)
    bright = xr.apply_ufunc(lambda x: _predict(models["brightness"], x[..., None]), area, **out)
    result = {}
    if novelty is not None:
        measure, what, flag = novelty
        distance = xr.apply_ufunc(lambda x: _distance(models["profile"], x, measure), profile,
                                  input_core_dims=[["delay"]], output_dtypes=[np.float32], dask="parallelized")
        threshold = float(classifier.attrs["novelty_distance"])
        result["novelty_distance"] = distance.assign_attrs(units="1", long_name=what)
        result["unlike_training"] = (distance > threshold).assign_attrs(long_name=flag)
        if objects:
            label, result["object"], result["unlike_training"] = _by_object(
                label, distance, threshold, profiles, object_margin_px, flag)
    result |= {"label": label, "brightness_label": bright.where(label >= 0, -1).astype(np.int16),
              "image": regular}
    if pool_px > 1:
        result["pooled_area"] = area.assign_attrs(units="counts", long_name="area of the pooled profile")
    if labels is not None:
        codes, truth_names = label_map(profiles, labels, label_image, classes, "profiles")
        unknown = sorted({n for k, n in enumerate(truth_names, start=1) if (codes == k).any()} - set(names))
        if unknown:
            raise StageError(Problem(f"the labels name classes the classifier does not know: {unknown}",
                                     fix=f"label only its classes {names}"))
        lookup = np.array([-1] + [names.index(n) if n in names else -1 for n in truth_names], np.int16)
        truth = xr.DataArray(lookup[codes], dims=("row", "col"))
        result["true_label"] = truth.assign_attrs(units=None, long_name="true class index (−1: unlabelled)")
        result |= _scores(truth, result["label"], len(names), "")
        result |= _scores(truth, result["brightness_label"], len(names), "brightness_")
        if "unlike_training" in result:
            labelled = truth >= 0
            result["unlike_training_fraction"] = (result["unlike_training"] & labelled).sum() / max(
                int(labelled.sum()), 1)
            result["unlike_training_fraction"].attrs = {
                "units": "1", "long_name": "labelled pixels flagged unlike every trained class (scored all the same)"}
        result["classified_fraction"] = usable_share(
            ((truth >= 0) & (label >= 0)).sum() / max(int((truth >= 0).sum()), 1), floor=0.5,
            what="labelled pixels with a usable profile",
            fix="check the capture's frames: labelled pixels are dark, saturated or missing")
    keep = {k: v for k, v in profiles.attrs.items() if k not in ("selpath_kind",)}
    return MATERIAL_CLASSIFICATION.label(xr.Dataset(
        result, coords={"material": ("material", names, {"long_name": "material class"}),
                        "true_material": ("true_material", names, {"long_name": "true class"})},
        attrs=keep | {"model_sha256": classifier["model"].attrs.get("sha256"),
                      "training_scene": classifier.attrs.get("training_scene", ""),
                      "labels": (label_image if labels == "image" else labels) or "",
                      "pool_px": pool_px, "smooth_px": smooth_px, "objects": int(objects),
                      "object_margin_px": object_margin_px}))
