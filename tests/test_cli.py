"""The command line, driven as a user would (typer's runner)."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

import selpath
from selpath.pipeline import FORMAT_VERSION
from selpath.pipeline.cli import app

runner = CliRunner()


def test_validate_ok_and_every_problem(small_workflow):
    ok = runner.invoke(app, ["validate", str(small_workflow)])
    assert ok.exit_code == 0 and "ok: small-absorption: 2 steps" in ok.output
    small_workflow.write_text(small_workflow.read_text().replace("stage: absorption", "stage: absorb")
                              .replace("n_rows: 3", "n_rows: three"))
    bad = runner.invoke(app, ["validate", str(small_workflow)])
    assert bad.exit_code == 2
    assert "2 problems in the workflow" in bad.output
    assert re.search(r"small.yaml:16: steps\[1\].stage: unknown stage 'absorb'", bad.output.replace("\n", ""))


def test_run_then_inspect(small_workflow):
    first = runner.invoke(app, ["run", str(small_workflow), "--no-progress"])
    assert first.exit_code == 0, first.output
    assert "computed" in first.output and "wrote" in first.output
    # one heading per step, with its reason, before it runs; the reason is not repeated in the closing table
    assert first.output.count("no finished output at") == 2, first.output
    headings = [first.output.index(f"── {step}") for step in ("capture (simulate_parallel_capture)",
                                                               "absorption (absorption)")]
    assert headings == sorted(headings)
    second = runner.invoke(app, ["run", str(small_workflow), "--no-progress"])
    assert "reused" in second.output and "computed" not in second.output
    store = small_workflow.parent / "out" / "absorption.zarr"
    shown = runner.invoke(app, ["inspect", str(store)], env={"COLUMNS": "200"})
    assert shown.exit_code == 0, shown.output
    assert f"absorption store, format {FORMAT_VERSION}" in shown.output
    assert "workflow: small-absorption" in shown.output
    assert "angle (angle) float64 [degree]: " in shown.output  # coordinates with units and range
    # each variable with its units and valid share, against a count of the store's own finite values
    from selpath.pipeline.store import open_store

    ds = open_store(store)
    finite = float(np.isfinite(ds["absorption"]).mean())
    assert f"absorption (angle, row, col) float32 [1]: {finite:.1%} finite" in shown.output
    assert f"flags (angle, row, col) uint8: valid {float((ds['flags'] == 0).mean()):.1%}" in shown.output
    assert f"signal_fraction () float64 [1] = {float(ds['signal_fraction']):.6g}" in shown.output
    missing = runner.invoke(app, ["inspect", str(small_workflow.parent / "nothing.zarr")])
    assert missing.exit_code == 2 and "no store at this path" in missing.output


def test_stages_lists_settings_with_units():
    listed = runner.invoke(app, ["stages", "absorption"], env={"COLUMNS": "200"})
    assert listed.exit_code == 0
    assert "min_signal" in listed.output and "[counts]" in listed.output and "float > 0 | None = None" in listed.output
    assert "float ≥ 0, ≤ 1" in listed.output  # the range of min_signal_relative
    assert "``" not in listed.output and ":func:" not in listed.output  # docstring markup rendered as text
    assert "capture  required" in listed.output  # inputs too
    short = runner.invoke(app, ["stages"], env={"COLUMNS": "200"})
    from selpath.pipeline.registry import default_registry

    assert all(s.name in short.output for s in default_registry())
    assert len(short.output.splitlines()) < 2 * len(default_registry().names()) + 10  # one line per stage
    unknown = runner.invoke(app, ["stages", "nope"])
    assert unknown.exit_code == 2 and "unknown stage 'nope'" in unknown.output


@pytest.mark.slow
def test_demo_acquires_on_the_simulated_rig_into_its_own_folder(tmp_path):
    """`selpath demo` end to end (about 150 s): the tomography workflow (acquisition, processing, FBP and the
    optimisation) and the projector–camera one (calibration, stack, demultiplexing, figures) land under
    --out with their reports; the optimisation beats FBP against the scene's truth; the calibrated scan
    speed is within 1 % of the rig's 1/17 rows/µs; a second run reuses all."""
    out = tmp_path / "demo"
    first = runner.invoke(app, ["demo", "--out", str(out)], env={"COLUMNS": "200"})
    assert first.exit_code == 0, first.output
    assert (out / "capture.zarr").is_dir() and (out / "absorption.zarr").is_dir()
    # summaries over the object: the background (off the backlit silhouette) is flagged, so max A is the object's
    match = re.search(r"absorption: ([\d.]+)% of object pixels valid \(([\d.]+)% of pixels off the object, "
                      r"flagged background\), max A on the object = ([\d.]+)", " ".join(first.output.split()))
    assert match and 90 < float(match[1]) <= 100 and 5 < float(match[2]) < 50 and float(match[3]) < 1.5, match
    rmse = {m[1]: float(m[2]) for m in re.finditer(r"(fbp|optimised): RMSE ([\d.e+-]+)", first.output)}
    assert rmse["optimised"] < rmse["fbp"], rmse
    page = (out / "report.html").read_text()
    assert page.count("<img src='data:image/png;base64,") == 5 and "optimised: RMSE" in page
    assert (out / "transport.zarr").is_dir() and (out / "delay-profiles.png").is_file()
    speed = re.search(r"v_p = ([\d.]+) rows/µs", first.output)
    assert speed and abs(float(speed[1]) * 17 - 1) < 0.01
    converged = re.search(r"([\d.]+)% converged", first.output)
    assert converged and float(converged[1]) > 90
    procam_page = (out / "procam-report.html").read_text()
    assert procam_page.count("<img src='data:image/png;base64,") >= 3 and "plane-to-ray transport" in procam_page
    second = runner.invoke(app, ["demo", "--out", str(out)], env={"COLUMNS": "200"})
    assert second.exit_code == 0 and "computed" not in second.output
    _every_store_carries_its_kinds_metadata(out)
    for report in ("report.html", "procam-report.html"):
        _every_figure_loads(out / report)
    _the_readmes_accessor_tour_runs_on_the_demo(out)


def _the_readmes_accessor_tour_runs_on_the_demo(out):
    """The exploring tutorial's ``.selpath`` block (docs/tutorials/exploring.md), as a user pastes it, on the demo's
    stores (its paths made the test's)."""
    text = (Path(__file__).resolve().parents[1] / "docs" / "tutorials" / "exploring.md").read_text()
    block = text.split("DataArray (`selpath.explore.accessor`")[1].split("```python")[1].split("```")[0]
    namespace = {"selpath": selpath}
    exec(block.replace("selpath-demo/", f"{out}/"), namespace)  # the README's own code
    assert namespace["p"].attrs["units"] == "counts" and namespace["p"]["sync_delay"].attrs["units"] == "us"


def _every_figure_loads(page):
    """Each figure of a report decodes to a non-blank image of the size of its PNG beside the stores, and, where a
    Chromium is installed, loads in the headless browser at that size (its naturalWidth × naturalHeight)."""
    import base64
    import io
    import shutil
    import subprocess

    import matplotlib.image

    text = page.read_text()
    shapes = []
    for data in re.findall(r"<img src='data:image/png;base64,([^']+)'", text):
        image = matplotlib.image.imread(io.BytesIO(base64.b64decode(data)), format="png")
        assert image.shape[0] >= 200 and image.shape[1] >= 400 and float(image[..., :3].std()) > 0.01, page
        shapes.append(f"{image.shape[1]}x{image.shape[0]}")
    captions = re.findall(r"<figcaption><b>[^<]+</b> \([^)]+\)\. ([^<]*)</figcaption>", text)
    assert shapes and len(captions) == len(shapes) and all(len(c) > 100 and "Fig." in c for c in captions), captions
    browser = next((shutil.which(b) for b in ("chromium", "chromium-browser", "google-chrome") if shutil.which(b)),
                   None)
    if browser is None:
        return
    probe = page.with_name("probe.html")
    probe.write_text(text.replace("</body>", "<script>window.addEventListener('load', () => document.body."
                                  "setAttribute('data-images', [...document.images].map(i => i.naturalWidth + 'x' + "
                                  "i.naturalHeight).join(',')))</script></body>"))
    shown = subprocess.run([browser, "--headless", "--no-sandbox", "--disable-gpu", "--virtual-time-budget=10000",
                            "--dump-dom", probe.as_uri()], capture_output=True, text=True, timeout=180)
    assert re.findall(r'data-images="([^"]*)"', shown.stdout) == [",".join(shapes)], shown.stderr[-500:]


def _every_store_carries_its_kinds_metadata(folder):
    """Each store the shipped demo writes opens (its units checked against its kind), every variable its kind
    declares has the kind's units and long name, and no other variable borrowed a coordinate's."""
    from selpath.pipeline.registry import default_registry
    from selpath.pipeline.store import open_store

    stores = sorted(folder.glob("*.zarr"))
    assert len(stores) >= 20
    for path in stores:
        ds = open_store(path)
        kind = ds.attrs["selpath_kind"]
        for name, (units, long_name) in default_registry().kinds[kind].metadata(ds).items():
            assert (ds[name].attrs.get("units"), ds[name].attrs.get("long_name")) == (units, long_name), (path, name)
        for name, var in ds.data_vars.items():
            for coord in ds.coords.values():
                if name != coord.name and coord.attrs.get("long_name"):
                    assert var.attrs.get("long_name") != coord.attrs["long_name"], (path, name, coord.name)


@pytest.mark.parametrize("command", ["run", "demo", "inspect", "stages", "validate", "workflows", "schema"])
def test_help_is_rendered_not_raw(command):
    """Every flag showed `<bool>`, `demo --help` showed ``--out`` literally."""
    shown = runner.invoke(app, [command, "--help"], env={"COLUMNS": "120"})
    assert shown.exit_code == 0
    assert "<bool>" not in shown.output and "``" not in shown.output and ":func:" not in shown.output


def test_errors_keep_bracketed_text_and_never_show_a_traceback(tmp_path, monkeypatch):
    """Rich markup ate `[degree]` in errors ("expected one of  (fix…)"); an unexpected exception printed a
    traceback. Both now reach the user as one plain message."""
    import selpath.pipeline.spec as spec

    store = tmp_path / "x.zarr"
    shown = runner.invoke(app, ["inspect", str(store)])
    assert shown.exit_code == 2 and "no store at this path" in shown.output

    def broken(*args, **kwargs):
        raise ValueError("units must be one of [degree] or [rad]")

    monkeypatch.setattr(spec, "load_workflow", broken)  # the command imports it when it runs
    result = runner.invoke(app, ["validate", str(tmp_path / "wf.yaml")])
    assert result.exit_code == 3 and "Traceback" not in result.output
    assert "unexpected ValueError: units must be one of [degree] or [rad] (this is a bug" in result.output.replace(
        "\n", " ")


def test_paths_with_brackets_print_as_they_are(tmp_path, workflow_text):
    """A workflow under `d[/x]` wrote its store, then rich read `[/x]` as markup and printed a traceback."""
    folder = tmp_path / "d[" / "x]"
    folder.mkdir(parents=True)
    (folder / "small.yaml").write_text(workflow_text)
    for command in (["validate"], ["run", "--no-progress"]):
        result = runner.invoke(app, [command[0], str(folder / "small.yaml"), *command[1:]], env={"COLUMNS": "300"})
        assert result.exit_code == 0, result.output
        assert "d[/x]/out/capture.zarr" in result.output.replace("\n", "")


def test_a_report_never_replaces_a_file_selpath_did_not_write(tmp_path, small_workflow):
    from selpath.pipeline import StoreError, load_workflow
    from selpath.pipeline.engine import RunReport
    from selpath.pipeline.report import write_html

    page = tmp_path / "report.html"
    page.write_text("my own notes")
    with pytest.raises(StoreError, match="a report would replace this file, which selpath did not write"):
        write_html(load_workflow(small_workflow), RunReport("small"), page)
    assert page.read_text() == "my own notes"
    page.unlink()
    for _ in range(2):  # its own report it replaces
        write_html(load_workflow(small_workflow), RunReport("small"), page)
    assert 'content="selpath"' in page.read_text()


def test_shipped_workflows_are_listed_and_copied_with_their_scenes(tmp_path):
    from selpath import workflows

    listed = runner.invoke(app, ["workflows"], env={"COLUMNS": "80"})
    assert listed.exit_code == 0 and all(name in listed.output for name in workflows.names())
    # one line each, starting with the name and saying what it does, in the file's own words
    lines = {line.split()[0]: line for line in listed.output.splitlines() if line.split() and
             line.split()[0] in workflows.names()}
    assert set(lines) == set(workflows.names())
    assert "Thesis §4.4.3: any convex shape works" in lines["tomography-triangle"]
    assert "Optical tomography on the simulated rig (thesis §4.4.2)" in lines["tomography-sim"]
    assert workflows.describe("procam-rectify-sim") == "Are the sync rows epipolar?"
    copied = runner.invoke(app, ["workflows", "--copy", str(tmp_path / "mine")])
    assert copied.exit_code == 0, copied.output
    assert "procam-materials-apply" in listed.output and "(run procam-materials first)" in listed.output
    for name in workflows.names():  # a copy validates where it lies: its scenes came along
        ok = runner.invoke(app, ["validate", str(tmp_path / "mine" / f"{name}.yaml")])
        if name in workflows.AFTER:  # it reads a store the other writes, which does not exist yet
            assert ok.exit_code == 2 and "no store at this path" in ok.output and "run the step that writes it" in \
                ok.output.replace("\n", " "), ok.output
            continue
        assert ok.exit_code == 0, ok.output
    again = runner.invoke(app, ["workflows", "--copy", str(tmp_path / "mine")])
    assert again.exit_code == 2 and "already holds" in again.output


def test_a_shipped_name_is_not_run_in_place_and_copy_needs_a_folder(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    named = runner.invoke(app, ["run", "tomography-sim"])
    assert named.exit_code == 2 and "selpath workflows --copy DIR" in named.output.replace("\n", " ")
    (tmp_path / "file").write_text("mine")
    onto = runner.invoke(app, ["workflows", "--copy", str(tmp_path / "file")])
    assert onto.exit_code == 2 and "is a file" in onto.output
    assert (tmp_path / "file").read_text() == "mine"


def test_version_short_stage_list_and_plural(small_workflow):
    from importlib.metadata import version

    shown = runner.invoke(app, ["--version"])
    assert shown.exit_code == 0 and shown.output.strip() == f"selpath {version('selpath')}"
    listed = runner.invoke(app, ["stages"], env={"COLUMNS": "80"})
    from selpath.pipeline.registry import default_registry

    names = [s.name for s in default_registry()]
    # piped (not a terminal): one plain line a stage, name, module and summary split by tabs, however narrow
    rows = [line.split("\t") for line in listed.output.splitlines()]
    assert listed.exit_code == 0 and [r[0] for r in rows] == names and all(len(r) == 3 for r in rows)
    assert dict((r[0], r[1]) for r in rows)["absorption"] == "tomography.calibrate"
    assert "settings" not in listed.output  # no settings without NAME or --all
    full = runner.invoke(app, ["stages", "--all"], env={"COLUMNS": "300"})
    assert sum(line.strip().startswith("inputs (data") for line in full.output.splitlines()) == sum(
        bool(s.inputs) for s in default_registry())
    small_workflow.write_text(small_workflow.read_text().replace(
        "  - id: absorption\n    stage: absorption\n    with:\n      capture: $capture\n      min_signal: 1.0\n", "")
        .replace("  absorption: {from: absorption, store: out/absorption.zarr}\n", ""))
    one = runner.invoke(app, ["validate", str(small_workflow)])
    assert one.exit_code == 0 and "1 step, outputs" in one.output, one.output


@pytest.mark.parametrize("kind", ["plane_to_ray_capture", "checkerboard_capture"])
def test_validate_refuses_a_capture_that_does_not_say_where_its_sensor_clips(tmp_path, kind):
    """#30: a capture without saturation_counts and dark_level_counts passed `selpath validate`, then failed at
    run time (or, for checkerboards, took clipped frames as data). Validation now names both attrs."""
    import xarray as xr

    if kind == "plane_to_ray_capture":
        ds = xr.Dataset({"image": (("delay", "exposure", "row", "col"), np.zeros((2, 1, 3, 4), np.float32),
                                   {"units": "counts"})},
                        coords={"delay": ("delay", [0.0, 17.0], {"units": "us"}),
                                "exposure": ("exposure", [170.0], {"units": "us"})},
                        attrs={"scan_speed_px_per_us": 1 / 17, "line_time_us": 17.0})
        step = "{id: t, stage: demux_plane_to_ray, with: {capture: $c}}"
    else:
        ds = xr.Dataset({"image": (("shift", "row", "col"), np.zeros((2, 3, 4), np.float32), {"units": "counts"})},
                        coords={"shift": ("shift", [0, 1], {"units": "1"})},
                        attrs={"square_px": [8, 8], "mode": "floodlit", "shifts_rows": [0, 4], "shifts_cols": [0, 4]})
        step = "{id: t, stage: separate_direct_global, with: {capture: $c}}"
    ds.assign_attrs(selpath_format=FORMAT_VERSION, selpath_kind=kind).to_zarr(tmp_path / "c.zarr", consolidated=False)
    (tmp_path / "wf.yaml").write_text("workflow: clip\nsteps:\n  - {id: c, stage: load_store, with: {store: c.zarr}}"
                                      f"\n  - {step}\n")
    result = runner.invoke(app, ["validate", str(tmp_path / "wf.yaml")], env={"COLUMNS": "300"})
    assert result.exit_code != 0, result.output
    output = result.output.replace("\n", "")
    assert "attr 'saturation_counts' is missing" in output and "attr 'dark_level_counts' is missing" in output
