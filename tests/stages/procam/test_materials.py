"""Material recognition (§5.4.9): delay profiles against the simulator's lobes, the SVM on a new capture against the
thesis's goal, and bad input."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.stats
import xarray as xr

from selpath import workflows
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.pipeline import StageError
from selpath.pipeline.quality import enforce
from selpath.pipeline.store import open_store, to_store
from selpath.stages.procam import _material_features as features
from selpath.stages.procam.material_classification import classify_materials, load_classifiers, wilson_interval
from selpath.stages.procam.materials import delay_profiles, train_material_classifier
from selpath.stages.procam.multiplexing import noiseless
from tests.helpers.materials import SWEEP, materials
from tests.helpers.procam import capture_of


def lobe_scene(widths, fractions, albedos=None, **rig) -> ProcamScene:
    """Side-by-side vertical strips, one subsurface material each, on a rig whose rows match the projector's."""
    n = len(widths)
    albedos = albedos or [0.8] * n
    objects = [{"name": f"m{k}", "region": {"kind": "rectangle", "x": [k / n, (k + 1) / n], "y": [0.0, 1.0]},
                "albedo": albedos[k], "effects": {"subsurface": {"width": f"{w} px", "fraction": f}}}
               for k, (w, f) in enumerate(zip(widths, fractions, strict=True))]
    base = {"camera_rows": 96, "camera_cols": 96, "projector_rows": 96, "projector_cols": 96}
    return ProcamScene.model_validate({"scene": "lobes", "background": {"albedo": 0.0}, "objects": objects,
                                       "rig": base | rig})


def test_profiles_spread_as_the_simulators_lobes():
    """t_e = t_p = the delay step = one row period: the delay sweep samples the transport itself, so the profile's
    mean square delay is τ²·Σ o²·T(o) / Σ T(o) with T = (1 − f)·δ + f·Laplace(w) integrated over unit offset cells,
    computed here from scipy's Laplace distribution over the swept offsets. Within 1e-5 (float32 frames), at
    pixels whose lobes stay inside the projector."""
    widths, fractions = (1.5, 2.5, 3.5), (0.4, 0.7, 0.85)
    s = noiseless(lobe_scene(widths, fractions, camera_cols=258, projector_cols=258))
    tau = s.rig.row_period
    offsets = np.arange(-40, 41)
    capture = capture_of(s, offsets * tau, np.array([tau]))
    profiles = delay_profiles(capture).compute()
    assert profiles.attrs["source_kind"] == "plane_to_ray_capture"
    np.testing.assert_allclose(profiles["profile"].sum("delay").values, 1.0, rtol=1e-5)
    for k, (w, f) in enumerate(zip(widths, fractions, strict=True)):
        cell = scipy.stats.laplace(scale=w).cdf(offsets + 0.5) - scipy.stats.laplace(scale=w).cdf(offsets - 0.5)
        mass = f * cell + (1 - f) * (offsets == 0)
        truth = np.sqrt(tau**2 * (offsets**2 * mass).sum() / mass.sum())
        centre = profiles["rms_delay"].isel(row=48, col=43 + 86 * k).item()
        assert centre == pytest.approx(truth, rel=1e-5), (w, centre, truth)
    # broader lobes, broader profiles: the order the classifier relies on
    spreads = [profiles["rms_delay"].isel(row=48, col=43 + 86 * k).item() for k in range(3)]
    assert spreads == sorted(spreads)


def test_area_normalised_profiles_cancel_albedo():
    """The same material at albedo 0.3 and 0.9: the same profile (to float32 rounding), areas in the ratio 1:3."""
    s = noiseless(lobe_scene((4.0, 4.0), (0.7, 0.7), albedos=[0.3, 0.9], camera_cols=256, projector_cols=256))
    profiles = delay_profiles(capture_of(s, SWEEP, np.array([170.0]))).compute()
    dim, bright = profiles.isel(row=48, col=64), profiles.isel(row=48, col=192)
    np.testing.assert_allclose(dim["profile"].values, bright["profile"].values, rtol=1e-5)
    assert bright["area"].item() / dim["area"].item() == pytest.approx(3.0, rel=1e-5)


@pytest.fixture(scope="module")
def trained():
    profiles = delay_profiles(materials("white-materials", 0))
    return profiles, train_material_classifier(profiles, samples_per_class=300, seed=0)


@pytest.mark.parametrize("seed", [0, 1])
def test_the_svm_recognises_every_material_of_a_new_capture_and_brightness_does_not(trained, seed):
    """Trained on one capture, scored on another (the materials placed otherwise, another noise draw: never the
    same pixels): ≥ 90 % per class with the 95 % interval's low end above 85 % (the thesis's goal), for two seeds
    (training draw and folds, and the new capture's noise); brightness alone (the rig's only colour) stays below
    75 % on average and fails some class outright (< 60 %)."""
    _, classifier = trained
    if seed:
        classifier = train_material_classifier(trained[0], samples_per_class=300, seed=seed)
    profiles = delay_profiles(materials("white-materials-shuffled", 10 + seed))
    scored = classify_materials(profiles, classifier, labels="scene").compute()
    assert scored["accuracy"].min() >= 0.9, scored["accuracy"].values
    assert scored["accuracy_low"].min() >= 0.85
    assert scored["brightness_accuracy"].mean() < 0.75
    assert scored["brightness_accuracy"].min() < 0.6
    # the confusion matrix counts every labelled pixel once
    assert int(scored["confusion"].sum()) == int((scored["true_label"] >= 0).sum())


def test_pixels_of_no_trained_material_are_flagged_and_the_materials_are_not():
    """The background (direct reflection only, albedo 0.1: a narrow, noisy profile) is none of the five materials:
    ≥ 95 % of its pixels are flagged unlike training (measured 99.9 %), and ≤ 2 % of the materials' pixels of a new
    capture (measured 0.95 %; the threshold is the 99.9th percentile of the training pixels' distances from their
    class's mean)."""
    profiles = delay_profiles(materials("white-materials", 0))
    classifier = train_material_classifier(profiles, samples_per_class=300, seed=0)
    scored = classify_materials(delay_profiles(materials("white-materials-shuffled", 10)), classifier,
                                labels="scene").compute()
    background = (scored["true_label"] < 0) & (scored["label"] >= 0)
    assert float(scored["unlike_training"].where(background).mean()) >= 0.95
    assert float(scored["unlike_training_fraction"]) <= 0.02


def test_a_classifier_travels_in_its_store_and_a_tampered_one_is_refused(trained, tmp_path):
    profiles, classifier = trained
    path = tmp_path / "classifier.zarr"
    to_store(classifier, path, "material_classifier")
    stored = open_store(path)
    assert stored.attrs["svm_C"] in (1.0, 10.0, 100.0)
    assert set(stored["material"].values) == {"hand soap", "fat-free milk", "2 % milk", "whole milk", "toothpaste"}
    a = classify_materials(profiles, classifier)["label"].values
    b = classify_materials(profiles, stored)["label"].values
    np.testing.assert_array_equal(a, b)
    tampered = stored.load().copy(deep=True)
    tampered["model"].values[100] ^= 1
    with pytest.raises(StageError, match="does not match its recorded sha256"):
        classify_materials(profiles, tampered)


def test_stored_profiles_cut_unevenly_classify_and_store(trained, tmp_path):
    """#55's crash: a profiles store whose ``profile`` is chunked 96 + 24 rows and ``area`` whole, classified and its
    result stored (the result's variables then come cut differently along row)."""
    profiles, classifier = trained
    uneven = profiles.copy()
    uneven["profile"] = uneven["profile"].chunk({"row": 96})
    to_store(uneven, tmp_path / "profiles.zarr", "delay_profiles")
    stored = open_store(tmp_path / "profiles.zarr")
    scored = classify_materials(stored, classifier, labels="scene")
    to_store(scored, tmp_path / "classification.zarr", "material_classification")
    back = open_store(tmp_path / "classification.zarr")
    np.testing.assert_array_equal(back["label"].values, classify_materials(profiles, classifier)["label"].values)


def test_folding_and_pooling(trained):
    """Folded profiles are p(t) + p(−t) over t_d ≥ 0 (still summing to 1); pooled within the labels to train and within
    superpixels to classify, a new capture still meets the thesis's 90 % per class (measured: worst class 91.5 %, hand
    soap, whose superpixels reach into its neighbour; the simulator's profiles are clean enough not to need it)."""
    profiles, classifier = trained
    folded = delay_profiles(materials("white-materials", 0), fold=True).compute()
    p = profiles["profile"].isel(row=60, col=80).values
    np.testing.assert_allclose(folded["profile"].isel(row=60, col=80).values,
                               np.concatenate([p[20:21], p[21:] + p[:20][::-1]]), rtol=1e-5)
    assert folded["delay"].values.tolist() == SWEEP[20:].tolist() and folded.attrs["folded"]
    pooled = train_material_classifier(folded, samples_per_class=300, seed=0, pool_px=5)
    assert pooled.attrs["pool_px"] == 5
    scored = classify_materials(delay_profiles(materials("white-materials-shuffled", 10), fold=True), pooled,
                                labels="scene").compute()
    assert scored["accuracy"].min() >= 0.9 and "pooled_area" in scored
    with pytest.raises(StageError, match="symmetric about 0"):
        delay_profiles(materials("white-materials", 0).isel(delay=slice(1, None)), fold=True)
    with pytest.raises(StageError, match="direct light arrives at t_d = −t_o = -5 µs"):
        delay_profiles(materials("white-materials", 0).assign_attrs(sync_offset_us=5.0), fold=True)


def test_pooling_is_the_mean_over_the_window_within_the_region():
    """Against a brute-force loop: each pixel's frames averaged over the 5 × 5 window's pixels of its own region
    (regions of any shape, pixels of no region left alone)."""
    from selpath.stages.procam._material_features import pool

    rng = np.random.default_rng(0)
    frames, regions = rng.random((3, 30, 40)), rng.integers(-1, 5, (30, 40))
    expected = frames.copy()
    for r in range(30):
        for c in range(40):
            if regions[r, c] >= 0:
                near = np.zeros((30, 40), bool)
                near[max(r - 2, 0):r + 3, max(c - 2, 0):c + 3] = True
                expected[:, r, c] = frames[:, near & (regions == regions[r, c])].mean(axis=1)
    np.testing.assert_allclose(pool(frames, regions, 5), expected, rtol=1e-12)


def test_the_guided_filter_is_he_et_al_s_formula():
    """Against the guided filter written from its paper (He, Sun and Tang 2013, Alg. 1: box means of radius r, a =
    cov(I, p) / (var(I) + ε), b = mean(p) − a·mean(I), q = mean(a)·I + mean(b)) on the pixels whose windows lie
    inside the frame (the borders differ in how they are padded); the guide is log area scaled to [0, 1]."""
    from scipy.ndimage import uniform_filter

    from selpath.stages.procam._material_features import guided_smooth

    rng = np.random.default_rng(1)
    area = np.exp(rng.normal(5.0, 1.0, (40, 50)))
    scores = rng.random((40, 50, 3)).astype(np.float32)
    r, eps = 3, 1e-2
    guide = (np.log(area) - np.log(area).min()) / np.ptp(np.log(area))

    def mean(x):
        return uniform_filter(x, size=2 * r + 1, mode="reflect")

    got = guided_smooth(scores, area, np.ones((40, 50), bool), r, eps)
    inner = (slice(2 * r, -2 * r), slice(2 * r, -2 * r))
    for k in range(3):
        p = scores[..., k].astype(float)
        a = (mean(guide * p) - mean(guide) * mean(p)) / (mean(guide**2) - mean(guide) ** 2 + eps)
        b = mean(p) - a * mean(guide)
        np.testing.assert_allclose(got[..., k][inner], (mean(a) * guide + mean(b))[inner], atol=2e-5)


def test_smoothed_probabilities_classify_a_new_capture_and_travel_in_the_store(trained, tmp_path):
    """A classifier trained with smooth_px carries calibrated probabilities (two scikit-learn calibration types
    skops does not list, trusted by name) and classifies the simulator's new capture at the thesis's 90 % per class
    through its store; classifying with smooth_px a classifier trained without is refused."""
    profiles, classifier = trained
    smoothing = train_material_classifier(profiles, samples_per_class=200, seed=0, smooth_px=2)
    path = tmp_path / "classifier.zarr"
    to_store(smoothing, path, "material_classifier")
    scored = classify_materials(delay_profiles(materials("white-materials-shuffled", 10)), open_store(path),
                                labels="scene").compute()
    assert scored.attrs["smooth_px"] == 2
    assert scored["accuracy"].min() >= 0.9, scored["accuracy"].values
    with pytest.raises(StageError, match="trained without them"):
        classify_materials(profiles, classifier, smooth_px=2)


def test_smoothing_refuses_a_class_some_fold_cannot_calibrate(trained, tmp_path):
    """A class labelled on one row lies in one band of rows, so a fold's training bands miss it and its Platt
    sigmoid would be fitted on placeholders: refused before anything is fitted, naming the class."""
    profiles, _ = trained
    codes = np.zeros((profiles.sizes["row"], profiles.sizes["col"]), np.int16)
    codes[20:100, 10:60] = 1
    codes[20:100, 200:250] = 2
    codes[50, 100:140] = 3
    np.save(tmp_path / "labels.npy", codes)
    settings = dict(labels="image", label_image=str(tmp_path / "labels.npy"), classes=("wide", "also wide", "one row"),
                    samples_per_class=200)
    with pytest.raises(StageError, match=r"\['one row'\] lie in too few bands of rows"):
        train_material_classifier(profiles, **settings, smooth_px=2)


def test_objects_give_each_object_one_class_and_unflag_its_pixels(trained):
    """With ``objects`` the simulator's new capture splits into its five materials' objects, each ≥ 99 % one
    material; every class ≥ 99 % right (measured 99.3–100 %; without objects 94.3–100 %), the materials' pixels
    flagged ≤ 0.5 % (measured 0.11 %; without 1.6 %), the background still ≥ 95 % (measured 99.8 %). A classifier
    without a novelty threshold cannot grow objects: refused."""
    _, classifier = trained
    profiles = delay_profiles(materials("white-materials-shuffled", 10))
    scored = classify_materials(profiles, classifier, labels="scene", objects=True).compute()
    found, truth = scored["object"].values, scored["true_label"].values
    assert found.max() == 5 and scored.attrs["objects"] == 1 and scored.attrs["object_margin_px"] == 4
    for code in range(1, 6):
        counts = np.bincount(truth[found == code] + 1)
        assert counts.max() >= 0.99 * counts.sum() and counts.argmax() >= 1  # a material, not the background
    assert scored["accuracy"].min() >= 0.985, scored["accuracy"].values
    assert float(scored["unlike_training_fraction"]) <= 0.005
    background = (scored["true_label"] < 0) & (scored["label"] >= 0)
    assert float(scored["unlike_training"].where(background).mean()) >= 0.95
    with pytest.raises(StageError, match="has none"):
        classify_materials(profiles, classifier.drop_attrs(deep=False).assign_attrs(
            {k: v for k, v in classifier.attrs.items() if k != "novelty_distance"}), objects=True)


def test_objects_and_vote_against_brute_force():
    """Two bright objects on a dim wall, each with a one-pixel strip the classifier does not know (its rim) and a
    dark gap between: two objects whose rims join them and whose gap stays background; the vote against a loop over
    random regions and voters."""
    area = np.full((30, 40), 10.0)
    area[5:25, 5:15], area[5:25, 25:35] = 50.0, 30.0
    distance = np.where(area > 20, 0.5, 9.0)
    distance[5:25, 5], distance[5:25, 34] = 9.0, 9.0  # the rims look unlike training
    usable = np.ones(area.shape, bool)
    usable[0, 0] = False
    found = features.objects(distance, 1.0, area, usable, margin=3)
    assert found[0, 0] == -1 and set(np.unique(found[1:])) == {0, 1, 2}
    assert (found[6:24, 5] == found[15, 10]).all() and (found[6:24, 34] == found[15, 30]).all()
    assert found[15, 10] != found[15, 30]
    assert (found[area < 20] <= 0).all()  # the wall, the gap between them included, joins no object
    # the brightness edge decides: on a flat image the band within the margin would go to the nearest seed
    flat = features.objects(distance, 1.0, np.full(area.shape, 10.0), usable, margin=3)
    assert (flat[area < 20] > 0).sum() > 100
    # a margin of 6 px leaves the 10-px gap no seed of its own: it is still background, flooded from the corners
    assert (features.objects(distance, 1.0, area, usable, margin=6)[area < 20] <= 0).all()
    # NaN distances are never a core; a core under min_px is no object; no core at all: everything background
    unknown = distance.copy()
    unknown[5:25, 25:35] = np.nan
    assert set(np.unique(features.objects(unknown, 1.0, area, usable, 3))) == {-1, 0, 1}
    assert features.objects(distance, 1.0, area, usable, 3, min_px=500).max() == 0
    assert features.objects(np.full(area.shape, 9.0), 1.0, area, usable, 3).max() == 0
    rng = np.random.default_rng(3)
    for _ in range(20):
        label, regions = rng.integers(-1, 4, (9, 11)), rng.integers(-1, 5, (9, 11))
        voters = rng.random((9, 11)) < 0.7
        expected = label.copy()
        for code in range(1, 5):
            ballot = label[(regions == code) & voters & (label >= 0)]
            if ballot.size:
                expected[(regions == code) & (label >= 0)] = np.bincount(ballot).argmax()
        np.testing.assert_array_equal(features.vote(label, regions, voters), expected)


def test_a_window_of_delay_keeps_the_near_delays_normalised_again(trained):
    """``window_profiles`` against a brute-force recomputation from the frames (profile × area), a pixel whose light
    lies all outside the window flagged no_light, a window keeping under 2 delays refused, one wider than the sweep
    a no-op."""
    from selpath.stages.procam.materials import NO_LIGHT, window_profiles

    profiles = trained[0].compute()
    profiles["profile"][:, 7, 9] = 0.0
    profiles["profile"][0, 7, 9] = 1.0  # all its light at the first delay, −340 µs
    kept = window_profiles(profiles, 100.0).compute()
    near = np.abs(profiles["delay"].values) <= 100.0
    frames = profiles["profile"].values[near] * profiles["area"].values
    assert kept["delay"].values.tolist() == profiles["delay"].values[near].tolist()
    np.testing.assert_allclose(kept["area"].values[5:9, 5:9], frames.sum(0)[5:9, 5:9], rtol=1e-6)
    np.testing.assert_allclose(kept["profile"].values[:, 60, 80], frames[:, 60, 80] / frames[:, 60, 80].sum(),
                               rtol=1e-5)
    assert kept["flags"].values[7, 9] == NO_LIGHT and np.isnan(kept["profile"].values[:, 7, 9]).all()
    assert kept.attrs["window_us"] == 100.0 and "rms_delay" not in kept
    assert window_profiles(profiles, 1000.0) is profiles
    with pytest.raises(StageError, match="keeps 1 of the profiles' delays"):
        window_profiles(profiles, 5.0)


def test_the_window_is_chosen_by_cross_validation_and_applied_when_classifying(trained, tmp_path):
    """The defaults try a quarter, half and all of the sweep (85, 170, 340 µs) and keep all on the simulator
    (cross-validated 0.51, 0.95, 1.00); a classifier given one window is trained and stored over it, and
    ``classify_materials`` cuts a full sweep's profiles to it: on the simulator's new capture it scores below the
    whole sweep, as its cross-validation foretold (measured 89.8–100 % per class against 94.3–100 %)."""
    _, classifier = trained
    assert classifier.attrs["window_us"] == 340.0 and classifier["window"].values.tolist() == [85.0, 170.0, 340.0]
    assert classifier["window_cv_accuracy"].values[-1] >= classifier["window_cv_accuracy"].values[0] + 0.2
    narrow = train_material_classifier(trained[0], samples_per_class=200, seed=0, window_grid_us=(170.0,))
    assert narrow.attrs["window_us"] == 170.0 and np.abs(narrow["delay"].values).max() == 170.0
    to_store(narrow, tmp_path / "narrow.zarr", "material_classifier")
    scored = classify_materials(delay_profiles(materials("white-materials-shuffled", 10)),
                                open_store(tmp_path / "narrow.zarr"), labels="scene").compute()
    assert scored["accuracy"].min() >= 0.85, scored["accuracy"].values
    whole = classify_materials(delay_profiles(materials("white-materials-shuffled", 10)), classifier, labels="scene")
    assert float(scored["overall_accuracy"]) < float(whole["overall_accuracy"])
    assert scored["image"].equals(delay_profiles(materials("white-materials-shuffled", 10))["area"].compute())


def test_the_flag_rate_holds_on_a_capture_like_the_training_one(trained):
    """The same scene, another noise draw: the materials' pixels flagged are about flag_rate (1 %; measured 0.9 %),
    at most 3 % here."""
    _, classifier = trained
    scored = classify_materials(delay_profiles(materials("white-materials", 7)), classifier, labels="scene").compute()
    assert classifier.attrs["flag_rate"] == 0.01
    assert float(scored["unlike_training_fraction"]) <= 0.03


def test_a_classifier_from_before_the_calibrated_flag_keeps_its_rule(trained):
    """A classifier store without ``reference`` (trained before #55) flags by the distance to the nearest class mean,
    against its own ``novelty_distance``: the rule it was trained with, named so in the flag's long name."""
    profiles, classifier = trained
    old = classifier.drop_vars("reference")
    centre = np.asarray(classifier["class_centre"].values)
    scored = classify_materials(profiles, old).compute()
    assert "novelty_quantile" in scored["unlike_training"].attrs["long_name"]
    pixel = profiles["profile"].isel(row=60, col=80).values[None]
    model = load_classifiers(old)
    standard = model["profile"].named_steps["scale"].transform(pixel)
    expected = np.sqrt(((standard - centre) ** 2).sum(1)).min()
    assert float(scored["novelty_distance"].isel(row=60, col=80)) == pytest.approx(expected, rel=1e-4)


def test_a_model_naming_an_untrusted_type_is_refused_even_with_a_matching_hash(trained):
    """skops refuses types it does not trust (here fractions.Fraction, harmless but not scikit-learn's) before any
    is loaded; the sha256 only catches corruption, so the archive here carries a matching one."""
    import fractions
    import hashlib

    import skops.io

    profiles, classifier = trained
    archive = skops.io.dumps({"profile": fractions.Fraction(1, 3)})
    forged = classifier.drop_vars("model").assign(model=("byte", np.frombuffer(archive, np.uint8),
                                                         {"sha256": hashlib.sha256(archive).hexdigest()}))
    with pytest.raises(StageError, match="names types skops does not trust: \\['fractions.Fraction'\\]"):
        classify_materials(profiles, forged)


def test_classification_is_lazy_and_a_class_without_training_pixels_is_no_class(trained, tmp_path):
    """Building the classification of dask-backed profiles computes nothing (the SVM runs once, when the result is
    computed), with objects too (found when the result is computed, the same as from profiles in memory). A label
    image whose code 2 no pixel carries trains a classifier of the other two classes, and its labels index them."""
    import dask

    from tests.conftest import ComputeCounter

    profiles, classifier = trained
    with dask.config.set(scheduler=ComputeCounter()):
        scored = classify_materials(profiles.chunk({"row": 40}), classifier, labels="scene")
        by_object = classify_materials(profiles.chunk({"row": 40}), classifier, labels="scene", objects=True)
    scored = scored.compute()
    eager = classify_materials(profiles.compute(), classifier, labels="scene", objects=True)
    for name in ("label", "object", "unlike_training"):
        np.testing.assert_array_equal(by_object[name].values, eager[name].values)
    codes = np.zeros((120, 160), np.int16)
    truth = scored["true_label"].values  # index into the scene's materials
    names = [str(v) for v in classifier["material"].values]
    codes[truth == names.index("hand soap")] = 1
    codes[truth == names.index("toothpaste")] = 3
    np.save(tmp_path / "gap.npy", codes)
    two = train_material_classifier(profiles, labels="image", label_image=str(tmp_path / "gap.npy"),
                                    classes=("hand soap", "unused", "toothpaste"), samples_per_class=200)
    assert list(two["material"].values) == ["hand soap", "toothpaste"]
    result = classify_materials(profiles, two, labels="image", label_image=str(tmp_path / "gap.npy"),
                                classes=("hand soap", "unused", "toothpaste")).compute()
    assert result["confusion"].shape == (2, 2) and result["accuracy"].min() > 0.95
    assert set(np.unique(result["label"].values)) <= {-1, 0, 1}


def test_wilson_interval_matches_scipy():
    for k, n in [(0, 10), (9, 10), (10, 10), (4880, 5000), (37, 41)]:
        low, high = wilson_interval(np.float64(k), np.float64(n))
        ci = scipy.stats.binomtest(k, n).proportion_ci(confidence_level=0.95, method="wilson")
        assert (low, high) == pytest.approx((ci.low, ci.high), abs=1e-12)


def test_bad_training_and_classification_input_is_refused(trained, tmp_path):
    profiles, classifier = trained
    one = np.zeros((120, 160), np.int16)
    one[10:20, 10:20] = 1
    np.save(tmp_path / "one.npy", one)
    with pytest.raises(StageError, match="at least 2"):
        train_material_classifier(profiles, labels="image", label_image=str(tmp_path / "one.npy"), classes=("a",))
    np.save(tmp_path / "none.npy", np.zeros((120, 160), np.int16))
    with pytest.raises(StageError, match="no pixel is labelled"):
        train_material_classifier(profiles, labels="image", label_image=str(tmp_path / "none.npy"),
                                  classes=("a", "b"))
    with pytest.raises(StageError, match="has codes but no class names"):
        train_material_classifier(profiles, labels="image", label_image=str(tmp_path / "one.npy"))
    np.save(tmp_path / "three.npy", one * 3)
    with pytest.raises(StageError, match="has codes 0 … 3; classes names 2"):
        train_material_classifier(profiles, labels="image", label_image=str(tmp_path / "three.npy"),
                                  classes=("a", "b"))
    # a class whose labelled pixels all have zero area (a dark patch)
    capture = materials("white-materials", 0)
    capture["image"][:, :, 40:50, 40:50] = 0.0
    two = np.zeros((120, 160), np.int16)
    two[10:20, 10:20], two[40:50, 40:50] = 1, 2
    np.save(tmp_path / "two.npy", two)
    dark = delay_profiles(capture).compute()  # computed with warnings as errors: no 0/0 where there is no light
    assert (dark["flags"].values[40:50, 40:50] == 4).all() and np.isnan(dark["profile"].values[:, 40:50, 40:50]).all()
    with pytest.raises(StageError, match="class 'dark' has 0 labelled pixels with a usable profile"):
        train_material_classifier(delay_profiles(capture), labels="image", label_image=str(tmp_path / "two.npy"),
                                  classes=("lit", "dark"))
    # an all-dark capture has no usable profile at all
    with pytest.raises(StageError, match="usable delay profile"):
        enforce(delay_profiles(capture.assign(image=xr.zeros_like(capture["image"]))))
    # profiles of another sweep than the training one
    other = delay_profiles(materials("white-materials", 0).isel(delay=slice(None, None, 2)))
    with pytest.raises(StageError, match="trained on 41 delays"):
        classify_materials(other, classifier)
    # scoring against classes the classifier never saw
    with pytest.raises(StageError, match="does not know"):
        classify_materials(profiles, classifier, labels="image", label_image=str(tmp_path / "two.npy"),
                           classes=("lit", "dark"))


@pytest.mark.slow
def test_the_two_material_workflows_train_store_and_apply_a_classifier(tmp_path):
    """The shipped pair end to end (about 45 s): procam-materials trains and stores the classifier; then, in the same
    folder, procam-materials-apply loads it (validated only now that the store exists) and scores a new capture at
    ≥ 90 % per class; the classification names the model it used by its sha256, and the figure is drawn."""
    import shutil

    from selpath.pipeline import load_workflow
    from selpath.pipeline.engine import run_workflow
    from selpath.pipeline.provenance import read_provenance

    for name in ("procam-materials", "procam-materials-apply"):
        shutil.copy(workflows.path(name), tmp_path / f"{name}.yaml")
    shutil.copytree(workflows.folder() / "scenes", tmp_path / "scenes")
    run_workflow(load_workflow(tmp_path / "procam-materials.yaml"), progress=False)
    classifier = open_store(tmp_path / "out/procam-materials/classifier.zarr")
    assert read_provenance(tmp_path / "out/procam-materials/classifier.zarr")["workflow"] == "procam-materials"
    run_workflow(load_workflow(tmp_path / "procam-materials-apply.yaml"), progress=False)
    scored = open_store(tmp_path / "out/procam-materials-apply/classification.zarr")
    assert float(scored["accuracy"].min()) >= 0.9 and float(scored["brightness_accuracy"].mean()) < 0.75
    assert scored.attrs["model_sha256"] == classifier["model"].attrs["sha256"]
    assert (tmp_path / "out/procam-materials-apply/materials-figure.png").is_file()
