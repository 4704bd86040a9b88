"""A highlight on the simulated rig (#30): clipped frames bound the light, censored pixels are flagged, and a sweep
whose short exposure stayed unclipped recovers the highlight (HDR from the sweep)."""

from __future__ import annotations

import numpy as np
import pytest

from selpath.stages.procam._capture_to_transport import solve_pixels
from selpath.stages.procam._demux_problem import DemuxProblem
from selpath.stages.procam._demux_solver import DemuxADMM
from selpath.stages.procam._illumination import plane_to_ray_illumination
from selpath.stages.procam.demux import demux_plane_to_ray
from selpath.stages.procam.figures import epipolar_figure, relighting_figure
from tests.helpers.highlight import DELAYS, EXPOSURES, highlight_scene, truth_of
from tests.helpers.procam import capture_of


@pytest.fixture(scope="module")
def all_clipped():
    """A mirror-like disk: direct peak 8 000 counts, twice the clip level, in every frame that sees it."""
    s = highlight_scene(10_000.0, albedo=0.8)
    capture = capture_of(s, DELAYS, EXPOSURES)
    return s, capture, demux_plane_to_ray(capture).compute()


def matrix_of(capture, offsets):
    d, e = np.meshgrid(capture["delay"].values, capture["exposure"].values, indexing="ij")
    return plane_to_ray_illumination(d.ravel(), e.ravel(), offsets, scan_speed=1 / 17, line_time=17.0)


def test_a_highlight_clipped_in_every_frame_was_a_converged_black_hole_and_is_now_a_flagged_lower_bound(all_clipped):
    s, capture, out = all_clipped
    level = s.rig.saturation_level
    frames = capture["image"].values.reshape(-1, s.rig.camera_rows * s.rig.camera_cols).T  # (P, N)
    clipped = frames >= level
    offsets = out["offset"].values
    matrix = matrix_of(capture, offsets)
    assert clipped.any() and np.array_equal(np.all(frames < level, axis=1), ~clipped.any(axis=1))
    # the pixels whose direct offset no unclipped frame sees: exactly those the stage flags
    sees_zero = matrix[:, offsets == 0][:, 0] > 0
    hidden = ~np.any(~clipped & sees_zero, axis=1)
    censored = out["censored"].values.ravel()
    assert hidden.sum() > 100
    np.testing.assert_array_equal(censored, hidden)
    assert not out["converged"].values.ravel()[hidden].any() and out["converged"].values.ravel()[~hidden].all()
    assert float(out["uncensored_fraction"]) == pytest.approx(1 - hidden.mean())

    # before #30 (clipped frames dropped): T ≈ 0 at the peak, and called converged
    problem = DemuxProblem.build(matrix)
    before = solve_pixels(DemuxADMM(), problem, frames / level, ~clipped)
    window = np.abs(offsets) <= 5
    assert np.all(before.value[hidden][:, window].sum(1) < 0.05) and before.converged[hidden].all()

    # after: every clipped frame is explained at the clip level or above (3 %: the pull of α and β), so the
    # peak's window carries at least the level; the truth (8 000) is above the bound, as a bound must be
    transport = out["transport"].values.reshape(offsets.size, -1).T
    prediction = transport @ matrix.T
    assert prediction[clipped].min() >= 0.97 * level
    truth = truth_of(s, offsets).reshape(offsets.size, -1).T
    recovered = transport[hidden][:, window].sum(1)
    assert np.all(recovered >= 0.97 * level) and np.all(recovered <= truth[hidden][:, window].sum(1))
    # the advice: the light must drop by at least the clip ratio (≥ 1 where clipped; the truth needs 8 000/4 095)
    ratio = out["clip_ratio"].values.ravel()
    assert np.all(ratio[hidden] >= 0.97) and np.all(ratio[hidden] <= 8000 / level)
    assert np.all(ratio[~clipped.any(1)] < 1)


def test_pixels_that_never_clip_are_solved_as_before(all_clipped):
    s, capture, out = all_clipped
    frames = capture["image"].values.reshape(-1, s.rig.camera_rows * s.rig.camera_cols).T
    clean = ~np.any(frames >= s.rig.saturation_level, axis=1)
    problem = DemuxProblem.build(matrix_of(capture, out["offset"].values))
    level = s.rig.saturation_level
    before = solve_pixels(DemuxADMM(), problem, frames[clean] / level, np.ones_like(frames[clean], bool))
    after = out["objective"].values.ravel()[clean]  # on images scaled to [0, 1], as the solver reports it
    np.testing.assert_allclose(after, before.stats["objective"], rtol=1e-3)


def test_hdr_from_the_sweep_recovers_a_highlight_its_short_exposure_saw_unclipped():
    """A bright subsurface lobe: the 10-row exposure sees 2 800 counts at most, the 30- and 50-row ones clip.
    The unclipped frames plus the clipped ones as lower bounds recover T as well as a sensor that never clips
    (the same scene rendered without a clip level). Masking the clipped frames (the old rule) does about as well
    here (L2 0.529 against 0.545): the short exposure sees every offset, so the bounds add little; what this
    guards is that keeping clipped frames costs no accuracy and censors nothing where a frame saw the light."""
    s = highlight_scene(7_000.0, albedo=0.9, effects={"subsurface": {"width": "10 px", "fraction": 0.9}})
    capture = capture_of(s, DELAYS, EXPOSURES)
    image = capture["image"].values
    level = s.rig.saturation_level
    assert (image[:, 0] < level).all() and (image[:, 1:] >= level).any()
    out = demux_plane_to_ray(capture).compute()
    unclipped = capture_of(s.with_rig(saturation_level=1e12), DELAYS, EXPOSURES)
    assert unclipped["image"].values.max() > 1.2 * level
    never = demux_plane_to_ray(unclipped, full_scale=level).compute()
    offsets = out["offset"].values
    truth = truth_of(s, offsets)
    lit = (image >= level).any(axis=(0, 1))
    assert lit.sum() > 100 and not out["censored"].values.any() and out["converged"].values.all()

    def error(t):  # relative L2 over the highlight (dominated by the sweep's 10-row resolution of the lobe)
        return np.linalg.norm((t - truth)[:, lit]) / np.linalg.norm(truth[:, lit])

    assert error(out["transport"].values) <= 1.02 * error(never["transport"].values)
    window = np.abs(offsets) <= 5  # the light the 10-row epipolar window gathers: within 3 % of the truth
    np.testing.assert_allclose(out["transport"].values[window].sum(0)[lit], truth[window].sum(0)[lit], rtol=0.03)


def test_relit_and_epipolar_figures_paint_censored_pixels_instead_of_drawing_them_black(all_clipped):
    _, capture, out = all_clipped
    for figure in (relighting_figure(out, lines=(0.5,)), epipolar_figure(capture, out, half_width=5)):
        image = figure["image"].values
        magenta = (image[..., 0] > 200) & (image[..., 1] < 80) & (image[..., 2] > 200)
        assert magenta.sum() > 100, "censored pixels are not marked"
        assert "drawn magenta" in figure.attrs["caption"]
    # a store from before #30 (no censored map) still draws, without the note
    old = out.drop_vars(["censored"])
    assert "magenta" not in relighting_figure(old, lines=(0.5,)).attrs["caption"]
