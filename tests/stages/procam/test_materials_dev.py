"""Material recognition on data selpath did not make (#55): the materials dev set (``../shared/data/materials-dev``,
rendered outside selpath: six translucent slabs, two placements, 12-bit noisy frames) brought in as a user would
(``selpath import`` with a spec written from its README, labels from its .npz), trained on placement D1 and scored
on D2 through ``selpath run``; the plain pipeline (no folding, no pooling) beside it in the same run.

The bounds are the numbers measured (docs/results.md), less a margin for the noise of a retrain on another
machine. With ``objects`` the pipeline meets #55's accuracy goals (≥ 80 % per pixel, every class ≥ 65 %) and the
background's flag goal (≥ 90 %); the slabs' (≤ 5 % flagged) it still misses, and the bound here guards the measured
14.4 %. Skipped where the set is absent
(``SELPATH_MATERIALS_DEV`` names another folder)."""

from __future__ import annotations

import os
import textwrap
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import selpath
from selpath.pipeline.cli import app

DEV = Path(os.environ.get("SELPATH_MATERIALS_DEV",
                          Path(__file__).resolve().parents[3].parent / "shared" / "data" / "materials-dev"))
pytestmark = [pytest.mark.slow, pytest.mark.skipif(not (DEV / "D1-materials-sweep.npz").is_file(),
                                                    reason=f"no materials dev set at {DEV}")]
CLASSES = "[m1, m2, m3, m4, m5, m6]"


def _spec(placement: str) -> str:
    """The import spec a user writes from the set's README: the materials sweep, the rig's timing and counts."""
    delays = ", ".join(f"{d:g}" for d in np.arange(-340.0, 341.0, 17.0))
    return textwrap.dedent(f"""\
        kind: plane_to_ray_capture
        frames: {{image: {DEV}/{placement}-materials-sweep.npz:frames}}
        delays_us: [{delays}]
        exposures_us: [170]
        scan_speed_px_per_us: {1 / 17!r}
        line_time_us: 17
        saturation_counts: 4095
        dark_level_counts: 0
        """)


def _steps(name: str, fold: bool, pool: int, smooth: int = 0) -> str:
    return textwrap.dedent(f"""\
          - id: {name}_d1
            stage: delay_profiles
            with: {{source: $d1, fold: {str(fold).lower()}}}
          - id: {name}_d2
            stage: delay_profiles
            with: {{source: $d2, fold: {str(fold).lower()}}}
          - id: {name}_classifier
            stage: train_material_classifier
            with: {{profiles: ${name}_d1, labels: image, label_image: {DEV}/D1-materials-sweep.npz:labels,
                    classes: {CLASSES}, samples_per_class: 600, pool_px: {pool}, smooth_px: {smooth}}}
          - id: {name}
            stage: classify_materials
            with: {{profiles: ${name}_d2, classifier: ${name}_classifier, labels: image,
                    label_image: {DEV}/D2-materials-sweep.npz:labels, classes: {CLASSES}}}
        """)


@pytest.fixture(scope="module")
def scored(tmp_path_factory):
    folder = tmp_path_factory.mktemp("materials-dev")
    runner = CliRunner()
    for placement in ("D1", "D2"):
        (folder / f"{placement}.yaml").write_text(_spec(placement))
        result = runner.invoke(app, ["import", str(folder / f"{placement}.yaml"), str(folder / f"{placement}.zarr")])
        assert result.exit_code == 0, result.output
    workflow = "workflow: materials-dev\nscheduler: threads\nsteps:\n" + textwrap.indent(textwrap.dedent("""\
        - id: d1
          stage: load_store
          with: {store: D1.zarr}
        - id: d2
          stage: load_store
          with: {store: D2.zarr}
        """), "  ")
    workflow += textwrap.indent(_steps("plain", False, 1) + _steps("pooled", True, 15)
                               + _steps("smoothed", True, 15, 4) + textwrap.dedent(f"""\
          - id: objects
            stage: classify_materials
            with: {{profiles: $smoothed_d2, classifier: $smoothed_classifier, labels: image,
                    label_image: {DEV}/D2-materials-sweep.npz:labels, classes: {CLASSES}, objects: true}}
        """), "  ") + textwrap.dedent("""\
        outputs:
          plain: {from: plain, store: out/plain.zarr}
          pooled: {from: pooled, store: out/pooled.zarr}
          pooled_classifier: {from: pooled_classifier, store: out/pooled-classifier.zarr}
          smoothed: {from: smoothed, store: out/smoothed.zarr}
          objects: {from: objects, store: out/objects.zarr}
        """)
    (folder / "wf.yaml").write_text(workflow)
    selpath.run(folder / "wf.yaml")
    return {name: selpath.open_store(folder / f"out/{name}.zarr").load()
            for name in ("plain", "pooled", "smoothed", "objects")}


def test_pooling_within_objects_lifts_every_class_over_the_plain_pipeline(scored):
    """Measured: plain 52 % per pixel (worst class 33 %); folded and pooled (15 px within the labels to train,
    within superpixels of 300 px to classify) 71 % (worst 52 %)."""
    plain, pooled = scored["plain"], scored["pooled"]
    assert float(plain["overall_accuracy"]) < 0.6
    assert float(pooled["overall_accuracy"]) >= 0.66, float(pooled["overall_accuracy"])
    assert float(pooled["accuracy"].min()) >= 0.45, pooled["accuracy"].values
    assert float(pooled["overall_accuracy"]) >= float(plain["overall_accuracy"]) + 0.12


def test_smoothing_the_class_probabilities_lifts_the_pooled_pipeline(scored):
    """Measured in one run: pooled 71.4 % (worst class 53.0 %); its class probabilities guided-filtered over 4 px
    (the radius the training placement's cross-validation over row bands chose) 76.7 % (worst 57.3 %, the absorbing
    m5), every class but m6 up (m6 91 → 89 %)."""
    pooled, smoothed = scored["pooled"], scored["smoothed"]
    assert float(smoothed["overall_accuracy"]) >= float(pooled["overall_accuracy"]) + 0.03
    assert float(smoothed["overall_accuracy"]) >= 0.73, float(smoothed["overall_accuracy"])
    assert float(smoothed["accuracy"].min()) >= 0.5, smoothed["accuracy"].values
    assert smoothed.attrs["smooth_px"] == 4 and pooled.attrs["smooth_px"] == 0


def test_the_never_trained_background_is_flagged(scored):
    """The wall and floor (label 0, never a training class): measured 98.2 % flagged with pooling (18.6 % without),
    while 22.7 % of the slabs' pixels are flagged too (the placement's shift; 1 % is the calibrated rate on data like
    the training capture's)."""
    pooled = scored["pooled"]
    background = (pooled["true_label"] < 0) & (pooled["label"] >= 0)
    assert float(pooled["unlike_training"].where(background).mean()) >= 0.9
    assert float(pooled["unlike_training_fraction"]) <= 0.3


def test_objects_meet_the_accuracy_goals_and_flag_the_background_not_the_slabs(scored):
    """#55's goals on the test placement: ≥ 80 % per pixel, every class ≥ 65 %, the never-trained background ≥ 90 %
    flagged, trained pixels ≤ 5 %. The smoothed pipeline's classes voted within objects grown from the pixels the
    classifier knows (margin 4 px, chosen on the training placement), measured in one run: 90.8 % per pixel (smoothed
    alone 76.7 %), worst class 79 % (the dense m4 at the frame's edge; the absorbing m5 81 %), background 97.1 %
    flagged; slabs 14.4 % flagged (smoothed alone 24.9 %), the one goal still missed: m4's half nearest its neighbour
    and m5's left side lie in shadow, and a band of m1 sits just beyond the novelty threshold; they form no core."""
    objects, smoothed = scored["objects"], scored["smoothed"]
    assert float(objects["overall_accuracy"]) >= 0.85, float(objects["overall_accuracy"])
    assert float(objects["accuracy"].min()) >= 0.7, objects["accuracy"].values
    background = (objects["true_label"] < 0) & (objects["label"] >= 0)
    assert float(objects["unlike_training"].where(background).mean()) >= 0.9
    assert float(objects["unlike_training_fraction"]) <= 0.2
    assert float(objects["unlike_training_fraction"]) < float(smoothed["unlike_training_fraction"]) - 0.05
    assert objects.attrs["objects"] == 1 and int(objects["object"].max()) >= 6
