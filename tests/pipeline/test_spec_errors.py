"""Every workflow error, one mutation of a valid file per case, asserting the message (npe2's mutator pattern)."""

from __future__ import annotations

import re

import numpy as np
import pytest
import xarray as xr

from selpath.pipeline import FORMAT_VERSION, SpecError, load_workflow, to_store


def _load(tmp_path, text):
    path = tmp_path / "wf.yaml"
    path.write_text(text)
    return load_workflow(path), path


def _errors(tmp_path, text) -> tuple[str, SpecError]:
    path = tmp_path / "wf.yaml"
    path.write_text(text)
    with pytest.raises(SpecError) as info:
        load_workflow(path)
    return str(info.value), info.value


def test_valid_workflow_loads_in_dependency_order(tmp_path, workflow_text):
    workflow, _ = _load(tmp_path, workflow_text)
    assert list(workflow.steps) == ["capture", "absorption"]
    assert workflow.outputs["capture"].store == str((tmp_path / "out" / "capture.zarr").resolve())
    assert workflow.steps["capture"].settings.rods[0].sigma == 0.05


def test_steps_may_be_listed_in_any_order(tmp_path, workflow_text):
    reordered = workflow_text.split("steps:\n")
    head, rest = reordered
    steps_text, outputs_text = rest.split("outputs:\n")
    capture, absorption = steps_text.split("  - id: absorption\n")
    text = head + "steps:\n  - id: absorption\n" + absorption + capture + "outputs:\n" + outputs_text
    workflow, _ = _load(tmp_path, text)
    assert list(workflow.steps) == ["capture", "absorption"]


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("stage: absorption", "stage: absorbtion",
         r"wf.yaml:16: steps\[1\].stage: unknown stage 'absorbtion' \(fix: did you mean 'absorption'"),
        ("min_signal: 1.0", "min_signl: 1.0",
         r"wf.yaml:19: steps\[1\].with.min_signl: stage 'absorption' has no parameter 'min_signl' "
         r"\(fix: did you mean 'min_signal'"),
        ("n_cols: 48", "n_cols: forty-eight",
         r"wf.yaml:9: steps\[0\].with.n_cols: setting of stage 'simulate_parallel_capture' Input should be a "
         r"valid integer \(got 'forty-eight'\) \(fix: expected int ≥ 1\)"),
        ("n_cols: 48", "n_cols: 48.5", r"steps\[0\].with.n_cols: .*valid integer \(got 48.5\)"),
        ("- {x: 6.0, y: 3.0, radius: 4.0, sigma: 0.05}", "- {x: 6.0, y: 3.0, radius: 4.0}",
         r"wf.yaml:13: steps\[0\].with.rods\[0\].sigma: setting of stage 'simulate_parallel_capture' is required"),
        ("capture: $capture\n", "capture: $captur\n",
         r"wf.yaml:18: steps\[1\].with.capture: reference \$captur names no step \(fix: did you mean 'capture'"),
        ("capture: $capture\n", "capture: capture.zarr\n",
         r"steps\[1\].with.capture: data input 'capture' of stage 'absorption' takes a reference, got 'capture.zarr'"),
        ("      capture: $capture\n", "",
         r"wf.yaml:17: steps\[1\].with: data input 'capture' of stage 'absorption' is missing"),
        ("min_signal: 1.0", "min_signal: $capture",
         r"steps\[1\].with.min_signal: setting 'min_signal' takes a value, not a reference"),
        ("- id: absorption", "- id: capture",
         r"wf.yaml:15: steps\[1\].id: duplicate step id 'capture' \(also steps\[0\]\)"),
        ("{from: absorption,", "{from: absorbtion,",
         r"wf.yaml:22: outputs.absorption.from: output 'absorption' comes from unknown step 'absorbtion'"),
        ("store: out/absorption.zarr", "store: out/capture.zarr",
         r"wf.yaml:22: outputs.absorption.store: store 'out/capture.zarr' is also written by output 'capture'"),
        ("scheduler: synchronous", "scheduler: gpu",
         r"wf.yaml:2: scheduler: must be one of synchronous, threads, processes or a tcp://"),
        ("workflow: small-absorption\n", "", r"wf.yaml:1: workflow: is required but missing"),
        ("    with:\n      capture", "    wiht:\n      capture", r"steps\[1\].wiht: is not a known field"),
        ("step: 5}", "step: -5}", r"steps\[0\].with.angles.step: .*greater than 0"),
    ],
)
def test_one_mutation_one_exact_error(tmp_path, workflow_text, old, new, expected):
    assert old in workflow_text
    message, _ = _errors(tmp_path, workflow_text.replace(old, new, 1))
    assert re.search(expected, message), message


def test_every_problem_is_reported_at_once(tmp_path, workflow_text):
    text = (workflow_text.replace("stage: absorption", "stage: absorbtion")
            .replace("n_cols: 48", "n_cols: many").replace("{from: capture,", "{from: captur,"))
    message, error = _errors(tmp_path, text)
    assert len(error.problems) == 3, message
    assert message.startswith("3 problems in the workflow:")


def test_cycle_is_named(tmp_path, workflow_text):
    text = workflow_text.replace("stage: simulate_parallel_capture\n    with:\n",
                                  "stage: absorption\n    with:\n      capture: $absorption\n")
    text = "\n".join(line for line in text.splitlines() if "angles" not in line and "n_rows" not in line
                     and "n_cols" not in line and "pixel_size" not in line and "radius: 20" not in line
                     and "rods" not in line and "sigma: 0.05" not in line and "noise_std" not in line) + "\n"
    message, _ = _errors(tmp_path, text)
    assert re.search(r"steps form a cycle: \$capture -> \$absorption", message), message


def test_yaml_syntax_error_has_a_line(tmp_path, workflow_text):
    message, _ = _errors(tmp_path, workflow_text.replace("n_rows: 3", "n_rows: [3"))
    assert re.search(r"wf.yaml:\d+: not valid YAML", message), message


def test_yaml_cannot_construct_python_objects(tmp_path, workflow_text):
    message, _ = _errors(tmp_path, workflow_text.replace("n_rows: 3", "n_rows: !!python/object/apply:os.system [ls]"))
    assert "not valid YAML" in message and "python/object/apply" in message


def test_missing_file():
    with pytest.raises(SpecError, match=r"no-such.yaml: no such workflow file"):
        load_workflow("no-such.yaml")


LOAD = """\
workflow: from-store
steps:
  - id: capture
    stage: load_store
    with: {{store: {store}}}
  - id: absorption
    stage: absorption
    with: {{capture: $capture}}
"""


def _capture(**changes) -> xr.Dataset:
    frames = np.full((2, 3, 4), 100.0, dtype=np.float32)
    ds = xr.Dataset({"target": (("angle", "row", "col"), frames), "reference": (("angle", "row", "col"), frames)},
                    coords={"angle": ("angle", [0.0, 1.0], {"units": "degree"})},
                    attrs={"camera_model": "orthographic", "pixel_size": 0.1, "light_angle_deg": 0.0,
                           "length_unit": "mm"})
    return ds


def test_input_store_with_wrong_units_fails_validation(tmp_path):
    ds = _capture()
    to_store(ds, tmp_path / "cap.zarr", "tomography_capture")
    good = LOAD.format(store="cap.zarr")
    _load(tmp_path, good)
    import zarr

    zarr.open_group(tmp_path / "cap.zarr", mode="r+")["angle"].attrs["units"] = "rad"
    message, _ = _errors(tmp_path, good)
    assert re.search(r"wf.yaml:5: steps\[0\].with: .*cap.zarr: coordinate 'angle' is in 'rad'; expected one of "
                     r"\[degree\]", message), message


def test_input_store_from_a_newer_format_fails_validation(tmp_path):
    to_store(_capture(), tmp_path / "cap.zarr", "tomography_capture")
    import zarr

    zarr.open_group(tmp_path / "cap.zarr", mode="r+").attrs["selpath_format"] = 99
    message, _ = _errors(tmp_path, LOAD.format(store="cap.zarr"))
    assert re.search(rf"format 99 is newer than this selpath reads \(format {FORMAT_VERSION}\) \(fix: upgrade selpath",
                     message)


def test_input_store_with_wrong_dims_fails_validation(tmp_path):
    ds = _capture().transpose("row", "angle", "col")
    with pytest.raises(Exception, match=r"variable 'target' has dims \('row', 'angle', 'col'\)"):
        to_store(ds, tmp_path / "cap.zarr", "tomography_capture")
    message, _ = _errors(tmp_path, LOAD.format(store="missing.zarr"))
    assert re.search(r"missing.zarr: no store at this path", message), message


def test_a_variable_reference_is_checked_against_the_input_store(tmp_path):
    """`$capture.nonexistent` passed validation and failed only at run time; the store's variables are known."""
    to_store(_capture(), tmp_path / "cap.zarr", "tomography_capture")
    text = LOAD.format(store="cap.zarr").replace("{capture: $capture}", "{capture: $capture.targett}")
    message, _ = _errors(tmp_path, text)
    assert re.search(r"wf.yaml:8: steps\[1\].with.capture: \$capture.targett names no variable of step 'capture' "
                     r"\(it has reference, target\) \(fix: did you mean 'target'\?\)", message), message


def test_a_yaml_bomb_is_refused_in_well_under_a_second(tmp_path):
    """445 bytes of nested aliases took 99 s and 9.2 GB to validate; two more levels never finished."""
    import time

    levels = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    levels += [f"a{i}: &a{i} [{', '.join([f'*a{i - 1}'] * 10)}]" for i in range(1, 12)]
    text = "\n".join(levels) + "\nworkflow: bomb\nsteps: [{id: s, stage: load_store, with: {store: *a11}}]\n"
    start = time.perf_counter()
    message, _ = _errors(tmp_path, text)
    assert time.perf_counter() - start < 1.0
    assert re.search(r"wf.yaml:\d+: the document expands to more than 100,000 nodes through its aliases", message)


def test_a_binary_file_is_not_a_workflow(tmp_path):
    path = tmp_path / "wf.yaml"
    path.write_bytes(b"workflow: x\n\xff\xfe\x00\x01binary")
    with pytest.raises(SpecError, match=r"wf.yaml:2: not UTF-8 text \(byte 0xff at offset 12\): a workflow file is "
                                        r"YAML text"):
        load_workflow(path)


@pytest.mark.parametrize("value", [".nan", ".inf", "-.inf", "1e999"])
def test_non_finite_settings_are_refused(tmp_path, workflow_text, value):
    """`.nan` as a setting passed validation and switched checks off (NaN compares false)."""
    message, _ = _errors(tmp_path, workflow_text.replace("min_signal: 1.0", f"min_signal: {value}"))
    assert re.search(r"wf.yaml:\d+: steps\[1\].with.min_signal: setting of stage 'absorption' Input should be a "
                     r"(finite|valid) number", message), message
