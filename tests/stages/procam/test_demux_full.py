"""demux_full on (delay, exposure, line) stacks from the time-integrating simulator, and its Kronecker solver
against CVXPY on the dense problem it never forms."""

from __future__ import annotations

import cvxpy as cp
import jax
import numpy as np
import pytest
import xarray as xr

from selpath.devices.sim import procam_lobes as lobes
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.pipeline.errors import StageError
from selpath.stages.procam._demux_problem import SeparableDemuxProblem
from selpath.stages.procam._demux_solver import DemuxADMM
from selpath.stages.procam._illumination import box_overlap, line_cells, line_illumination, plane_to_ray_illumination
from selpath.stages.procam.demux_full import demux_full
from selpath.stages.procam.full_figures import profile_2d_figure, relighting_full_figure
from selpath.stages.procam.relight import cell_average, checkerboard_relight, relight_full
from tests.helpers.full_transport import DELAYS, EXPOSURES, GRID, LINES, WIDTH, full_capture, scene


@pytest.fixture(scope="module")
def noise_free():
    s = scene()
    capture = full_capture(s)
    out = demux_full(capture, offsets=GRID, alpha=1e-3, beta=1e-4, tol=1e-4, max_iter=600).compute()
    return s, capture, out


def truth_u_direct(s: ProcamScene) -> np.ndarray:
    return np.concatenate([lobes.tile_lobes(s, t)[1] for t in tr.tiles(s)]).reshape(s.rig.camera_rows, -1)


def test_round_trip_reproduces_the_frames(noise_free):
    """T → every (line, delay) frame through the boxes of Eq. 38 written out per pixel (not the solver's
    Kronecker operators): within 2 % of the simulator's images (the regularisation's bias)."""
    _, capture, out = noise_free
    step = out.attrs["cell_width_px"]
    u = out["u_direct"].values[None] + out["du"].values[:, None, None]  # (du, r, c) absolute cell centres
    t = np.nan_to_num(out["transport"].values)  # (du, dv, r, c)
    for i, delay in enumerate(DELAYS):
        w_v = plane_to_ray_illumination([delay], EXPOSURES, out["dv"].values, scan_speed=capture.attrs[
            "scan_speed_px_per_us"], line_time=capture.attrs["line_time_us"])[0]
        if out.attrs["frames_dropped"] and [delay, EXPOSURES[0]] in out.attrs["frames_dropped"]:
            continue
        for j, line in enumerate(LINES):
            w_u = box_overlap(line - WIDTH / 2, line + WIDTH / 2, u - step / 2, u + step / 2) / step
            predicted = np.einsum("arc,abrc,b->rc", np.nan_to_num(w_u), t, w_v)
            image = capture["image"].values[i, 0, j]
            assert np.abs(predicted - image).max() <= 0.02 * capture["image"].values.max(), (delay, line)
    assert out["converged"].mean() >= 0.95
    assert np.nanmin(out["transport"].values) >= 0


def test_direct_correspondence_and_light_match_the_simulator(noise_free):
    """u₀ within one cell (2 columns) of the simulator's direct column, disparity included. Against the
    simulator's plane-to-ray truth: the epipolar light Σ_du T(du, dv = 0) within 3 % of the brightest pixel
    and each pixel's total within 1.5 % where light stays on the surface (background, page); on the candle
    (subsurface lobes 1.5 px wide in u and v) within 12 % and 8 %: N = 204 frames against K = 425 cells
    leave the prior to shape the lobe, and β's shrinkage takes ~7 % (measured: 3 % at α, β 100× smaller)."""
    s, _, out = noise_free
    error = np.abs(out["u_direct"].values - truth_u_direct(s))
    assert np.nanmax(error) <= out.attrs["cell_width_px"], np.nanmax(error)
    candle = (lobes.Tile.of(s, 0, s.rig.camera_rows).label == 0).reshape(s.rig.camera_rows, -1)
    assert candle.sum() > 50
    truth = s.rig.intensity * np.concatenate([tr.truth_tile(s, t, out["dv"].values) for t in tr.tiles(s)], axis=-1)
    truth = truth.reshape(-1, *candle.shape)
    epipolar = np.nansum(out["transport"].sel(dv=0).values, axis=0)
    truth0 = truth[list(out["dv"].values).index(0)]
    top = truth0.max()
    assert np.abs(epipolar - truth0)[~candle].max() <= 0.03 * top
    assert np.abs(epipolar - truth0)[candle].max() <= 0.12 * top
    total = np.nansum(out["transport"].values, axis=(0, 1))
    relative = np.abs(total - truth.sum(0)) / truth.sum(0)
    assert relative[~candle].max() <= 0.015 and relative[candle].max() <= 0.08, (relative[~candle].max(),
                                                                                 relative[candle].max())


def test_specular_interreflection_sits_at_its_displacement(noise_free):
    """The page's specular lobe comes from du = −6 columns, dv = +2 rows: the largest indirect cell there."""
    _, _, out = noise_free
    pixel = out["transport"].isel(row=8, col=18)  # the ball's centre (0.75, 0.5)
    indirect = pixel.where((abs(pixel["du"]) > 2) | (abs(pixel["dv"]) > 1), 0)
    du, dv = np.unravel_index(int(np.nanargmax(indirect.values)), indirect.shape)
    assert abs(float(indirect["du"][du]) + 6) <= out.attrs["cell_width_px"] and abs(int(indirect["dv"][dv]) - 2) <= 1


def test_relighting_a_2d_pattern_matches_a_global_shutter_render(noise_free):
    """Relit under a cosine of the columns × a band of rows (separable, so the simulator can render it with
    its global shutter, each row lit once): within 4 % of the render's brightest pixel off the candle, 8 % on
    it (β's shrinkage, as above). T is known per 2-column cell and a direct delta on a cell edge is split
    between two cells, so the pattern must vary slowly across a cell: one cosine period over the projector
    (measured: a 12-column period costs 14 % on the candle; a sharp stripe edge is averaged over the cell,
    the resolution the sweep buys)."""
    s, _, out = noise_free
    candle = (lobes.Tile.of(s, 0, s.rig.camera_rows).label == 0).reshape(s.rig.camera_rows, -1)
    columns = 0.5 + 0.5 * np.cos(2 * np.pi * np.arange(24) / 24)
    rows = ((np.arange(16) >= 4) & (np.arange(16) < 12)).astype(float)
    pattern = np.outer(rows, columns)
    render = tr.render_frame(s, -s.rig.line_time, s.rig.row_period * 16 + 2 * s.rig.line_time, pattern,
                             shutter="global")
    ours = relight_full(out, pattern).values
    assert np.abs(ours - render)[~candle].max() <= 0.04 * render.max()
    assert np.abs(ours - render)[candle].max() <= 0.08 * render.max()
    white = tr.render_frame(s, -s.rig.line_time, s.rig.row_period * 16 + 2 * s.rig.line_time, shutter="global")
    relit_white = relight_full(out, np.ones((16, 24))).values
    assert np.abs(relit_white - white).max() <= 0.08 * white.max()  # the candle's β shrinkage, as above


def test_checkerboard_relighting_matches_the_simulator_away_from_square_edges(noise_free):
    """Fig. 41 on the simulated rig: an 8-px checkerboard is p_r ⊗ n_c + n_r ⊗ p_c (p, n: the even and odd
    squares along rows and columns), two separable patterns the simulator renders with its global shutter.
    A square edge is resolved to a 2-column cell, so pixels whose direct correspondence lies within a cell of
    a column edge (or a row of a row edge) are left out; elsewhere within 5 % of the render's brightest pixel
    off the candle, 10 % on it (measured 3.7 % and 7.6 %; 28 % at the edges left out). The two
    boards sum to the white relighting (linearity, to float32 rounding)."""
    s, _, out = noise_free
    relit = checkerboard_relight(out, 8, 24).compute()
    even_r, even_c = (np.arange(16) // 8) % 2 == 0, (np.arange(24) // 8) % 2 == 0
    window = (-s.rig.line_time, s.rig.row_period * 16 + 2 * s.rig.line_time)
    truth = sum(tr.render_frame(s, *window, np.outer(r, c).astype(float), shutter="global")
                for r, c in ((even_r, ~even_c), (~even_r, even_c)))
    u0 = truth_u_direct(s)
    rows = np.arange(16)[:, None] * np.ones((1, 24))
    away = (np.min(np.abs(u0[..., None] - np.array([7.5, 15.5])), axis=-1) >= 2) & (np.abs(rows - 7.5) >= 1.5)
    candle = (lobes.Tile.of(s, 0, s.rig.camera_rows).label == 0).reshape(s.rig.camera_rows, -1)
    error = np.abs(relit["checkerboard"].values - truth)
    assert away.sum() >= 150
    assert error[away & ~candle].max() <= 0.05 * truth.max(), error[away & ~candle].max() / truth.max()
    assert error[away & candle].max() <= 0.10 * truth.max(), error[away & candle].max() / truth.max()
    both = relit["checkerboard"] + relit["complement"]
    np.testing.assert_allclose(both, relit["white"], rtol=1e-4, atol=1e-5 * float(relit["white"].max()))


def test_full_transport_figures_draw_and_refuse_plane_to_ray_transport(noise_free):
    _, _, out = noise_free
    for figure in (profile_2d_figure(out, pixels={"candle": (0.2, 0.5), "page": (0.8, 0.5)}),
                   relighting_full_figure(out)):
        image = figure["image"].values
        assert image.dtype == np.uint8 and image.shape[-1] == 4 and image[..., :3].std() > 10
    plane = xr.Dataset({"transport": (("offset", "row", "col"), np.zeros((3, 4, 5)))})
    with pytest.raises(StageError, match="demux_full"):
        profile_2d_figure(plane, pixels={"a": (0.5, 0.5)})
    with pytest.raises(StageError, match="demux_full"):
        relighting_full_figure(plane)


def test_cell_average_is_the_pixel_coverage_mean():
    pattern = np.array([[0.0, 1.0, 1.0, 0.0, 0.5]])
    # cells [0, 2], [0.5, 2.5], [3, 5] (half on the projector, which ends at 4.5), [5, 7] (off it)
    np.testing.assert_allclose(cell_average(pattern, np.array([1.0, 1.5, 4.0, 6.0]), 2.0),
                               [[(0.5 * 0 + 1 + 0.5 * 1) / 2, 1.0, (0.5 * 0 + 0.5 * 1) / 1.5, 0.0]])


def test_line_illumination_rows_sum_to_the_line_width():
    cells, step = line_cells(LINES, WIDTH)
    assert step == 2.0 and cells[0] == -1.0 and cells.size == 13
    np.testing.assert_allclose(line_illumination(LINES, WIDTH, cells, step).sum(1) * step, WIDTH)


def test_kronecker_solver_matches_cvxpy_on_the_dense_problem():
    """The separable solver (never forming A = L_u ⊗ L) against CVXPY/Clarabel with A formed densely: the
    objective within 1e-4 relative of the optimum, including a rank-deficient sweep (N = 24 < K = 63)."""
    cells, step = line_cells(np.arange(0.0, 9.0, 2.0), 4.0)  # 5 lines on 6 cells
    a_u = line_illumination(np.arange(0.0, 9.0, 2.0), 4.0, cells, step)
    d, e = np.meshgrid([-51.0, 0.0, 51.0], [17.0, 85.0], indexing="ij")
    offsets = np.arange(-5, 6)
    a_v = plane_to_ray_illumination(d.ravel(), e.ravel(), offsets, scan_speed=1 / 17, line_time=17)
    problem = SeparableDemuxProblem.build(a_u, a_v)
    rng = np.random.default_rng(5)
    truth = rng.random((6, cells.size, offsets.size)) ** 6
    data = np.einsum("ju,puv,nv->pjn", a_u, truth, a_v).reshape(6, -1) + rng.normal(0, 0.005, (6, 30))
    with jax.enable_x64(True):
        ours = DemuxADMM(tol=1e-9, max_iter=20000, polish_iter=40, dtype="float64").solve(problem, data)
    dense = np.kron(a_u, a_v)
    t, y = cp.Variable((cells.size, offsets.size)), cp.Parameter(dense.shape[0])
    qp = cp.Problem(cp.Minimize(cp.sum_squares(dense @ cp.vec(t, order="C") - y) + problem.alpha
                                * cp.sum_squares(cp.diff(t, axis=1)) + problem.beta * cp.sum(t)), [t >= 0])
    for p in range(data.shape[0]):
        y.value = data[p]
        qp.solve(solver=cp.CLARABEL)
        value = problem.objective(ours.value[p:p + 1], data[p:p + 1])[0]
        assert (value - qp.value) / abs(qp.value) <= 1e-4
        # the objective helper is the dense formula
        assert problem.objective(t.value.reshape(1, -1), data[p:p + 1])[0] == pytest.approx(qp.value, rel=1e-6)
    assert ours.converged.all()


def test_plane_to_ray_captures_and_missing_line_width_are_refused(noise_free):
    _, capture, _ = noise_free
    with pytest.raises(StageError, match="demux_plane_to_ray"):
        demux_full(capture.isel(line=0, drop=True))
    with pytest.raises(StageError, match="line_width_px"):
        demux_full(capture.drop_attrs(deep=False).assign_attrs(
            {k: v for k, v in capture.attrs.items() if k != "line_width_px"}))


def test_relighting_snr_renders_the_same_board_and_measures_the_error_on_lit_pixels(noise_free):
    """full_relighting_snr (Fig. 43): its truth is the simulator's render of the very board that
    relighting_full_figure relights (8 px squares: the two separable halves rendered here independently, and
    white), and its SNR is 10·log10(Σ truth² / Σ error²) over the pixels lit at 5 % of the brightest,
    recomputed here; on the noise-free sweep only the prior's bias is left (measured 15.4 and 26.4 dB)."""
    from selpath.stages.procam.multiplexing import full_relighting_snr

    s, capture, out = noise_free
    study = full_relighting_snr(capture.assign_attrs(simulated_scene=s.model_dump(mode="json")), out)
    even_r, even_c = (np.arange(16) // 8) % 2 == 0, (np.arange(24) // 8) % 2 == 0
    window = (-2 * s.rig.line_time, s.rig.row_period * 16 + 5 * s.rig.line_time)
    board = sum(tr.render_frame(s, *window, np.outer(r, c).astype(float), shutter="global")
                for r, c in ((~even_r, even_c), (even_r, ~even_c)))
    white = tr.render_frame(s, *window, shutter="global")
    for name, truth in (("checkerboard", board), ("floodlit", white)):
        np.testing.assert_allclose(study["truth"].sel(pattern=name), truth, rtol=1e-5, atol=1e-3)
        lit = truth >= 0.05 * truth.max()
        relit = study["image"].sel(pattern=name).values
        expected = 10 * np.log10(np.sum(truth[lit] ** 2) / np.sum((relit[lit] - truth[lit]) ** 2))
        assert float(study["snr_db"].sel(pattern=name)) == pytest.approx(expected, abs=0.01)
    assert study.attrs["square_px"] == 8 and float(study["snr_db"].min()) > 10.0
    with pytest.raises(StageError, match="would split cells"):
        full_relighting_snr(capture.assign_attrs(simulated_scene=s.model_dump(mode="json")), out, square_px=3)


def test_the_accessor_relights_full_transport_and_its_dv_carries_the_sync_delay(noise_free):
    """The ``.selpath`` accessor on a full transport: any 2-D pattern (relight_full's), a row pattern lighting every
    projector column, the epipolar image of T summed over du, the 2-D profile; dv's sync delay o / v_p − t_o."""
    s, _, out = noise_free
    columns = 0.5 + 0.5 * np.cos(2 * np.pi * np.arange(24) / 24)
    rows = ((np.arange(16) >= 4) & (np.arange(16) < 12)).astype(float)
    pattern = np.outer(rows, columns)
    np.testing.assert_allclose(out.selpath.relight(pattern).values, relight_full(out, pattern).values)
    np.testing.assert_allclose(out.selpath.relight(rows=range(4, 12)).values,
                               relight_full(out, np.repeat(rows[:, None], 24, axis=1)).values)
    np.testing.assert_allclose(out.selpath.epipolar().values,
                               out["transport"].sum("du").sel(dv=0).values, rtol=1e-6)
    profile = out.selpath.profile(row=8, col=12)
    assert profile.dims == ("du", "dv") and profile["sync_delay"].dims == ("dv",)
    np.testing.assert_allclose(out["sync_delay"].values, out["dv"].values / s.rig.scan_speed - s.rig.sync_offset)
    assert out["sync_delay"].attrs["units"] == "us"
