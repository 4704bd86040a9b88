"""Every figure stage says what it draws: a one-paragraph ``caption`` attr (known before anything is computed)
and a description of each data input and setting; the reconstruction figure crops to the object and draws the
reconstruction's error, so an exact and a wrong reconstruction look different."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.pipeline.errors import StageError
from selpath.pipeline.registry import default_registry
from selpath.stages._figures import as_figure, panels, rgba, shape_of
from selpath.stages.tomography.reconstruction_figures import object_window, reconstruction_figure, reconstruction_size

MM = {"units": "mm"}


def _lazy(ds: xr.Dataset) -> xr.Dataset:
    return ds.chunk()


def tomography_capture() -> xr.Dataset:
    rng = np.random.default_rng(0)
    frames = rng.uniform(0, 100, (3, 6, 8))
    dims = ("angle", "row", "col")
    return _lazy(xr.Dataset({"target": (dims, frames, {"units": "counts"}),
                             "backlit": (dims, frames[::-1], {"units": "counts"})},
                            coords={"angle": ("angle", [0.0, 1.0, 2.0], {"units": "degree"})},
                            attrs={"light_angle_deg": 45.0}))


def sinogram() -> xr.Dataset:
    dims = ("slice", "theta", "x")
    values = np.random.default_rng(1).uniform(0, 1, (2, 6, 8))
    return _lazy(xr.Dataset({"absorption": (dims, values, {"units": "1"}), "observed": (dims, values > 0.2)},
                            coords={"slice": [59, 60], "theta": ("theta", np.arange(6) * 30.0, {"units": "degree"}),
                                    "x": ("x", np.linspace(-7, 7, 8), MM)}, attrs={"light_angle_deg": 45.0}))


def coverage() -> xr.Dataset:
    return _lazy(xr.Dataset({"coverage": ("slice", [0.8, 0.82]), "analytic_coverage": ("slice", [0.85, 0.85])},
                            coords={"slice": [59, 60]}, attrs={"light_angle_deg": 45.0}))


def reconstruction(sigma: np.ndarray, **variables) -> xr.Dataset:
    """A reconstruction store of one slice (camera row 59) on an n × n grid of 1 mm cells, σ in 1/mm."""
    n = sigma.shape[-1]
    grid = np.arange(n) - (n - 1) / 2
    dims = ("slice", "y", "x")
    data = {"sigma": (dims, sigma[None], {"units": "1/mm"}), "reliable": (dims, np.ones((1, n, n), bool)),
            **variables}
    return _lazy(xr.Dataset(data, coords={"slice": [59], "y": ("y", grid, MM), "x": ("x", grid, MM)},
                            attrs={"light_angle_deg": 45.0, "tv_weight": 0.02, "tol": 1e-3}))


def optimised(sigma: np.ndarray) -> xr.Dataset:
    history = np.geomspace(1, 1e-4, 10)[None]
    hist = ("slice", "iteration")
    return reconstruction(sigma, objective=(hist, history), primal_residual=(hist, history),
                          dual_residual=(hist, history), iterations=("slice", [10]), converged=("slice", [True]))


def volume() -> xr.Dataset:
    """A reconstruction of 6 slices (camera rows 10–15, z from 2.5 mm down by 1 mm), a block of σ in slices 2–3."""
    n = SIGMA.shape[-1]
    grid = np.arange(n) - (n - 1) / 2
    sigma = np.zeros((6, n, n))
    sigma[2:4] = SIGMA
    volume = _lazy(xr.Dataset({"sigma": (("slice", "y", "x"), sigma, {"units": "1/mm"})},
                              coords={"slice": np.arange(10, 16), "y": ("y", grid, MM), "x": ("x", grid, MM)},
                              attrs={"method": "fbp"}))
    return volume.assign_coords(z=("slice", 2.5 - np.arange(6.0), MM))  # in memory, as a store's coordinates


def plane_capture() -> xr.Dataset:
    dims = ("delay", "exposure", "row", "col")
    return _lazy(xr.Dataset({"image": (dims, np.random.default_rng(2).uniform(0, 100, (5, 2, 6, 8)),
                                       {"units": "counts"})},
                            coords={"delay": ("delay", [-340.0, -170.0, 0.0, 170.0, 340.0], {"units": "us"}),
                                    "exposure": ("exposure", [170.0, 510.0], {"units": "us"})},
                            attrs={"scan_speed_px_per_us": 1 / 17}))


def plane_transport() -> xr.Dataset:
    return _lazy(xr.Dataset({"transport": (("offset", "row", "col"), np.random.default_rng(3).uniform(0, 1, (5, 6, 8)),
                                           {"units": "counts"})},
                            coords={"offset": ("offset", np.arange(-2, 3), {"units": "px"})}))


def full_transport() -> xr.Dataset:
    rng = np.random.default_rng(4)
    cells = np.arange(0.0, 16.0, 2.0)
    return _lazy(xr.Dataset({"transport": (("du", "dv", "row", "col"), rng.uniform(0, 1, (3, 3, 6, 8)),
                                           {"units": "counts"}),
                             "u_direct": (("row", "col"), np.tile(cells, (6, 1)), {"units": "px"})},
                            coords={"du": ("du", [-2.0, 0.0, 2.0], {"units": "px"}),
                                    "dv": ("dv", [-1, 0, 1], {"units": "px"})},
                            attrs={"cell_width_px": 2.0, "cells_px": cells.tolist()}))


def direct_global(seed: int) -> xr.Dataset:
    rng = np.random.default_rng(seed)
    return _lazy(xr.Dataset({name: (("row", "col"), rng.uniform(0, 100, (6, 8)), {"units": "counts"})
                             for name in ("direct", "global")}, attrs={"square_px": [4, 4], "shifts": 16}))


def short_range() -> xr.Dataset:
    rng = np.random.default_rng(7)
    return _lazy(xr.Dataset({"image": (("max_delay", "row", "col"), rng.uniform(0, 100, (3, 6, 8))),
                             "energy_fraction": ("max_delay", [0.9, 0.97, 1.0]),
                             "captures": ("max_delay", [1, 11, 21]),
                             "pixel_to_pixel_captures": ("max_delay", [30, 30, 30])},
                            coords={"max_delay": ("max_delay", [0.0, 850.0, 1700.0], {"units": "us"})},
                            attrs={"delay_step_us": 170.0, "exposure_us": 170.0}))


def line_study() -> xr.Dataset:
    methods = ["multiplexed (demultiplexed)", "single line, 1 scan", "single line, 50 scans"]
    return xr.Dataset({"image": (("method", "row", "col"), np.random.default_rng(0).random((3, 12, 16))),
                       "truth": (("row", "col"), np.ones((12, 16))),
                       "snr_db": ("method", [5.7, -1.2, 20.7]), "predicted_snr_db": ("method", [np.nan, -1.2, 20.6]),
                       "captures": ("method", [63, 1, 1])}, coords={"method": methods},
                      attrs={"selpath_kind": "line_relighting_snr", "line_rows": [5, 8], "lit_fraction": 0.05,
                             "lit_pixels": 48, "read_std_counts": 2.0, "gain_counts_per_electron": 1.0})


def relighting_snr(snr: float) -> xr.Dataset:
    return xr.Dataset({"image": (("pattern", "row", "col"), np.random.default_rng(1).random((2, 12, 16))),
                       "truth": (("pattern", "row", "col"), np.ones((2, 12, 16))),
                       "snr_db": ("pattern", [snr, snr + 5])}, coords={"pattern": ["checkerboard", "floodlit"]},
                      attrs={"selpath_kind": "relighting_snr", "square_px": 40, "line_width_px": 10.0,
                             "exposures_us": [170.0], "captures": 352, "lit_fraction": 0.05})


def material_stores(scored: bool) -> tuple[xr.Dataset, xr.Dataset]:
    rng = np.random.default_rng(8)
    names = ["soap", "milk"]
    classifier = xr.Dataset({"mean_profile": (("material", "delay"), rng.random((2, 5)))},
                            coords={"material": names, "delay": ("delay", np.arange(5) * 17.0, {"units": "us"})},
                            attrs={"svm_C": 10.0, "svm_gamma": 1.0, "folds": 5, "source_kind": "plane_to_ray_capture"})
    label = rng.integers(-1, 2, (6, 8))
    result = {"label": (("row", "col"), label), "image": (("row", "col"), rng.random((6, 8)))}
    if scored:
        result |= {"true_label": (("row", "col"), label),
                   "confusion": (("true_material", "material"), [[5, 1], [0, 9]]),
                   "brightness_accuracy": ("material", [0.5, 0.4])}
    return _lazy(xr.Dataset(result, coords={"material": names, "true_material": names})), classifier


def delay_choice() -> xr.Dataset:
    rng = np.random.default_rng(9)
    return _lazy(xr.Dataset({"image": (("view", "row", "col"), rng.random((3, 6, 8))),
                             "contrast": ("delay", [np.nan, 0.2, 0.5, 0.1]), "contrast_of": ("view", [0.1, 0.2, 0.5])},
                            coords={"delay": ("delay", [0.0, 100.0, 200.0, 300.0], {"units": "us"})},
                            attrs={"chosen_delay_us": 200.0, "direct_free_from_us": 93.5, "structure": "vein",
                                   "surround": "skin", "exposure_us": 170.0, "far_range_rows": 5.5}))


def atlas() -> xr.Dataset:
    rng = np.random.default_rng(10)
    window = np.arange(-3, 4)
    return _lazy(xr.Dataset({"profile": (("site", "du", "dv"), rng.random((2, 7, 7))), "extent": ("site", [0.7, 3.1]),
                             "image": (("row", "col"), rng.random((6, 8)))},
                            coords={"site": ["wood", "candle"], "site_row": ("site", [2, 3]),
                                    "site_col": ("site", [1, 6]), "du": ("du", window, {"units": "px"}),
                                    "dv": ("dv", window, {"units": "px"})},
                            attrs={"reach_px": 3, "extent_floor": 0.02}))


def appearance() -> tuple[xr.Dataset, xr.Dataset]:
    rng = np.random.default_rng(11)
    delay = ("delay", np.arange(-2, 3) * 17.0, {"units": "us"})
    profile = xr.Dataset({"profile": ("distance", [0.2, 0.05, 0.02]), "measured": ("delay", rng.random(5)),
                          "model": ("delay", rng.random(5))},
                         coords={"distance": ("distance", [0, 1, 2], {"units": "px"}), "delay": delay},
                         attrs={"material": "soap", "fraction": 0.85, "fraction_std": 0.01, "width_px": 9.0,
                                "width_std_px": 0.1})
    render = xr.Dataset({"image": (("render", "row", "col"), rng.random((2, 6, 8)))},
                        coords={"render": ["lambertian", "subsurface"]},
                        attrs={"mesh": "teapot", "width_render_px": 9.0})
    return _lazy(profile), _lazy(render)


#: each figure stage with inputs of the kinds it expects; a new figure stage needs an entry here
SIGMA = np.zeros((16, 16))
SIGMA[10:13, 3:6] = 0.2
PIXELS = {"page": (0.3, 0.8), "candle": (0.2, 0.3)}
CALLS = {
    "capture_figure": lambda: ((tomography_capture(),), {"angle_index": 1}),
    "sinogram_figure": lambda: ((sinogram(),), {"slice_index": 1}),
    "coverage_figure": lambda: ((coverage(),), {}),
    "reconstruction_figure": lambda: ((reconstruction(SIGMA), optimised(SIGMA), reconstruction(SIGMA)), {}),
    "convergence_figure": lambda: ((optimised(SIGMA),), {}),
    "volume_figure": lambda: ((volume(), volume()), {"at": (2.0, -1.0, 0.4)}),
    "delay_profile_figure": lambda: ((plane_capture(), plane_transport()), {"pixels": PIXELS}),
    "relighting_figure": lambda: ((plane_transport(),), {"lines": (0.2, 0.6)}),
    "epipolar_figure": lambda: ((plane_capture(), plane_transport()), {"half_width": 1}),
    "profile_2d_figure": lambda: ((full_transport(),), {"pixels": PIXELS}),
    "relighting_full_figure": lambda: ((full_transport(),), {"projector_cols": 16}),
    "separation_figure": lambda: ((direct_global(5), direct_global(6)), {}),
    "short_range_figure": lambda: ((short_range(),), {}),
    "line_relighting_figure": lambda: ((line_study(),), {}),
    "transport_matrix_figure": lambda: ((plane_transport(),), {"columns": {"wall": 0.2, "ball": 0.7}}),
    "multiplexed_relighting_figure": lambda: ((relighting_snr(3.0), relighting_snr(12.0)), {}),
    "material_figure": lambda: (material_stores(scored=True), {}),
    "vein_figure": lambda: ((delay_choice(),), {}),
    "atlas_figure": lambda: ((atlas(),), {}),
    "appearance_figure": lambda: (appearance(), {}),
}


def figure_stages():
    return [s for s in default_registry() if s.func.__module__.endswith("figures")]


def test_every_figure_stage_is_covered_here():
    assert {s.name for s in figure_stages()} == set(CALLS)


@pytest.mark.parametrize("name", sorted(CALLS))
def test_each_figure_stage_captions_its_figure_before_computing_it(name, no_compute):
    stage = default_registry()[name]
    args, settings = CALLS[name]()
    figure = stage(*args, **settings)
    assert no_compute.count == 0
    caption = figure.attrs.get("caption")
    assert isinstance(caption, str) and len(caption) > 200, caption
    assert "\n" not in caption and "  " not in caption and "``" not in caption  # one paragraph, plain text
    assert "Fig." in caption  # the thesis figure it reproduces (or that it has none)
    assert figure.attrs["selpath_kind"] == "figure"


@pytest.mark.parametrize("name", sorted(CALLS))
def test_each_figure_stage_describes_every_input_and_setting(name):
    stage = default_registry()[name]
    described = {k for k, v in stage.param_docs.items() if v}
    assert set(stage.inputs) | set(stage.params.model_fields) <= described, stage.param_docs


@pytest.mark.parametrize("name", ["capture_figure", "relighting_figure", "relighting_full_figure",
                                  "profile_2d_figure", "delay_profile_figure", "epipolar_figure", "volume_figure"])
def test_figures_of_other_sizes_draw_the_shape_they_declare(name):
    args, settings = CALLS[name]()
    figure = default_registry()[name](*args, **settings)
    declared = figure["image"].shape
    image = figure["image"].values
    assert image.shape == declared and image.dtype == np.uint8 and image[..., :3].std() > 10


def test_as_figure_refuses_no_caption_and_a_render_of_another_size():
    def draw():
        return rgba(panels(size=(3.0, 2.0))[0])

    with pytest.raises(ValueError, match="caption"):
        as_figure(draw, caption=" ")
    with pytest.raises(ValueError, match="declares"):
        as_figure(draw, caption="a figure").image.compute()
    assert as_figure(draw, caption="a\n   figure", size=(3.0, 2.0)).attrs["caption"] == "a figure"


def test_the_object_window_holds_the_object_with_a_margin():
    support = np.zeros((64, 64), bool)
    support[40:44, 10:14] = True
    rows, cols = object_window(support)
    assert rows.stop - rows.start == cols.stop - cols.start == 8  # 4 cells + 30 % each side, at least 8
    assert rows.start < 40 and rows.stop > 44 and cols.start < 10 and cols.stop > 14
    support[:] = False
    support[0:3, 60:64] = True  # at a corner: the window stays on the grid
    rows, cols = object_window(support)
    assert rows.start == 0 and cols.stop == 64 and rows.stop - rows.start == 8
    assert object_window(np.zeros((5, 7), bool)) == (slice(0, 5), slice(0, 7))


def _panel_colours(image: np.ndarray, top: float, bottom: float, left: float, right: float) -> np.ndarray:
    h, w = image.shape[:2]
    return image[int(top * h):int(bottom * h), int(left * w):int(right * w), :3].reshape(-1, 3) / 255.0


def test_the_reconstruction_figure_puts_the_path_bundles_beside_both_models():
    """With a reconstruct_scattering store the figure gains a column (4 × 3 in wide, as declared): its panel is
    titled by the store's σ_s and λ, and its error panel (bottom right) is neutral for an exact bundle
    reconstruction and blue (negative error) for one at half the true σ, while the others stay as they were. A
    bundle reconstruction on another grid is refused with both grids named."""
    truth = np.zeros((64, 64))
    truth[40:44, 10:14] = 0.15

    def bundles(sigma):
        return reconstruction(sigma).assign_attrs(sigma_s=2.0, tv_weight=0.05, method="bundle_lbfgsb_tv")

    figures = [reconstruction_figure(reconstruction(truth), optimised(truth), reconstruction(truth), bundles(b))
               for b in (truth, truth / 2)]
    assert figures[0]["image"].shape == shape_of(reconstruction_size(3, True))
    assert "(d) the path-bundle reconstruction" in figures[0].attrs["caption"]
    assert "(f–h) each reconstruction minus the truth" in figures[0].attrs["caption"]
    exact, wrong = (f["image"].values for f in figures)
    blue = [[(p[:, 2] - p[:, 0] > 0.3).mean() for p in (_panel_colours(i, 0.6, 0.92, left, right) for i in
                                                         (exact, wrong))] for left, right in ((0.72, 0.88),
                                                                                              (0.48, 0.64))]
    assert blue[0][0] == 0 and blue[0][1] > 0.05, blue  # the bundles' error panel
    assert blue[1] == [0, 0], blue  # the optimisation's, exact in both
    coarse = reconstruction(truth[::2, ::2])
    with pytest.raises(StageError, match=r"grids differ: \(y, x\) = \(64, 64\), \(64, 64\), \(32, 32\)"):
        reconstruction_figure(reconstruction(truth), optimised(truth), None, coarse.assign_attrs(sigma_s=1.0))


def test_the_reconstruction_figure_crops_to_the_object_and_shows_the_error():
    """On a 64-cell grid a 4 × 4-cell object fills 0.4 % of the slice; cropped it fills a large part of the truth
    panel (top left). An exact reconstruction leaves the error panel (bottom, right of centre) one neutral colour;
    one at half the true σ turns the object blue there (negative error)."""
    truth = np.zeros((64, 64))
    truth[40:44, 10:14] = 0.15
    exact = reconstruction_figure(reconstruction(truth), optimised(truth), reconstruction(truth))["image"].values
    wrong = reconstruction_figure(reconstruction(truth), optimised(truth / 2), reconstruction(truth))["image"].values
    panel = _panel_colours(exact, 0.1, 0.45, 0.03, 0.3)
    bright = (panel[:, 0] > 0.9) & (panel[:, 1] > 0.75) & (panel[:, 2] < 0.85)  # magma's top (pale yellow)
    assert bright.mean() > 0.1, bright.mean()
    blue = [(p[:, 2] - p[:, 0] > 0.3).mean() for p in (_panel_colours(i, 0.6, 0.92, 0.62, 0.8) for i in
                                                          (exact, wrong))]
    assert blue[0] == 0 and blue[1] > 0.05, blue


def test_the_material_figure_outlines_the_objects_found():
    """A classification made with ``objects`` carries ``object``: panel (c) outlines each object in white (the
    unscored label map is coloured, never white) and the caption says so; without it, no outline is drawn."""
    stage = default_registry()["material_figure"]
    classification, classifier = material_stores(scored=False)
    objects = np.zeros((6, 8), np.int32)
    objects[1:5, 2:6] = 1
    outlined = stage(classification.assign(object=(("row", "col"), objects)), classifier)
    plain = stage(classification, classifier)
    assert "white outlines: the objects found" in outlined.attrs["caption"]
    assert "outlines" not in plain.attrs["caption"]
    a, b = outlined["image"].values, plain["image"].values
    changed = (a != b).any(axis=-1)
    cols = np.flatnonzero(changed.any(axis=0))
    assert changed.sum() > 50 and a.shape[1] * 0.55 < cols.min() < cols.max() < a.shape[1] * 0.8  # panel (c) only
    assert a[changed][:, :3].mean() > b[changed][:, :3].mean() + 40  # lighter: the white outline over the colours
