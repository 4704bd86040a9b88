"""Every stage setting is range-checked when a workflow is validated, before anything runs.

Mutator pattern: a valid workflow (``SMALL_WORKFLOW`` or a shipped ``workflows/*.yaml``) with one field
broken must fail :func:`selpath.pipeline.load_workflow` with the exact message. Sizes that would not fit in memory
are checked against a machine of 16 GiB (``machine_memory`` patched), so the messages do not depend on the
machine the tests run on. The last tests walk every registered stage: a new int or float setting needs a
lower bound, or a place in :data:`SIGNED` with the reason it may be negative.
"""

from __future__ import annotations

import re
import shutil
import types
import typing
from pathlib import Path

import pydantic
import pytest
from annotated_types import Ge, Gt

import selpath.pipeline.constraints as constraints
from selpath import workflows
from selpath.pipeline import SpecError, load_workflow
from selpath.pipeline.registry import default_registry
from selpath.stages._sweeps import sweep_count
from selpath.stages.procam._capture_to_transport import OffsetGrid
from selpath.stages.procam.acquire import PixelSweep, TimeSweep
from selpath.stages.tomography.acquire import AngleSweep

WORKFLOWS = workflows.folder()
GIB = 2**30


@pytest.fixture(autouse=True)
def machine_of_16_gib(monkeypatch):
    monkeypatch.setattr(constraints, "machine_memory", lambda: 16 * GIB)


def _shipped(name: str) -> str:
    return (WORKFLOWS / name).read_text()


def _mutated(text: str, old: str, new: str) -> str:
    assert text.count(old) == 1, f"{old!r} must occur exactly once in the workflow"
    return text.replace(old, new)


def assert_refused(tmp_path: Path, text: str, message: str) -> None:
    """``text`` written beside a copy of the shipped scenes fails validation with ``message`` (its end, exactly:
    the file's own path comes first)."""
    if not (tmp_path / "scenes").exists():
        shutil.copytree(WORKFLOWS / "scenes", tmp_path / "scenes")
    path = tmp_path / "wf.yaml"
    path.write_text(text)
    with pytest.raises(SpecError, match=re.escape(message) + "$"):
        load_workflow(path)


def test_the_unbroken_workflows_validate(tmp_path, workflow_text):
    """Every shipped workflow but those that read another's output (``selpath.workflows.AFTER``: test_cli covers
    them)."""
    shutil.copytree(WORKFLOWS / "scenes", tmp_path / "scenes")
    shipped = (p.read_text() for p in sorted(WORKFLOWS.glob("*.yaml")) if p.stem not in workflows.AFTER)
    for text in (workflow_text, *shipped):
        (tmp_path / "wf.yaml").write_text(text)
        assert load_workflow(tmp_path / "wf.yaml").steps


SMALL = [  # (old, new, message): mutations of SMALL_WORKFLOW
    ("n_rows: 3", "n_rows: 0",
     "wf.yaml:8: steps[0].with.n_rows: setting of stage 'simulate_parallel_capture' Input should be greater than or "
     "equal to 1 (got 0) (fix: expected int ≥ 1)"),
    ("n_cols: 48", "n_cols: -48",
     "wf.yaml:9: steps[0].with.n_cols: setting of stage 'simulate_parallel_capture' Input should be greater than or "
     "equal to 1 (got -48) (fix: expected int ≥ 1)"),
    ("stop: 40", "stop: 1e300",
     "wf.yaml:7: steps[0].with.angles: setting of stage 'simulate_parallel_capture' angle sweep: the sweep would "
     "have 2e+299 angles (start 0, stop 1e+300, step 5); at most 100,000 are allowed: take a larger step or a "
     "narrower range (fix: expected AngleSweep)"),
    ("step: 5", "step: 0",
     "wf.yaml:7: steps[0].with.angles.step: setting of stage 'simulate_parallel_capture' Input should be greater "
     "than 0 (got 0) (fix: expected AngleSweep)"),
    ("stop: 40", "stop: 0",
     "wf.yaml:7: steps[0].with.angles: setting of stage 'simulate_parallel_capture' angle sweep: the sweep is "
     "empty: stop must be greater than start (start 0, stop 0, step 5) (fix: expected AngleSweep)"),
    ("step: 5", "step: 0.0001",
     "wf.yaml:7: steps[0].with.angles: setting of stage 'simulate_parallel_capture' angle sweep: the sweep would "
     "have 400,000 angles (start 0, stop 40, step 0.0001); at most 100,000 are allowed: take a larger step or a "
     "narrower range (fix: expected AngleSweep)"),
    ("min_signal: 1.0", "min_signal: -1.0",
     "wf.yaml:19: steps[1].with.min_signal: setting of stage 'absorption' Input should be greater than or equal to 0 "
     "(got -1.0) (fix: expected float ≥ 0)"),
    ("pixel_size: 1.0", "pixel_size: .nan",
     "wf.yaml:10: steps[0].with.pixel_size: setting of stage 'simulate_parallel_capture' Input should be a finite "
     "number (got nan) (fix: expected float > 0)"),
    ("radius: 20.0", "radius: .inf",
     "wf.yaml:11: steps[0].with.radius: setting of stage 'simulate_parallel_capture' Input should be a finite "
     "number (got inf) (fix: expected float > 0)"),
    ("radius: 20.0", "radius: 0",
     "wf.yaml:11: steps[0].with.radius: setting of stage 'simulate_parallel_capture' Input should be greater than 0 "
     "(got 0) (fix: expected float > 0)"),
    ("noise_std: 1.5", "noise_std: -1.5",
     "wf.yaml:14: steps[0].with.noise_std: setting of stage 'simulate_parallel_capture' Input should be greater than "
     "or equal to 0 (got -1.5) (fix: expected float ≥ 0)"),
    ("noise_std: 1.5", "skin_transmittance: 1.5",
     "wf.yaml:14: steps[0].with.skin_transmittance: setting of stage 'simulate_parallel_capture' Input should be "
     "less than or equal to 1 (got 1.5) (fix: expected float > 0, ≤ 1)"),
    ("noise_std: 1.5", "seed: -1",
     "wf.yaml:14: steps[0].with.seed: setting of stage 'simulate_parallel_capture' Input should be greater than or "
     "equal to 0 (got -1) (fix: expected int ≥ 0)"),
    ("noise_std: 1.5", "dark_level: 5000",
     "wf.yaml:6: steps[0].with: saturation_level (4095) must be above dark_level (5000) [counts]"),
    ("n_rows: 3\n      n_cols: 48", "n_rows: 100000\n      n_cols: 100000",
     "wf.yaml:6: steps[0].with: one render task (a frame of 100,000 × 100,000 px float32, about 13.1× that in "
     "working arrays) would take 488.0 GiB, more than 50% of this machine's memory (16.0 GiB) (fix: lower n_rows or "
     "n_cols)"),
]
HUGE_FRAME = SMALL[-1]


@pytest.mark.parametrize(("old", "new", "message"), SMALL, ids=[m[1].split("\n")[0] for m in SMALL])
def test_small_workflow_mutations_are_refused(tmp_path, workflow_text, old, new, message):
    assert_refused(tmp_path, _mutated(workflow_text, old, new), message)


def test_memory_message_names_this_machines_memory(tmp_path, workflow_text, monkeypatch):
    monkeypatch.setattr(constraints, "machine_memory", lambda: 256 * GIB)
    old, new, message = HUGE_FRAME
    assert_refused(tmp_path, _mutated(workflow_text, old, new), message.replace("(16.0 GiB)", "(256.0 GiB)"))


def test_frames_that_fit_are_not_refused(tmp_path, workflow_text):
    """256 × 4096 frames: eight per render task, 13.1 × 32 MiB = 419 MiB of working arrays, under 8 GiB."""
    path = tmp_path / "wf.yaml"
    path.write_text(_mutated(workflow_text, "n_rows: 3\n      n_cols: 48", "n_rows: 256\n      n_cols: 4096"))
    assert load_workflow(path).steps["capture"].settings.n_cols == 4096


SHIPPED = [  # (workflow, old, new, message)
    ("tomography-sim.yaml", "tv_weight: 0.02", "tv_weight: -1",
     "wf.yaml:48: steps[8].with.tv_weight: setting of stage 'reconstruct_tv' Input should be greater than or equal "
     "to 0 (got -1) (fix: expected float ≥ 0)"),
    ("tomography-sim.yaml", "max_iter: 150", "max_iter: 0",
     "wf.yaml:51: steps[8].with.max_iter: setting of stage 'reconstruct_tv' Input should be greater than or equal "
     "to 1 (got 0) (fix: expected int ≥ 1, ≤ 1e+06)"),
    ("tomography-sim.yaml", "tol: 0.001", "tol: 0",
     "wf.yaml:50: steps[8].with.tol: setting of stage 'reconstruct_tv' Input should be greater than 0 (got 0) "
     "(fix: expected float > 0)"),
    ("tomography-sim.yaml", "bound_slack: 0.1", "rho: 0",
     "wf.yaml:49: steps[8].with.rho: setting of stage 'reconstruct_tv' Input should be greater than 0 (got 0) "
     "(fix: expected float > 0)"),
    ("tomography-sim.yaml", "{rays: $rays, n_theta: 180, n_x: 128}", "{rays: $rays, n_theta: 1, n_x: 128}",
     "wf.yaml:36: steps[5].with.n_theta: setting of stage 'bin_sinogram' Input should be greater than or equal to "
     "2 (got 1) (fix: expected int ≥ 2 | None)"),
    ("tomography-sim.yaml", "{rays: $rays, n_theta: 180, n_x: 128}", "{rays: $rays, n_theta: 1000000, n_x: 1000000}",
     "wf.yaml:36: steps[5].with: one slice's binned sinogram (1,000,000 × 1,000,000 bins, sums and counts in "
     "float64) would take 14.6 TiB, more than 50% of this machine's memory (16.0 GiB) (fix: lower n_theta or n_x)"),
    ("tomography-sim.yaml", "{sinogram: $sinogram, hull: $hull, fill: linear}",
     "{sinogram: $sinogram, hull: $hull, fill: linear, n_pixels: 100000}",
     "wf.yaml:42: steps[7].with: one 100,000 × 100,000 px slice (float64) would take 74.5 GiB, more than 50% of this "
     "machine's memory (16.0 GiB) (fix: lower n_pixels)"),
    ("tomography-sim.yaml", "{sinogram: $sinogram, scene: scenes/gelatin-bin.yaml}",
     "{sinogram: $sinogram, scene: scenes/gelatin-bin.yaml, supersample: 100000}",
     "wf.yaml:54: steps[9].with: the truth raster's sample points (even the smallest (2 × 2 px) grid × 100000² "
     "samples, 3 float64 coordinates each) would take 894.1 GiB, more than 50% of this machine's memory (16.0 GiB) "
     "(fix: lower n_pixels or supersample)"),
    ("tomography-sim.yaml", "{capture: $capture, angle_index: 90}", "{capture: $capture, angle_index: -1}",
     "wf.yaml:57: steps[10].with.angle_index: setting of stage 'capture_figure' Input should be greater than or "
     "equal to 0 (got -1) (fix: expected int ≥ 0)"),
    ("tomography-sim.yaml", "angles: {start: 0, stop: 360, step: 1}", "angles: {start: 0, stop: 360, step: -1}",
     "wf.yaml:17: steps[0].with.angles.step: setting of stage 'acquire_tomography' Input should be greater than 0 "
     "(got -1) (fix: expected AngleSweep)"),
    ("tomography-setup.yaml", "n_x: 128", "n_x: 4096",
     "wf.yaml:11: steps[0].with: the projector's interpolation arrays (180 × 4,096 × 4,096 float32) would take "
     "11.2 GiB, more than 50% of this machine's memory (16.0 GiB) (fix: lower n_theta or n_x)"),
    ("tomography-setup.yaml", "light_angles: [0, 30, 60, 90, 120]", "light_angles: [0, 30, 200]",
     "wf.yaml:13: steps[0].with.light_angles[2]: setting of stage 'light_angle_study' Input should be less than or "
     "equal to 180 (got 200) (fix: expected tuple)"),
    ("tomography-setup.yaml", "light_angles: [0, 30, 60, 90, 120]", "light_angles: []",
     "wf.yaml:13: steps[0].with.light_angles: setting of stage 'light_angle_study' Tuple should have at least 1 item "
     "after validation, not 0 (fix: expected tuple)"),
    ("procam-sim.yaml", "exposures: [170, 340, 680, 1020]", "exposures: [0, 340, 680, 1020]",
     "wf.yaml:20: steps[0].with.exposures[0]: setting of stage 'acquire_scan_calibration' Input should be greater "
     "than 0 (got 0) (fix: expected tuple)"),
    ("procam-sim.yaml", "exposures: [170, 340, 680, 1020]", "exposures: []",
     "wf.yaml:20: steps[0].with.exposures: setting of stage 'acquire_scan_calibration' Tuple should have at least 1 "
     "item after validation, not 0 (fix: expected tuple)"),
    ("procam-sim.yaml", "delays: {start: 500, stop: 2000, step: 500}", "delays: {start: 2000, stop: 500, step: 500}",
     "wf.yaml:19: steps[0].with.delays: setting of stage 'acquire_scan_calibration' delays sweep: the sweep is "
     "empty: stop must be at least start (start 2000, stop 500, step 500) (fix: expected TimeSweep)"),
    ("procam-sim.yaml", "delays: {start: 500, stop: 2000, step: 500}", "delays: {start: 0, stop: 1e9, step: 1}",
     "wf.yaml:19: steps[0].with.delays: setting of stage 'acquire_scan_calibration' delays sweep: the sweep would "
     "have 1,000,000,000 delays (start 0, stop 1e+09, step 1); at most 100,000 are allowed: take a larger step or "
     "a narrower range (fix: expected TimeSweep)"),
    ("procam-sim.yaml", "sensor: [300, 400]\n  - id: scan_speed", "sensor: [0, 400]\n  - id: scan_speed",
     "wf.yaml:21: steps[0].with.sensor[0]: setting of stage 'acquire_scan_calibration' Input should be greater than "
     "or equal to 1 (got 0) (fix: expected tuple | None)"),
    ("procam-sim.yaml", "sensor: [300, 400]\n  - id: scan_speed", "sensor: [100000, 100000]\n  - id: scan_speed",
     "wf.yaml:16: steps[0].with: one camera frame (100,000 × 100,000 px float32) would take 37.3 GiB, more than 50% "
     "of this machine's memory (16.0 GiB) (fix: a smaller sensor [rows, cols])"),
    ("procam-sim.yaml", "page: [0.3, 0.8]", "page: [1.3, 0.8]",
     "wf.yaml:42: steps[4].with.pixels.page[0]: setting of stage 'delay_profile_figure' Input should be less than or "
     "equal to 1 (got 1.3) (fix: expected dict)"),
    ("procam-sim.yaml", "lines: [0.2, 0.4, 0.6, 0.8]", "lines: [0.2, -0.4]",
     "wf.yaml:48: steps[5].with.lines[1]: setting of stage 'relighting_figure' Input should be greater than or equal "
     "to 0 (got -0.4) (fix: expected tuple)"),
    ("procam-sim.yaml", "{capture: $stack, transport: $transport, half_width: 5}",
     "{capture: $stack, transport: $transport, half_width: -5}",
     "wf.yaml:51: steps[6].with.half_width: setting of stage 'epipolar_figure' Input should be greater than or equal "
     "to 0 (got -5) (fix: expected int ≥ 0)"),
    ("procam-sim.yaml", "{capture: $stack, scan_calibration: $scan_speed}",
     "{capture: $stack, scan_calibration: $scan_speed, max_iter: 0}",
     "wf.yaml:35: steps[3].with.max_iter: setting of stage 'demux_plane_to_ray' Input should be greater than or "
     "equal to 1 (got 0) (fix: expected int ≥ 1, ≤ 1e+06)"),
    ("procam-sim.yaml", "{capture: $stack, scan_calibration: $scan_speed}",
     "{capture: $stack, scan_calibration: $scan_speed, tol: 0}",
     "wf.yaml:35: steps[3].with.tol: setting of stage 'demux_plane_to_ray' Input should be greater than 0 (got 0) "
     "(fix: expected float > 0)"),
    ("procam-sim.yaml", "{capture: $stack, scan_calibration: $scan_speed}",
     "{capture: $stack, scan_calibration: $scan_speed, offsets: {start: -100000, stop: 100000}}",
     "wf.yaml:35: steps[3].with.offsets: setting of stage 'demux_plane_to_ray' offset grid: the sweep would have "
     "200,001 offsets (start -100000, stop 100000, step 1); at most 10,000 are allowed: take a larger step or a "
     "narrower range (fix: expected OffsetGrid | None)"),
    ("procam-full-sim.yaml", "lines: {start: 20, stop: 1260, step: 40}", "lines: {start: 20, stop: 1260, step: 0}",
     "wf.yaml:30: steps[2].with.lines.step: setting of stage 'acquire_full_transport' Input should be greater than 0 "
     "(got 0) (fix: expected PixelSweep)"),
    ("procam-full-sim.yaml", "lines: {start: 20, stop: 1260, step: 40}", "lines: {start: 20, stop: 1e12, step: 40}",
     "wf.yaml:30: steps[2].with.lines: setting of stage 'acquire_full_transport' lines sweep: the sweep would have "
     "25,000,000,000 lines (start 20, stop 1e+12, step 40); at most 100,000 are allowed: take a larger step or a "
     "narrower range (fix: expected PixelSweep)"),
]


@pytest.mark.parametrize(("workflow", "old", "new", "message"), SHIPPED,
                         ids=[f"{w.removesuffix('.yaml')}:{n.split(chr(10))[0]}" for w, _, n, _ in SHIPPED])
def test_shipped_workflow_mutations_are_refused(tmp_path, workflow, old, new, message):
    assert_refused(tmp_path, _mutated(_shipped(workflow), old, new), message)


SCENES = [  # (scene file, old, new, message): a scene broken under a shipped workflow that reads it
    ("tomography-sim.yaml", "gelatin-bin.yaml", "noise: {read_std: 2.0, gain: 1.0, seed: 0}",
     "noise: {read_std: 2.0, gain: 1.0, seed: -1}",
     "effects.noise.seed: Input should be greater than or equal to 0 (got -1)"),
    ("tomography-sim.yaml", "gelatin-bin.yaml", "sensor: {dark_level: 64, saturation_level: 4095, backlight: 2000}",
     "sensor: {dark_level: 64, saturation_level: 60, backlight: 2000}",
     "sensor: saturation_level (60) must be above dark_level (64) [counts]"),
    ("tomography-sim.yaml", "gelatin-bin.yaml", "fov: 14 deg", "fov: 180 deg",
     "camera.fov: Input should be less than 180 (got '180 deg')"),
    ("tomography-sim.yaml", "gelatin-bin.yaml", "rows: 120, cols: 320", "rows: 100000, cols: 100000",
     "the simulated camera's rays (100,000 × 100,000 px, 3 float64 coordinates each) would take 223.5 GiB, more "
     "than 50% of this machine's memory (16.0 GiB) (fix: lower camera.rows or camera.cols in the scene)"),
    ("procam-sim.yaml", "book-candle-mirrorball.yaml", "x: [0.12, 0.26]", "x: [0.26, 0.12]",
     "objects[2].region.x: [0.26, 0.12] is empty: the first edge must be below the second"),
]


@pytest.mark.parametrize(("workflow", "scene", "old", "new", "message"), SCENES, ids=[s[3] for s in SCENES])
def test_scene_mutations_are_refused(tmp_path, workflow, scene, old, new, message):
    shutil.copytree(WORKFLOWS / "scenes", tmp_path / "scenes")
    path = tmp_path / "scenes" / scene
    path.write_text(_mutated(path.read_text(), old, new))
    assert_refused(tmp_path, _shipped(workflow), message)


def test_hardware_rig_sizes_are_checked(tmp_path):
    rig = tmp_path / "rig.yaml"
    rig.write_text("stage: {url: /dev/null}\ncamera: {source: 0, width: 0, height: 1200}\n"
                   "geometry: {camera_model: orthographic, light_angle_deg: 45, length_unit: mm, pixel_size: 0.1}\n")
    text = ("workflow: hw\nsteps:\n  - id: capture\n    stage: acquire_tomography\n"
            "    with: {rig: hardware, hardware: rig.yaml, store: out/capture.zarr}\noutputs: {}\n")
    assert_refused(tmp_path, text, "camera.width: Input should be greater than 0 (got 0)")


# -- sweeps ------------------------------------------------------------------------------------------------

@pytest.mark.parametrize(("model", "bounds", "count"), [
    (AngleSweep, (0, 360, 1), 360), (AngleSweep, (0, 359.5, 0.5), 719), (AngleSweep, (-10, 10, 3), 7),
    (TimeSweep, (-1700, 1700, 170), 21), (TimeSweep, (500, 500, 1), 1), (PixelSweep, (20, 1260, 40), 32),
    (OffsetGrid, (-8, 8, 1), 17), (OffsetGrid, (0, 10, 3), 4),
])
def test_sweep_count_is_the_number_of_values(model, bounds, count):
    start, stop, step = bounds
    sweep = model(start=start, stop=stop, step=step)
    assert len(sweep.values()) == count
    assert sweep_count(start, stop, step, inclusive=model is not AngleSweep) == count


@pytest.mark.parametrize("model", [AngleSweep, TimeSweep, PixelSweep, OffsetGrid])
def test_every_sweep_refuses_empty_huge_and_backwards(model):
    cap = model.MAX_VALUES
    for start, stop, step, match in ((10, 0, 1, "the sweep is empty"), (0, 10 * cap, 1, "the sweep would have"),
                                     (0, 10, 0, "greater than 0"), (0, 10, -1, "greater than 0")):
        with pytest.raises(pydantic.ValidationError, match=match):
            model(start=start, stop=stop, step=step)
    model(start=0, stop=cap - 1, step=1)  # cap values (cap − 1 below stop for the exclusive angle sweep)
    if model is AngleSweep:
        with pytest.raises(pydantic.ValidationError, match="stop must be greater than start"):
            model(start=5, stop=5, step=1)


# -- every setting has a range ---------------------------------------------------------------------------

#: numeric settings that may legitimately be negative, each with the reason (``stage.setting`` or
#: ``Model.field`` for nested setting models)
SIGNED = {
    "render_appearance.light": "a direction towards the light: each component has either sign",
    "demux_plane_to_ray.sync_offset_us": "t_o, true minus commanded delay: the trigger may lead or lag",
    "demux_full.sync_offset_us": "t_o, true minus commanded delay: the trigger may lead or lag",
    "AngleSweep.start": "a stage angle: a sweep may start below 0°",
    "AngleSweep.stop": "a stage angle: a sweep may end at or below 0° when it starts below",
    "TimeSweep.start": "a sync delay: negative delays expose before the projector's row (procam workflows sweep ±)",
    "TimeSweep.stop": "a sync delay: a sweep may end before VSYNC",
    "PixelSweep.start": "a line centre: a line may sit partly beyond the projector's left edge",
    "PixelSweep.stop": "a line centre: a line may sit partly beyond the projector's edge",
    "OffsetGrid.start": "an offset, projector row − camera row, has either sign",
    "OffsetGrid.stop": "an offset, projector row − camera row, has either sign",
    "RodSpec.x": "a rod's centre in the object frame: either side of the rotation axis",
    "volume_figure.at": "a point (x, y, z) in the object frame: either side of the axis, above or below z = 0",
    "RodSpec.y": "a rod's centre in the object frame: either side of the rotation axis",
}


def _bounds(items) -> list:
    out = []
    for item in items:
        out += item.metadata if isinstance(item, pydantic.fields.FieldInfo) else [item]
    return out


def _unbounded(annotation, metadata: list, where: str, seen: set) -> list[str]:
    """Every int or float inside ``annotation`` (through Optional, Annotated, tuples, dicts and nested models)
    without a lower bound, as ``stage.setting`` or ``Model.field`` (each nested model walked once)."""
    origin, args = typing.get_origin(annotation), typing.get_args(annotation)
    if origin is typing.Annotated:
        return _unbounded(args[0], metadata + _bounds(annotation.__metadata__), where, seen)
    if origin in (typing.Union, types.UnionType):
        return [w for a in args if a is not type(None) for w in _unbounded(a, metadata, where, seen)]
    if origin in (tuple, list):
        return [w for a in args if a is not Ellipsis for w in _unbounded(a, [], where, seen)]
    if origin is dict:
        return _unbounded(args[1], [], where, seen)
    if isinstance(annotation, type) and issubclass(annotation, pydantic.BaseModel):
        if annotation in seen:
            return []
        seen.add(annotation)
        return [w for name, f in annotation.model_fields.items()
                for w in _unbounded(f.annotation, list(f.metadata), f"{annotation.__name__}.{name}", seen)]
    if annotation in (int, float) and not any(isinstance(m, Ge | Gt) for m in metadata):
        return [where]
    return []


def test_every_numeric_setting_has_a_lower_bound_or_is_signed():
    seen: set = set()
    found = [w for s in default_registry() for name, f in s.params.model_fields.items()
             for w in _unbounded(f.annotation, list(f.metadata), f"{s.name}.{name}", seen)]
    unexplained = sorted(set(found) - set(SIGNED))
    assert not unexplained, (f"settings without a range: {unexplained}; constrain them (pipeline.constraints) "
                             "or add them to SIGNED with the reason they may be negative")
    assert sorted(set(SIGNED) - set(found)) == [], "SIGNED names settings that no longer exist or are now bounded"


def test_walker_finds_an_unconstrained_setting():
    from selpath.pipeline.registry import _build_stage

    def plugin(*, passes: int = 1, sigma: float | None = None, sizes: tuple[int, int] = (1, 1)):
        """A stage whose author forgot the ranges."""

    stage = _build_stage("plugin", plugin, None, None)
    found = [w for name, f in stage.params.model_fields.items()
             for w in _unbounded(f.annotation, list(f.metadata), f"plugin.{name}", set())]
    assert sorted(set(found)) == ["plugin.passes", "plugin.sigma", "plugin.sizes"]
