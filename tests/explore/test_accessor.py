"""The ``.selpath`` accessor against independent truths: the simulator's rolling-shutter frames for the ideal-rig
frame, its global-shutter render under a line for relighting, hand-written sums, the reconstruction_error stage's
RMSE for a reconstruction's error; labels and units asserted."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.devices import patterns
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.stages.procam.demux import PLANE_TO_RAY_TRANSPORT
from selpath.stages.tomography.evaluate import reconstruction_error
from selpath.stages.tomography.reconstruct import RECONSTRUCTION
from selpath.stages.tomography.sinogram import SINOGRAM

OBJECTS = [{"name": "candle", "region": {"kind": "rectangle", "x": [0.1, 0.5], "y": [0.2, 0.8]}, "albedo": 0.9,
            "effects": {"subsurface": {"width": "3 px", "fraction": 0.5},
                        "specular_interreflection": {"centre": [0.3, 0.5], "reach": 0.3,
                                                     "displacement": ["2 px", "-7 px"], "strength": 0.6}}}]
OFFSETS = np.arange(-39, 40)


def truth_store(rig: dict) -> tuple[ProcamScene, xr.Dataset]:
    """The simulator's true plane-to-ray transport as a labelled store would hold it (attrs as demux writes)."""
    s = ProcamScene.model_validate({"scene": "t", "background": {"albedo": 0.3}, "objects": OBJECTS,
                                    "rig": {"camera_rows": 40, "camera_cols": 48, "projector_cols": 48,
                                            "bits": None} | rig})
    truth = s.rig.intensity * np.concatenate([tr.truth_tile(s, t, OFFSETS) for t in tr.tiles(s)], axis=-1)
    ds = xr.Dataset({"transport": (("offset", "row", "col"), truth.reshape(len(OFFSETS), 40, 48).astype(np.float32))},
                    coords={"offset": ("offset", OFFSETS, {"units": "px"})},
                    attrs={"scan_speed_px_per_us": s.rig.scan_speed, "line_time_us": s.rig.line_time,
                           "sync_offset_us": s.rig.sync_offset,
                           "projector_shape": [s.rig.projector_rows, s.rig.projector_cols]})
    return s, PLANE_TO_RAY_TRANSPORT.label(ds).chunk({"row": 16})


@pytest.fixture(scope="module")
def shifted():
    """A rig with a sync offset (t_o = 8.5 µs, half a row): the ideal frame must apply it as the demux does."""
    return truth_store({"projector_rows": 40, "sync_offset": "8.5 us"})


@pytest.mark.parametrize(("delay", "exposure"), [(0.0, 17.0), (-100.0, 170.0), (59.5, 85.0), (340.0, 510.0)])
def test_the_ideal_frame_is_the_simulators_rolling_shutter_frame(shifted, delay, exposure):
    """Σ_o T(o)·w(o; t_d, t_e) from the true transport against the simulator's time-integrated frame at the same
    commanded delay (no noise, no quantisation): float32 rounding, 1e-5 of the brightest pixel."""
    s, transport = shifted
    rendered = tr.render_frame(s, delay, exposure)
    frame = transport.selpath.ideal_frame(delay, exposure)
    np.testing.assert_allclose(frame.values, rendered, rtol=0, atol=1e-5 * rendered.max() + 1e-3)
    assert frame.attrs["units"] == "counts" and frame.attrs["long_name"].startswith("ideal frame at t_d")
    assert "plane-to-ray" not in frame.attrs["long_name"]


def test_a_profile_carries_the_sync_delay_of_each_offset(shifted):
    s, transport = shifted
    profile = transport.selpath.profile(x=0.25, y=0.5)
    assert (profile.sizes, transport.selpath.pixel(x=0.25, y=0.5)) == ({"offset": 79}, (20, 12))
    np.testing.assert_array_equal(profile.values, transport["transport"].values[:, 20, 12])
    # t_d = o / v_p − t_o, by hand: 17 µs a row, t_o = 8.5 µs
    np.testing.assert_allclose(profile["sync_delay"].values, OFFSETS * 17.0 - 8.5, rtol=1e-12)
    assert profile["sync_delay"].attrs["units"] == "us" and profile.attrs["units"] == "counts"
    assert profile.attrs["long_name"] == "transport T(offset) of pixel (row 20, col 12)"
    # an explicit timing overrides the store's; a transport that records none needs it
    bare = transport.drop_attrs(deep=False)
    with pytest.raises(ValueError, match="give scan_speed"):
        bare.selpath.sync_delay()
    np.testing.assert_allclose(bare.selpath.sync_delay(scan_speed=0.1, sync_offset=0.0).values, OFFSETS * 10.0)
    unknown = bare.selpath.profile(row=1, col=1)  # no timing: the profile, without a delay it cannot know
    assert "sync_delay" not in unknown.coords and "give scan_speed" in unknown.attrs["description"]
    given = bare.selpath.profile(row=1, col=1, scan_speed=0.1, sync_offset=2.0)
    np.testing.assert_allclose(given["sync_delay"].values, OFFSETS * 10.0 - 2.0)


def test_the_pixel_rule_is_the_figure_stages_rule(shifted):
    _, transport = shifted
    assert transport.selpath.pixel(x=0.0, y=0.0) == (0, 0)
    assert transport.selpath.pixel(x=1.0, y=1.0) == (39, 47)  # min(⌊y·rows⌋, rows − 1)
    assert transport.selpath.pixel(x=0.999, y=0.026) == (1, 47)  # ⌊0.026·40⌋ = 1, ⌊0.999·48⌋ = 47
    assert transport["transport"].selpath.pixel(row=3, col=4) == (3, 4)
    for bad in ({"row": 40, "col": 0}, {"x": 1.2, "y": 0.0}, {"row": 1}, {"row": 1, "col": 1, "x": 0.1, "y": 0.1}):
        with pytest.raises(ValueError):
            transport.selpath.pixel(**bad)


@pytest.mark.parametrize("row", [5, 20, 33])
def test_relighting_under_a_projector_line_is_the_simulators_render(shifted, row):
    """A projector row on a rig of as many projector as camera rows: the global-shutter render under that line."""
    s, transport = shifted
    pattern = patterns.horizontal_line((s.rig.projector_rows, s.rig.projector_cols), row, 1.0)
    rendered = tr.render_frame(s, -100.0, 2000.0, pattern, shutter="global")
    relit = transport.selpath.relight(line=row)
    np.testing.assert_allclose(relit.values, rendered, rtol=0, atol=1e-5 * rendered.max() + 1e-3)
    assert relit.attrs["long_name"] == "image relit under a virtual row pattern" and relit.attrs["units"] == "counts"


def test_projector_rows_are_averaged_onto_the_camera_rows_they_cover():
    """A projector of 100 rows over 40 camera rows (2.5 each): against the simulator under a pattern constant over
    whole camera rows (which it point-samples) and against a hand-written sum under one that is not."""
    s, transport = truth_store({"projector_rows": 100})
    band = np.zeros((100, s.rig.projector_cols))
    band[25:35] = 1.0  # camera rows 10–13 exactly
    rendered = tr.render_frame(s, -100.0, 2000.0, band, shutter="global")
    np.testing.assert_allclose(transport.selpath.relight(band).values, rendered, rtol=0,
                               atol=1e-5 * rendered.max() + 1e-3)
    # one projector row, 51: camera row 20 covers projector rows [49.5, 52) → 1/2.5 of it lit
    t = transport["transport"].values
    expected = np.zeros((40, 48))
    for o_index, o in enumerate(OFFSETS):
        s_row = 20 - o
        if 0 <= s_row < 40:
            expected[s_row] += t[o_index, s_row] * 0.4
    np.testing.assert_allclose(transport.selpath.relight(rows=[51]).values, expected, rtol=1e-6, atol=1e-6)
    with pytest.raises(ValueError, match="beyond the 100 rows"):
        transport.selpath.relight(line=100)
    with pytest.raises(ValueError, match="varies along its rows"):
        transport.selpath.relight(np.tile([0.0, 1.0], (100, 24)))


def test_epipolar_bands_split_the_floodlit_image(shifted):
    _, transport = shifted
    total = transport["transport"].sum("offset").values
    for band in (0, 3, 39):
        epi, non = transport.selpath.epipolar(band), transport.selpath.non_epipolar(band)
        np.testing.assert_allclose(epi.values + non.values, total, rtol=1e-5)
        by_hand = transport["transport"].values[np.abs(OFFSETS) <= band].sum(0)
        np.testing.assert_allclose(epi.values, by_hand, rtol=1e-5)
        assert epi.attrs["units"] == "counts" and "epipolar image" in epi.attrs["long_name"]
    assert not transport.selpath.non_epipolar(39).values.any()


def test_region_statistics_are_numpys(shifted):
    _, transport = shifted
    stats = transport.selpath.region(rows=(10, 20), cols=(5, 25))
    block = transport["transport"].values[:, 10:20, 5:25]
    np.testing.assert_allclose(stats["mean"].values, block.mean((1, 2)), rtol=1e-5)
    np.testing.assert_allclose(stats["std"].values, block.std((1, 2)), rtol=1e-4, atol=1e-6)
    assert stats["mean"].dims == ("offset",) and stats["mean"].attrs["units"] == "counts"
    assert (stats["count"] == 200).all()
    by_fraction = transport.selpath.region(x=(5 / 48, 25 / 48), y=(0.25, 0.5))
    np.testing.assert_allclose(by_fraction["max"].values, block.max((1, 2)))
    with pytest.raises(ValueError, match="empty or outside"):
        transport.selpath.region(rows=(30, 50))


def test_a_captures_pixel_is_its_delay_sweep_per_exposure():
    image = np.random.default_rng(0).random((5, 2, 4, 6))
    capture = xr.Dataset({"image": (("delay", "exposure", "row", "col"), image, {"units": "counts"})},
                         coords={"delay": ("delay", np.linspace(-40, 40, 5), {"units": "us"}),
                                 "exposure": ("exposure", [17.0, 34.0], {"units": "us"})})
    sweep = capture.selpath.intensity(row=2, col=5)
    np.testing.assert_array_equal(sweep.values, image[:, :, 2, 5])
    assert sweep.attrs["units"] == "counts" and sweep.attrs["long_name"] == "I(t_d) of pixel (row 2, col 5)"
    figure = sweep.selpath.plot()
    np.testing.assert_array_equal(figure.axes[0].lines[1].get_ydata(), image[:, 1, 2, 5])


def _tomography(rng):
    y = x = ("x", np.linspace(-1, 1, 8), {"units": "mm"})
    sigma = rng.random((2, 8, 8))
    recon = RECONSTRUCTION.label(xr.Dataset(
        {"sigma": (("slice", "y", "x"), sigma)},
        coords={"slice": [3, 4], "y": ("y", y[1], {"units": "mm"}), "x": x,
                "z": ("slice", [0.5, 0.75], {"units": "mm"})}))
    truth = RECONSTRUCTION.label(xr.Dataset({"sigma": (("slice", "y", "x"), sigma[:1] * 0.9)},
                                            coords={"slice": [3], "y": ("y", y[1], {"units": "mm"}), "x": x}))
    return recon, truth


def test_a_reconstruction_beside_its_truth_and_error():
    recon, truth = _tomography(np.random.default_rng(1))
    recon["sigma"].attrs["units"] = "1/mm"
    compared = recon.selpath.compare(truth)
    np.testing.assert_allclose(compared["error"].values, recon["sigma"].values - truth["sigma"].values[0])
    rmse = float(reconstruction_error(recon, truth)["rmse"])
    assert float((compared["error"] ** 2).mean() ** 0.5) == pytest.approx(rmse, rel=1e-12)
    assert compared["error"].attrs["units"] == "1/mm" and compared["truth"].attrs["long_name"].startswith("true")
    volume = recon.selpath.volume()
    assert volume.dims == ("z", "y", "x") and volume["z"].attrs["units"] == "mm"


def test_a_sinogram_hides_what_no_ray_observed():
    rng = np.random.default_rng(2)
    observed = rng.random((6, 9)) > 0.3
    sino = SINOGRAM.label(xr.Dataset({"absorption": (("theta", "x"), rng.random((6, 9))),
                                      "observed": (("theta", "x"), observed)},
                                     coords={"theta": ("theta", np.arange(6) * 60.0, {"units": "deg"}),
                                             "x": ("x", np.linspace(-1, 1, 9), {"units": "mm"})}))
    masked = sino.selpath.sinogram()
    assert np.array_equal(np.isnan(masked.values), ~observed)
    figure = sino.selpath.plot()
    legend = [t.get_text() for t in figure.axes[0].get_legend().get_texts()]
    assert legend == [f"unobserved ({1 - observed.mean():.0%} of bins)"]


def test_flags_plot_with_a_categorical_key_and_profiles_with_a_delay_axis(shifted):
    _, transport = shifted
    flags = xr.DataArray(np.eye(4, 6, dtype=bool), dims=("row", "col"), attrs={"long_name": "converged"})
    figure = flags.selpath.plot()
    assert len(figure.axes) == 1  # no colour bar
    assert [t.get_text() for t in figure.axes[0].get_legend().get_texts()] == ["converged: yes (4 px)",
                                                                                 "no (20 px)"]
    profile = transport.selpath.profile(row=20, col=12)
    figure = profile.selpath.plot()
    np.testing.assert_array_equal(figure.axes[0].lines[0].get_ydata(), profile.values)
    assert figure.axes[0].get_xlabel() == "offset [px]"
    top = [a for a in figure.axes[0].child_axes if a.get_xlabel()]
    assert top and top[0].get_xlabel() == "sync delay t_d (o / v_p − t_o) [us]"
