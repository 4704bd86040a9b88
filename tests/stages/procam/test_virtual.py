"""Relighting and the epipolar images as stages: what they store equals the accessor's arithmetic (itself tested
against the simulator in tests/explore), patterns come from YAML lists and image files, an edited pattern file
makes the step run again, and bad patterns are refused by name."""

from __future__ import annotations

import textwrap

import imageio.v3 as iio
import numpy as np
import pytest
import xarray as xr

import selpath
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.pipeline.errors import SpecError, StageError
from selpath.stages.procam.demux import PLANE_TO_RAY_TRANSPORT
from selpath.stages.procam.virtual import EPIPOLAR_IMAGES, RELIT_IMAGES, Pattern, epipolar_images, relight_images

OFFSETS = np.arange(-23, 24)


@pytest.fixture(scope="module")
def transport() -> xr.Dataset:
    """The simulator's true transport of a 24 × 32 scene with a projector of 48 rows (two per camera row)."""
    s = ProcamScene.model_validate({
        "scene": "t", "background": {"albedo": 0.3},
        "objects": [{"name": "candle", "region": {"kind": "rectangle", "x": [0.1, 0.5], "y": [0.2, 0.8]},
                     "albedo": 0.9, "effects": {"subsurface": {"width": "3 px", "fraction": 0.5}}}],
        "rig": {"camera_rows": 24, "camera_cols": 32, "projector_rows": 48, "projector_cols": 32, "bits": None}})
    truth = s.rig.intensity * np.concatenate([tr.truth_tile(s, t, OFFSETS) for t in tr.tiles(s)], axis=-1)
    ds = xr.Dataset({"transport": (("offset", "row", "col"), truth.reshape(len(OFFSETS), 24, 32))},
                    coords={"offset": ("offset", OFFSETS, {"units": "px"})},
                    attrs={"scan_speed_px_per_us": s.rig.scan_speed, "line_time_us": s.rig.line_time,
                           "sync_offset_us": 0.0, "projector_shape": [48, 32], "full_scale_counts": 4095.0})
    return PLANE_TO_RAY_TRANSPORT.label(ds)


def test_relit_images_are_the_accessors_under_each_named_pattern(transport, tmp_path):
    values = np.linspace(0, 1, 48)
    image = np.zeros((48, 32), np.uint8)
    image[10:20] = 255
    iio.imwrite(tmp_path / "band.png", image)
    out = relight_images(transport, patterns={"line": Pattern(rows=(30,)), "ramp": Pattern(values=tuple(values)),
                                              "two": Pattern(band=(10, 11))},
                         pattern_file=str(tmp_path / "band.png"))
    assert list(out["pattern"].values) == ["line", "ramp", "two", "band"]
    np.testing.assert_allclose(out["image"].sel(pattern="two"), transport.selpath.relight(rows=[10, 11]), rtol=1e-12)
    np.testing.assert_allclose(out["image"].sel(pattern="line"), transport.selpath.relight(line=30), rtol=1e-12)
    np.testing.assert_allclose(out["image"].sel(pattern="ramp"), transport.selpath.relight(values), rtol=1e-12)
    band = np.zeros(48)
    band[10:20] = 1.0
    np.testing.assert_allclose(out["image"].sel(pattern="band"), transport.selpath.relight(rows=range(10, 20)),
                               rtol=1e-12)
    np.testing.assert_allclose(out["lit_share"], [1 / 48, values.mean(), 2 / 48, 10 / 48])
    assert not RELIT_IMAGES.check(out)
    assert out["image"].attrs == {"units": "counts", "long_name": "image relit under a virtual projector pattern"}
    assert out.attrs["patterns"]["band"] == "file band.png, projector rows"


def test_camera_space_takes_rectified_rows_as_they_are(transport):
    rows = np.zeros(24)
    rows[12] = 1.0
    out = relight_images(transport, patterns={"one": Pattern(values=tuple(rows))}, space="camera")
    np.testing.assert_allclose(out["image"].isel(pattern=0), transport.selpath.relight(rows, space="camera"))


def test_bad_patterns_are_refused_by_name(transport):
    with pytest.raises(StageError, match="pattern 'short': the pattern has 5 rows; the projector has 48"):
        relight_images(transport, patterns={"short": Pattern(values=(1, 0, 1, 0, 1))})
    with pytest.raises(StageError, match="rows \\[48\\] are beyond the 48 rows"):
        relight_images(transport, patterns={"far": Pattern(rows=(48,))})
    with pytest.raises(StageError, match="varies along its rows"):
        relight_images(transport, patterns={"board": Pattern(values=((0, 1) * 16,) * 48)})
    with pytest.raises(ValueError, match="exactly one of rows"):
        Pattern(rows=(1,), values=(1.0,))
    with pytest.raises(ValueError, match="ends before it starts"):
        Pattern(band=(5, 4))
    with pytest.raises(StageError, match="does not record the projector's rows"):
        relight_images(transport.drop_attrs(deep=False), patterns={"x": Pattern(rows=(1,))})


def test_epipolar_bands_sum_to_the_floodlit_image(transport):
    out = epipolar_images(transport, bands=(0, 2, 30))
    total = transport["transport"].sum("offset")
    for band in (0, 2, 30):
        np.testing.assert_allclose(out["epipolar"].sel(band=band) + out["non_epipolar"].sel(band=band), total)
        np.testing.assert_allclose(out["epipolar"].sel(band=band),
                                   transport["transport"].where(abs(transport["offset"]) <= band, 0).sum("offset"))
    assert not EPIPOLAR_IMAGES.check(out) and out["band"].attrs["units"] == "px"


def test_a_workflow_stores_them_and_reruns_when_the_pattern_file_changes(transport, tmp_path):
    selpath.to_store(transport, tmp_path / "transport.zarr", "plane_to_ray_transport")
    image = np.zeros((48, 32), np.uint8)
    image[::4] = 255
    iio.imwrite(tmp_path / "stripes.png", image)
    (tmp_path / "wf.yaml").write_text(textwrap.dedent("""\
        workflow: relight-test
        scheduler: synchronous
        steps:
          - id: transport
            stage: load_store
            with: {store: transport.zarr}
          - id: relit
            stage: relight
            with:
              transport: $transport
              patterns:
                top: {rows: [0, 1, 2, 3]}
              pattern_file: stripes.png
          - id: epipolar
            stage: epipolar_images
            with: {transport: $transport, bands: [0, 3]}
          - id: figure
            stage: relit_figure
            with: {relit: $relit}
        outputs:
          relit: {from: relit, store: out/relit.zarr}
          epipolar: {from: epipolar, store: out/epipolar.zarr}
          figure: {from: figure, store: out/relit-figure.zarr}
        """))
    report = selpath.run(tmp_path / "wf.yaml")
    stored = selpath.open_store(tmp_path / "out/relit.zarr")
    assert stored.selpath.kind == "relit_images" and list(stored["pattern"].values) == ["top", "stripes"]
    np.testing.assert_allclose(stored["image"].sel(pattern="stripes"),
                               transport.selpath.relight(image[:, 0] / 255.0), rtol=1e-6)
    assert (tmp_path / "out/relit-figure.png").is_file()
    assert selpath.open_store(tmp_path / "out/epipolar.zarr")["epipolar"].sizes["band"] == 2
    again = selpath.run(tmp_path / "wf.yaml")
    assert "relit" not in again.computed() and "relit" in report.computed()
    iio.imwrite(tmp_path / "stripes.png", 255 - image)  # an edited pattern: the step runs again
    edited = selpath.run(tmp_path / "wf.yaml")
    assert "relit" in edited.computed() and "epipolar" not in edited.computed()
    np.testing.assert_allclose(selpath.open_store(tmp_path / "out/relit.zarr")["image"].sel(pattern="stripes"),
                               transport.selpath.relight(1.0 - image[:, 0] / 255.0), rtol=1e-6)


def test_a_workflow_without_any_pattern_or_with_a_missing_file_fails_validation(transport, tmp_path):
    selpath.to_store(transport, tmp_path / "transport.zarr", "plane_to_ray_transport")
    for extra, message in (("", "no pattern"), ("pattern_file: nowhere.png", "is not a file")):
        (tmp_path / "wf.yaml").write_text(textwrap.dedent(f"""\
            workflow: relight-test
            steps:
              - id: transport
                stage: load_store
                with: {{store: transport.zarr}}
              - id: relit
                stage: relight
                with:
                  transport: $transport
                  {extra}
            outputs:
              relit: {{from: relit, store: out/relit.zarr}}
            """))
        with pytest.raises(SpecError, match=message):
            selpath.load_workflow(tmp_path / "wf.yaml")
