"""Volumes (issue #26): a light sheet over an ellipsoidal grape, every camera row a slice at its height z, against the
scene's truth volume; the volume figure and the OME-Zarr metadata that lets 3-D viewers open a reconstruction."""

from __future__ import annotations

import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
import xarray as xr

from selpath import workflows
from selpath.devices.sim.scene import Scene, load_scene
from selpath.pipeline import StageError
from selpath.stages.tomography.acquire import AngleSweep
from selpath.stages.tomography.calibrate import absorption
from selpath.stages.tomography.evaluate import reconstruction_error
from selpath.stages.tomography.hull import silhouettes, visual_hull
from selpath.stages.tomography.paths import align_paths
from selpath.stages.tomography.phantom import phantom_truth
from selpath.stages.tomography.reconstruct import fbp, ome_attrs, reconstruct_tv
from selpath.stages.tomography.reconstruction_figures import upright, volume_figure
from selpath.stages.tomography.simulate import simulate_capture
from selpath.stages.tomography.sinogram import bin_sinogram

sys.path.insert(0, str(Path(__file__).parent))
from test_tomography_processing import capture  # noqa: E402  (the in-memory simulated capture)

SCENE = workflows.folder() / "scenes" / "grape-ellipsoid.yaml"


def small_grape(rows: int = 24, cols: int = 24, pixel: float = 0.9) -> Scene:
    """The shipped grape scene on a coarser camera (fast)."""
    scene = load_scene(SCENE)
    camera = scene.camera.model_copy(update={"rows": rows, "cols": cols, "pixel_size": pixel})
    return scene.model_copy(update={"camera": camera})


def volume_chain(scene: Scene, step: float = 8.0):
    with xr.set_options(keep_attrs=True):
        cap = capture(scene, np.arange(0.0, 360.0, step))
    hull = visual_hull(silhouettes(cap))
    sinogram = bin_sinogram(align_paths(absorption(cap, min_signal=1.0), hull))
    return cap, hull, sinogram


def centroid_z(volume: xr.DataArray, inclusion) -> float:
    """σ-weighted mean height of the volume in a box around an inclusion (its semi-axes + 1 mm, + 2 mm in z)."""
    (cx, cy, cz), (a, b, c) = inclusion.shape.centre, inclusion.shape.semi_axes
    box = volume.where((abs(volume["x"] - cx) < max(a, b) + 1) & (abs(volume["y"] - cy) < max(a, b) + 1)
                       & (abs(volume["z"] - cz) < c + 2), 0.0).clip(min=0.0)
    weight = box.sum(("y", "x"))
    return float((weight * volume["z"]).sum() / weight.sum())


def test_the_truth_volume_holds_each_inclusions_integral():
    """Σ σ · cell² · Δz over the truth volume equals Σ σ_i · 4/3 π a b c of the ellipsoidal inclusions (2 %)."""
    scene = load_scene(SCENE)
    z = np.arange(11.0, -11.0, -0.25)
    grid = xr.Dataset(coords={"slice": ("slice", np.arange(len(z))), "z": ("slice", z, {"units": "mm"}),
                              "x": ("x", np.linspace(-8.5, 8.5, 96), {"units": "mm"})}, attrs={"x_extent": 8.5})
    truth = phantom_truth(grid, scene=str(SCENE), n_pixels=96).compute()
    got = float(truth["sigma"].sum()) * truth.attrs["cell_size"] ** 2 * 0.25
    want = sum(i.sigma * 4 / 3 * np.pi * np.prod(i.shape.semi_axes) for i in scene.object.inclusions)
    assert got == pytest.approx(want, rel=0.02)
    np.testing.assert_array_equal(truth["z"].values, z)


def test_slices_carry_their_height_and_a_volume_is_recovered_at_the_right_heights():
    """Every stage carries z (the camera's axis height of each row, in mm; the formula is pinned in
    tests/devices/test_geometry.py, and here row 0 at the top: +10.35 mm); the FBP volume puts each inclusion at
    the height the truth volume does, within half a slice (0.45 mm), and its RMSE is within 2.5 % of the σ peak."""
    scene = small_grape()
    _, hull, sinogram = volume_chain(scene)
    heights = scene.geometry().camera.axis_height(np.arange(24))
    assert heights[0] == pytest.approx(11.5 * 0.9)  # (c_y − 0) · pixel size, c_y = 11.5
    np.testing.assert_allclose(hull["z"].values, heights, rtol=1e-12)
    np.testing.assert_allclose(sinogram["z"].values, heights, rtol=1e-12)
    assert sinogram["z"].attrs["units"] == "mm"
    volume = fbp(sinogram, hull, fill="linear").compute()
    truth = phantom_truth(sinogram, scene=str(SCENE), n_pixels=volume.sizes["x"]).compute()
    np.testing.assert_allclose(volume["z"].values, heights, rtol=1e-12)
    for inclusion in scene.object.inclusions:
        assert centroid_z(volume["sigma"], inclusion) == pytest.approx(centroid_z(truth["sigma"], inclusion),
                                                                       abs=0.45), inclusion.name
    rmse = float(reconstruction_error(volume, truth)["rmse"])
    assert rmse < 0.025 * 0.4


def test_building_a_volume_and_its_figure_computes_nothing(no_compute):
    scene = small_grape(rows=12, cols=16, pixel=1.6)
    _, hull, sinogram = volume_chain(scene, step=20.0)
    optimised = reconstruct_tv(sinogram, hull, max_iter=5)
    volume_figure(optimised, phantom_truth(sinogram, scene=str(SCENE)))
    assert no_compute.count == 0


def test_a_volume_needs_heights_and_more_than_one_slice():
    scene = small_grape(rows=12, cols=16, pixel=1.6)
    _, hull, sinogram = volume_chain(scene, step=20.0)
    volume = fbp(sinogram, hull)
    with pytest.raises(StageError, match="has 1 slice;.*light sheet"):
        volume_figure(volume.isel(slice=[5]))
    with pytest.raises(StageError, match="have no height z"):
        volume_figure(volume.drop_vars("z"))
    beam = scene.model_copy(update={"light": scene.light.model_copy(update={"kind": "beam", "height": 4.0})})
    _, hull, sinogram = volume_chain(beam, step=20.0)
    with pytest.raises(StageError, match="reconstruction has 1 slice"):  # a beam lights the row at its height (row 3)
        volume_figure(fbp(sinogram, hull))


@pytest.mark.parametrize("order", [1, -1], ids=["z falling", "z rising"])
def test_vertical_sections_are_drawn_with_the_highest_slice_on_top(order):
    z = np.array([2.0, 1.0, 0.0])[::order]
    section = np.zeros((3, 4))
    section[int(np.argmax(z))] = 1.0  # the highest slice is marked
    np.testing.assert_array_equal(upright(section, z)[0], 1.0)
    np.testing.assert_array_equal(upright(section, z)[1:], 0.0)


def test_ome_metadata_is_written_only_for_a_regular_grid():
    z, yx = np.array([1.0, 0.5, 0.0]), np.linspace(-1, 1, 5)
    ome = ome_attrs(z, yx, yx, "mm")["ome"]["multiscales"][0]
    assert [a["name"] for a in ome["axes"]] == ["slice", "y", "x"] and ome["axes"][0]["unit"] == "millimeter"
    assert ome["datasets"][0]["coordinateTransformations"][0]["scale"] == [-0.5, 0.5, 0.5]
    assert ome_attrs(z[:1], yx, yx, "mm") == {}  # one slice: no volume
    assert ome_attrs(np.array([1.0, 0.5, 0.1]), yx, yx, "mm") == {}  # uneven heights
    assert "unit" not in ome_attrs(z, yx, yx, "px")["ome"]["multiscales"][0]["axes"][0]  # pixels: no NGFF unit


def test_a_lazily_simulated_capture_is_the_rigs_under_any_chunking(tmp_path):
    """simulate_capture renders what the rig's camera records (the in-memory capture of these tests, to float32
    rounding), in bands of rows or whole frames alike; with noise, two bandings give identical frames."""
    angles = AngleSweep(start=0, stop=360, step=30)
    banded = simulate_capture(scene=str(SCENE), angles=angles, rows_per_chunk=7)
    assert banded["target"].chunks[1] == (7, 7, 7, 7, 7, 5)
    banded = banded.compute()
    whole = simulate_capture(scene=str(SCENE), angles=angles).compute()
    with xr.set_options(keep_attrs=True):
        rig = capture(load_scene(SCENE), angles.values()).compute()
    for kind in ("target", "reference", "backlit"):
        np.testing.assert_array_equal(banded[kind].values, whole[kind].values)
        np.testing.assert_allclose(banded[kind].values, np.clip(rig[kind].values, 0, 4095), atol=1e-3)
    noisy = tmp_path / "noisy.yaml"
    noisy.write_text(SCENE.read_text() + "effects: {noise: {read_std: 2, gain: 1.0, seed: 3}}\n")
    a = simulate_capture(scene=str(noisy), angles=angles, rows_per_chunk=5)["target"].values
    b = simulate_capture(scene=str(noisy), angles=angles, rows_per_chunk=16)["target"].values
    np.testing.assert_array_equal(a, b)
    assert 1.0 < float(np.std(a - whole["target"].values)) < 60.0  # the noise is there
    with pytest.raises(StageError, match="scattering"):
        simulate_capture(scene=str(SCENE.parent / "cylinder-in-cylinder-s1.yaml"))


@pytest.mark.parametrize("rows_per_chunk", [None, 5], ids=["frames", "bands"])
def test_no_task_of_the_volume_chain_holds_a_whole_capture(monkeypatch, tmp_path, rows_per_chunk):
    """Memory bounded by tile: with 4-frame render chunks, 1-KiB hull blocks and binning tasks, one-slice
    reconstruction batches and dask's rechunk intermediates at most 16 KiB (``array.chunk-size``, 128 MiB by default:
    the same proportions as a full capture's), no task's
    result holds more than 8 render chunks' bytes (the paths' 4 float64 fields of a chunk: 8×) or the hull's
    contours of every slice (which each path task reads), and either is under a quarter of one frame kind."""
    import dask
    from dask.callbacks import Callback

    import selpath.stages.tomography.hull as hull_module
    import selpath.stages.tomography.reconstruct as reconstruct_module
    import selpath.stages.tomography.simulate as simulate_module
    import selpath.stages.tomography.sinogram as sinogram_module

    scene = small_grape(cols=96)
    path = tmp_path / "small-grape.yaml"
    chunk = 4 * 24 * 96 * 4  # 4 frames
    monkeypatch.setattr(simulate_module, "SCENE_CHUNK_BYTES", chunk)
    monkeypatch.setattr(hull_module, "HULL_CHUNK_BYTES", 1024)
    monkeypatch.setattr(sinogram_module, "BIN_CHUNK_BYTES", 1024)
    monkeypatch.setattr(reconstruct_module, "SLICE_BATCH", 1)
    largest = [0, ""]

    def size(value) -> int:
        if isinstance(value, np.ndarray | xr.DataArray | xr.Dataset):
            return int(value.nbytes)
        if isinstance(value, tuple | list):
            return sum(size(v) for v in value)
        return 0

    def record(key, result, dsk, state, worker_id):
        if size(result) > largest[0] and "finalize" not in str(key):  # finalize: the volume handed back
            largest[:] = [size(result), str(key)]

    path.write_text(scene.model_dump_json())
    with dask.config.set({"array.chunk-size": "16KiB"}):  # rechunks are planned as the graph is built
        cap = simulate_capture(scene=str(path), angles=AngleSweep(start=0, stop=360, step=2),
                               rows_per_chunk=rows_per_chunk)
        hull = visual_hull(silhouettes(cap))
        volume = fbp(bin_sinogram(align_paths(absorption(cap, min_signal=1.0), hull)), hull)
        with Callback(posttask=record):
            volume["sigma"].compute(scheduler="threads")
    one_kind, contours = cap["target"].nbytes, hull["vertices"].nbytes
    assert cap["target"].data.chunksize[0] == 4
    assert 0 < largest[0] <= max(8 * chunk, contours) < one_kind / 4, (largest, contours, one_kind)


@pytest.mark.slow
def test_the_volume_workflow_recovers_the_grape_and_3d_viewers_can_open_it(tmp_path):
    """tomography-volume end to end (about 15 s): RMSE over the volume (FBP 3.9e-3, optimisation 2.9e-3 when
    written, largest true σ 0.4 /mm), each inclusion's height within 0.1 mm of the truth's, and the stores pass
    an independent OME-Zarr 0.5 validator (ome-zarr-models)."""
    import zarr
    from ome_zarr_models.v05.image import Image

    from selpath.pipeline import load_workflow, open_store
    from selpath.pipeline.engine import run_workflow

    shutil.copy(workflows.path("tomography-volume"), tmp_path / "tomography-volume.yaml")
    shutil.copytree(workflows.folder() / "scenes", tmp_path / "scenes")
    run_workflow(load_workflow(tmp_path / "tomography-volume.yaml"), progress=False)
    out = tmp_path / "out/grape-volume"
    truth = open_store(out / "truth.zarr")
    scene = load_scene(SCENE)
    for name, limit in (("fbp", 4.5e-3), ("optimised", 3.5e-3)):
        volume = open_store(out / f"{name}.zarr")
        assert float(open_store(out / f"{name}-error.zarr")["rmse"]) < limit
        for inclusion in scene.object.inclusions:
            assert centroid_z(volume["sigma"], inclusion) == pytest.approx(centroid_z(truth["sigma"], inclusion),
                                                                           abs=0.1), (name, inclusion.name)
        image = Image.from_zarr(zarr.open_group(str(out / f"{name}.zarr"), mode="r"))
        scale = image.attributes.ome.multiscales[0].datasets[0].coordinateTransformations[0].scale
        assert scale[0] == pytest.approx(-0.6) and scale[1] == pytest.approx(float(np.diff(volume["y"])[0]))
    assert (out / "volume-figure.png").exists()


def test_the_rays_move_to_slices_by_a_task_rechunk_on_any_scheduler():
    """Distributed's default rechunk (p2p) holds its shards outside a worker's managed memory and stalled a 4 GB
    worker at full size: the binning asks for the task-based rechunk whatever dask's setting says, so that a
    ``processes`` or ``tcp://`` run gets it too (the graph built under ``method = p2p`` has no p2p layer)."""
    import dask

    cap, hull, _ = volume_chain(small_grape(), step=30.0)
    rays = align_paths(absorption(cap, min_signal=1.0), hull).chunk({"angle": 2})
    with dask.config.set({"array.rechunk.method": "p2p"}):
        names = list(bin_sinogram(rays)["absorption"].data.__dask_graph__().layers)
        assert any("p2p" in name for name in rays["absorption"].data.rechunk({0: -1}).__dask_graph__().layers)
    assert any(name.startswith("rechunk") for name in names), names
    assert not any("p2p" in name for name in names), names
