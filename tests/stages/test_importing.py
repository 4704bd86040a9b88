"""Importing captures made elsewhere (#24 item 1): frames from TIFF folders, .npz, HDF5 and .npy plus an import
spec become the same capture store the rig would have written; bad specs and frames are named."""

from __future__ import annotations

import h5py
import numpy as np
import pytest
import tifffile
import xarray as xr
import yaml
from typer.testing import CliRunner

from selpath.pipeline import ConfigError, StageError, load_workflow, open_store, run_workflow
from selpath.pipeline.cli import app
from selpath.pipeline.errors import StoreError
from selpath.stages.frame_files import read_frames
from selpath.stages.importing import import_capture
from tests.helpers.acquisition import make_workflow

runner = CliRunner()


@pytest.fixture(scope="module")
def original(tmp_path_factory) -> xr.Dataset:
    """A simulated tomography capture (the acquisition's own store), loaded."""
    folder = tmp_path_factory.mktemp("rig")
    run_workflow(load_workflow(make_workflow(folder)), progress=False)
    return open_store(folder / "capture.zarr").load()


def _export(ds: xr.Dataset, folder) -> dict:
    """The capture as a lab might hold it: target as one TIFF per angle (names that sort wrongly as text),
    reference as an .npz member, backlit in an HDF5 file, dark as .npy; and its import spec (a renderer's
    convention: pixel centres at j + 0.5)."""
    (folder / "target").mkdir()
    for i, frame in enumerate(ds["target"].values):
        tifffile.imwrite(folder / "target" / f"frame_{i}.tif", frame)
    np.savez(folder / "reference.npz", frames=ds["reference"].values, other=np.zeros(3))
    with h5py.File(folder / "scan.h5", "w") as handle:
        handle.create_dataset("/scan/backlit", data=ds["backlit"].values)
    np.save(folder / "dark.npy", ds["dark"].values)
    angles = ds["angle"].values
    keep = ("camera_model", "light_angle_deg", "length_unit", "focal_length_px", "camera_distance",
            "light_kind", "beam_height", "saturation_counts")  # no light_distance: a collimated beam has none
    spec = {"kind": "tomography_capture",
            "frames": {"target": "target", "reference": "reference.npz:frames", "backlit": "scan.h5:/scan/backlit",
                       "dark": "dark.npy"},
            "angles_deg": {"start_deg": float(angles[0]), "step_deg": float(angles[1] - angles[0]),
                           "count": int(angles.size)},
            "pixel_centres": "half",
            "principal_point_px": [float(v) + 0.5 for v in ds.attrs["principal_point_px"]],
            **{k: ds.attrs[k] for k in keep}}
    (folder / "spec.yaml").write_text(yaml.safe_dump(spec, sort_keys=False))
    return spec


def test_a_tomography_capture_from_four_file_formats_imports_as_the_rig_wrote_it(original, tmp_path):
    _export(original, tmp_path)
    shown = runner.invoke(app, ["import", str(tmp_path / "spec.yaml"), str(tmp_path / "imported.zarr")],
                          env={"COLUMNS": "200"})
    assert shown.exit_code == 0, shown.output
    imported = open_store(tmp_path / "imported.zarr").load()
    for name in ("target", "reference", "backlit", "dark"):
        np.testing.assert_array_equal(imported[name].values, original[name].values)  # bit for bit, frame order
    np.testing.assert_array_equal(imported["angle"].values, original["angle"].values)
    assert imported.attrs["principal_point_px"] == list(original.attrs["principal_point_px"])  # j + 0.5 → j
    assert "light_distance" not in imported.attrs  # and nothing downstream needs it (the same absorption, below)
    # the store says where it came from: the spec's text, a digest of the spec and frames, the command
    from selpath.pipeline.provenance import read_provenance
    from selpath.stages.importing import spec_identity

    record = read_provenance(tmp_path / "imported.zarr")
    assert record["imported"] and record["spec_text"] == (tmp_path / "spec.yaml").read_text()
    assert record["spec_and_frames_sha256"] == spec_identity(
        type("S", (), {"spec": str(tmp_path / "spec.yaml")}))["spec_and_frames_sha256"]
    assert record["command"].startswith("selpath import ") and record["versions"]["selpath"]
    inspected = runner.invoke(app, ["inspect", str(tmp_path / "imported.zarr")], env={"COLUMNS": "300"})
    assert inspected.exit_code == 0, inspected.output
    assert "imported: by `selpath import" in inspected.output and record["spec_and_frames_sha256"] in inspected.output
    assert "provenance: none" not in inspected.output
    # the same frames imported again (elsewhere, under the same name) are the same store, byte for byte: what reads it
    # keeps its identity; and nothing replaces an imported capture without being told to
    from selpath.pipeline.provenance import content_digest
    from selpath.pipeline.store import to_store

    (tmp_path / "again").mkdir()
    again = runner.invoke(app, ["import", str(tmp_path / "spec.yaml"), str(tmp_path / "again" / "imported.zarr")])
    assert again.exit_code == 0, again.output
    assert content_digest(tmp_path / "again" / "imported.zarr") == content_digest(tmp_path / "imported.zarr")
    with pytest.raises(StoreError, match="holds a capture imported with `selpath import`"):
        to_store(imported, tmp_path / "imported.zarr", "tomography_capture")
    # the stages read it as they read the rig's own store: the same absorption, the same hull
    workflow = tmp_path / "reprocess.yaml"
    workflow.write_text("workflow: reprocess\nsteps:\n"
                        "  - {id: capture, stage: import_capture, with: {spec: spec.yaml}}\n"
                        "  - {id: absorption, stage: absorption, with: {capture: $capture}}\n"
                        "outputs:\n  absorption: {from: absorption, store: out/absorption.zarr}\n")
    run_workflow(load_workflow(workflow), progress=False)
    from selpath.stages.tomography.calibrate import absorption

    expected = absorption(original)
    xr.testing.assert_allclose(open_store(tmp_path / "out" / "absorption.zarr")["absorption"].load(),
                               expected["absorption"].load())
    # the rays traced through the imported geometry (no light_distance) are those of the rig's own store
    from selpath.stages.tomography.hull import silhouettes, visual_hull
    from selpath.stages.tomography.paths import align_paths

    def rays(capture):
        return align_paths(absorption(capture), visual_hull(silhouettes(capture))).compute()

    xr.testing.assert_allclose(rays(imported)[["theta", "x", "absorption"]],
                               rays(original)[["theta", "x", "absorption"]])
    # a second run reuses it; a changed frame changes the import's identity and recomputes
    assert run_workflow(load_workflow(workflow), progress=False).computed() == []
    tifffile.imwrite(tmp_path / "target" / "frame_3.tif", original["target"].values[3] + 1)
    assert run_workflow(load_workflow(workflow), progress=False).computed() == ["capture", "absorption"]


@pytest.mark.parametrize("order", ["delay_major", "exposure_major"])
def test_a_plane_to_ray_stack_in_either_frame_order(tmp_path, order):
    rng = np.random.default_rng(0)
    cube = rng.integers(0, 4095, (3, 2, 4, 5)).astype(np.uint16)  # (delay, exposure, row, col)
    flat = cube.reshape(6, 4, 5) if order == "delay_major" else cube.transpose(1, 0, 2, 3).reshape(6, 4, 5)
    np.save(tmp_path / "stack.npy", flat)
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump({
        "kind": "plane_to_ray_capture", "frames": {"image": "stack.npy"}, "delays_us": [-170.0, 0.0, 170.0],
        "exposures_us": [170.0, 510.0], "order": order, "scan_speed_px_per_us": 1 / 17, "line_time_us": 17.0,
        "saturation_counts": 4095, "dark_level_counts": 64}))
    ds = import_capture(spec=str(tmp_path / "spec.yaml"))
    np.testing.assert_array_equal(ds["image"].values, cube)
    assert ds["delay"].attrs["units"] == "us" and ds.attrs["dark_level_counts"] == 64
    assert runner.invoke(app, ["import", str(tmp_path / "spec.yaml"), str(tmp_path / "c.zarr")]).exit_code == 0
    np.testing.assert_array_equal(open_store(tmp_path / "c.zarr")["image"].values, cube)


@pytest.mark.parametrize("order", [["delay", "exposure", "line"], ["line", "exposure", "delay"]])
def test_a_line_sweep_imports_in_any_frame_order_as_the_cube_a_sweep_writes(tmp_path, order):
    """A full-transport stack written in another frame order comes back as the (delay, exposure, line) cube, frame
    for frame; an order that is not a permutation is named."""
    rng = np.random.default_rng(1)
    cube = rng.integers(0, 4095, (3, 2, 4, 5, 6)).astype(np.uint16)  # (delay, exposure, line, row, col)
    axes = [("delay", "exposure", "line").index(d) for d in order]
    np.save(tmp_path / "stack.npy", cube.transpose(*axes, 3, 4).reshape(24, 5, 6))
    spec = {"kind": "full_transport_capture", "frames": {"image": "stack.npy"}, "delays_us": [-170.0, 0.0, 170.0],
            "exposures_us": [170.0, 510.0], "lines_px": [10.0, 20.0, 30.0, 40.0], "order": order,
            "line_width_px": 10.0, "scan_speed_px_per_us": 1 / 17, "line_time_us": 17.0, "saturation_counts": 4095,
            "dark_level_counts": 64}
    (tmp_path / "spec.yaml").write_text(yaml.safe_dump(spec))
    ds = import_capture(spec=str(tmp_path / "spec.yaml"))
    np.testing.assert_array_equal(ds["image"].values, cube)
    assert ds["line"].attrs["units"] == "px" and ds.attrs["line_width_px"] == 10.0
    assert runner.invoke(app, ["import", str(tmp_path / "spec.yaml"), str(tmp_path / "c.zarr")]).exit_code == 0
    stored = open_store(tmp_path / "c.zarr")
    assert stored.attrs["selpath_kind"] == "full_transport_capture"
    np.testing.assert_array_equal(stored["image"].values, cube)
    (tmp_path / "bad.yaml").write_text(yaml.safe_dump(spec | {"order": ["delay", "delay", "line"]}))
    with pytest.raises(ConfigError, match=r"order: .*must name delay, exposure and line once each"):
        import_capture(spec=str(tmp_path / "bad.yaml"))


def test_bad_specs_and_frames_are_named_with_their_field(original, tmp_path):
    spec = _export(original, tmp_path)
    path = tmp_path / "spec.yaml"

    def write(**changes):
        path.write_text(yaml.safe_dump({k: v for k, v in {**spec, **changes}.items() if v is not None},
                                       sort_keys=False))

    write(light_angle_deg=None)
    with pytest.raises(ConfigError, match=r"spec.yaml:1: light_angle_deg: is required but missing"):
        import_capture(spec=str(path))
    write(focal_length_px=None, length_unit="furlong")
    with pytest.raises(ConfigError, match="a perspective camera needs focal_length_px"):
        import_capture(spec=str(path))
    write(length_unit="furlong")
    with pytest.raises(ConfigError, match="length_unit 'furlong' is not one of"):
        import_capture(spec=str(path))
    write(pixel_centers="half")  # a misspelt field: named, with the known field its name is closest to
    with pytest.raises(ConfigError, match=r"pixel_centers: is not a known field \(fix: did you mean 'pixel_centres'"):
        import_capture(spec=str(path))
    write(pixel_centres="half", sky="blue")  # nothing close: no guess
    with pytest.raises(ConfigError, match=r"sky: is not a known field$"):
        import_capture(spec=str(path))
    write(angles_deg=list(range(23)))
    with pytest.raises(StageError, match="frames.target has 24 frames for 23 angles"):
        import_capture(spec=str(path))
    write(frames={**spec["frames"], "reference": "reference.npz"})
    with pytest.raises(StageError, match=r"has members \['frames', 'other'\]"):
        import_capture(spec=str(path))
    write(frames={**spec["frames"], "backlit": "scan.h5:/nope"})
    with pytest.raises(StageError, match="has no dataset '/nope'"):
        import_capture(spec=str(path))
    write(frames={**spec["frames"], "target": "elsewhere"})
    with pytest.raises(StageError, match="frames.target.*no frames at"):
        import_capture(spec=str(path))
    shown = runner.invoke(app, ["import", str(path), str(tmp_path / "x.zarr")], env={"COLUMNS": "200"})
    assert shown.exit_code == 2 and "no frames at" in shown.output and "Traceback" not in shown.output
    write(principal_point_px=None)  # the sensor's centre: pixel (cols − 1) / 2, (rows − 1) / 2
    rows, cols = original.sizes["row"], original.sizes["col"]
    assert import_capture(spec=str(path)).attrs["principal_point_px"] == [(cols - 1) / 2, (rows - 1) / 2]
    write()
    (tmp_path / "exists.zarr").mkdir()
    shown = runner.invoke(app, ["import", str(path), str(tmp_path / "exists.zarr")], env={"COLUMNS": "200"})
    assert shown.exit_code == 2 and "never replaces" in shown.output


def test_frames_are_read_lazily_one_task_per_frame(original, tmp_path):
    _export(original, tmp_path)
    stack = read_frames("target", tmp_path)
    assert stack.numblocks[0] == original.sizes["angle"] and stack.chunks[1] == (original.sizes["row"],)
    h5 = read_frames("scan.h5:/scan/backlit", tmp_path)
    assert h5.numblocks[0] == original.sizes["angle"]
    np.testing.assert_array_equal(h5[5].compute(), original["backlit"].values[5])


def test_a_stack_mixing_bit_depths_or_sizes_or_a_broken_file_is_named(tmp_path):
    """Review finding: dask took every frame's dtype from the first file, so a 16-bit frame after an 8-bit one
    came back as uint8 (301 → 45) without a word; a broken file was an 'unexpected' error."""
    import imageio.v3 as iio

    folder = tmp_path / "frames"
    folder.mkdir()
    iio.imwrite(folder / "f_0.png", np.full((4, 5), 7, np.uint8))
    iio.imwrite(folder / "f_1.png", np.full((4, 5), 301, np.uint16))
    with pytest.raises(StageError, match=r"f_1.png is uint16 \(4, 5\); the stack's first frame is uint8 \(4, 5\)"):
        read_frames("frames", tmp_path).compute()
    (folder / "f_1.png").write_bytes(b"not a png")
    with pytest.raises(StageError, match="f_1.png cannot be read as an image"):
        read_frames("frames", tmp_path).compute()


def test_a_multi_page_tiff_is_read_page_by_page(original, tmp_path):
    tifffile.imwrite(tmp_path / "stack.tif", original["target"].values)
    stack = read_frames("stack.tif", tmp_path)
    assert stack.numblocks[0] == original.sizes["angle"]  # one task per page, nothing read whole
    np.testing.assert_array_equal(stack.compute(), original["target"].values)


def test_a_symlinked_spec_is_identified_by_the_frames_it_reads(original, tmp_path):
    """Review finding: the identity hashed frames beside the link while the import read those beside its target,
    so changed frames were never seen and a re-run reused a stale import."""
    from selpath.stages.importing import spec_identity

    real = tmp_path / "real"
    real.mkdir()
    _export(original, real)
    (tmp_path / "link.yaml").symlink_to(real / "spec.yaml")
    settings = type("Settings", (), {"spec": str(tmp_path / "link.yaml")})()
    before = spec_identity(settings)
    np.save(real / "dark.npy", original["dark"].values + 1)
    assert spec_identity(settings) != before


def test_an_uncompressed_npz_member_is_memory_mapped_and_a_compressed_one_still_reads(tmp_path):
    """``np.savez`` members are mapped in place (frames read one by one, like a ``.npy``), C or Fortran order;
    ``np.savez_compressed`` ones are inflated whole (the zip cannot be read in pieces); both give the same frames."""
    from selpath.stages.frame_files import _npz_stored_member

    rng = np.random.default_rng(2)
    frames = rng.integers(0, 4095, (4, 3, 5)).astype(np.uint16)
    fortran = np.asfortranarray(rng.random((3, 4, 2)))
    np.savez(tmp_path / "plain.npz", image=frames, other=fortran)
    np.savez_compressed(tmp_path / "packed.npz", image=frames)
    mapped = _npz_stored_member(tmp_path / "plain.npz", "image")
    assert isinstance(mapped, np.memmap)
    np.testing.assert_array_equal(mapped, frames)
    np.testing.assert_array_equal(_npz_stored_member(tmp_path / "plain.npz", "other"), fortran)
    assert _npz_stored_member(tmp_path / "packed.npz", "image") is None
    for name in ("plain.npz:image", "packed.npz"):
        lazy = read_frames(name, tmp_path)
        assert lazy.chunks[0] == (1, 1, 1, 1)
        np.testing.assert_array_equal(lazy.compute(), frames)
