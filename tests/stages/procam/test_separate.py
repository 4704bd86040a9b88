"""Direct/global separation (Nayar et al.; §5.4.6): the closed form with the projector's black level, bad shift sets
and saturated frames, and the simulator's own direct and global light (it renders both apart)."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.devices import patterns
from selpath.devices.sim import procam_lobes as lobes
from selpath.devices.sim import procam_transport as tr
from selpath.devices.sim.procam_scene import ProcamScene
from selpath.pipeline import StageError
from selpath.pipeline.quality import enforce
from selpath.stages.procam.separate import SATURATED, separate_direct_global, shift_problems


def stack(frames: np.ndarray, shifts, square=(4, 4), **attrs) -> xr.Dataset:
    shifts = np.asarray(shifts)
    return xr.Dataset({"image": (("shift", "row", "col"), frames, {"units": "counts"})},
                      coords={"shift_row": ("shift", shifts[:, 0]), "shift_col": ("shift", shifts[:, 1])},
                      attrs={"square_px": list(square), **attrs})


@pytest.mark.parametrize("b", [0.0, 0.2])
def test_the_closed_form_recovers_direct_and_global_exactly(b):
    """Frames made by the model itself (lit: L_d + (1 + b)·L_g/2, dark: b·L_d + (1 + b)·L_g/2), each pixel lit
    under one of the two boards: L_d and L_g come back to float64 rounding (1e-12 of the pixel's L_d + L_g: a
    difference of frames, so a faint L_d under a bright L_g carries the bright one's rounding), over 1e-3…1e3;
    b = 0 is the classic max − min and 2·min."""
    rng = np.random.default_rng(0)
    direct, global_ = 10 ** rng.uniform(-3, 3, (2, 6, 7))
    lit_first = rng.random((6, 7)) < 0.5
    lit, dark = direct + (1 + b) * global_ / 2, b * direct + (1 + b) * global_ / 2
    frames = np.stack([np.where(lit_first, lit, dark), np.where(lit_first, dark, lit)])
    out = separate_direct_global(stack(frames, [(0, 0), (0, 4)]), black_level=b)
    scale = 1e-12 * (direct + global_)
    assert (abs(out["direct"].values - direct) <= scale).all() and (abs(out["global"].values - global_) <= scale).all()
    if b == 0:
        np.testing.assert_array_equal(out["direct"].values, frames.max(0) - frames.min(0))
        np.testing.assert_array_equal(out["global"].values, 2 * frames.min(0))
    assert (out["flags"].values == 0).all() and float(out["unsaturated_fraction"]) == 1.0


def test_shift_sets_that_cannot_separate_are_named():
    assert shift_problems((4, 4), [(0, 0), (0, 4)]) == []  # a board and its complement
    assert shift_problems((4, 4), [(0, 0), (0, 2), (0, 4), (0, 6)]) == []
    assert len(shift_problems((4, 4), [(0, 0), (4, 4)])) == 2  # a whole square both ways: the same board
    (few,) = shift_problems((4, 4), [(0, 0)])
    assert "needs at least 2" in few
    half = shift_problems((4, 4), [(0, 0), (0, 1)])  # a one-pixel step: most phases lit (or dark) both times
    assert len(half) == 2 and half[0].startswith("38% of the board's phases are never lit")
    frames = np.zeros((2, 3, 3))
    with pytest.raises(StageError, match="never lit under these shifts.*capture more shifts"):
        separate_direct_global(stack(frames, [(0, 0), (0, 1)]))
    with pytest.raises(StageError, match="does not say which boards it holds"):
        separate_direct_global(xr.Dataset({"image": (("shift", "row", "col"), frames)}))
    with pytest.raises(StageError, match="black_level is 1.0"):
        separate_direct_global(stack(frames, [(0, 0), (0, 4)]), black_level=1.0)


def test_saturated_frames_are_flagged_and_a_mostly_saturated_stack_is_refused():
    frames = np.full((2, 4, 5), 100.0)
    frames[0] += 50.0
    frames[0, 1, 2] = 4095.0
    out = separate_direct_global(stack(frames, [(0, 0), (0, 4)], saturation_counts=4095.0))
    assert out["flags"].values[1, 2] == SATURATED and np.isnan(out["direct"].values[1, 2])
    assert np.nansum(out["direct"].values) == 50.0 * 19 and float(out["unsaturated_fraction"]) == 19 / 20
    frames[0] = 4095.0
    with pytest.raises(StageError, match="lower the exposure"):
        enforce(separate_direct_global(stack(frames, [(0, 0), (0, 4)], saturation_counts=4095.0)))


RIG = {"camera_rows": 96, "camera_cols": 96, "projector_rows": 96, "projector_cols": 96, "bits": None}
BROAD = {"name": "corner", "region": {"kind": "rectangle", "x": [0.05, 0.95], "y": [0.05, 0.95]}, "albedo": 0.8,
         "effects": {"diffuse_interreflection": {"corner_x": 0.5, "strength": 0.4}}}
MIRROR = {"name": "mirror", "region": {"kind": "rectangle", "x": [0.05, 0.95], "y": [0.05, 0.95]}, "albedo": 0.8,
          "effects": {"specular_interreflection": {"centre": [0.5, 0.5], "reach": 0.3,
                                                   "displacement": ["12 px", "20 px"], "strength": 0.5}}}
DIRECT_ONLY = dict.fromkeys(lobes.EFFECTS, lambda *_: [])
SQUARE, SHIFTS = 4, [(r, c) for r in (0, 2, 4, 6) for c in (0, 2, 4, 6)]  # 16 half-square steps over a period


def _boards(s: ProcamScene, mode: str, effects=None) -> xr.Dataset:
    window = (-100.0, 2000.0, "global") if mode == "floodlit" else (0.0, s.rig.line_time, "rolling")
    frames = np.stack([tr.render_frame(s, window[0], window[1], patterns.checkerboard(
        (s.rig.projector_rows, s.rig.projector_cols), SQUARE, shift), shutter=window[2], effects=effects)
        for shift in SHIFTS])
    return stack(frames, SHIFTS, (SQUARE, SQUARE))


def _interior(shape, margin=12):
    inside = np.zeros(shape, bool)
    inside[margin:-margin, margin:-margin] = True
    return inside


def test_against_the_simulators_own_direct_and_global_light():
    """A broad diffuse inter-reflection (its spread ≫ the 4-px board): Nayar's direct and global images match the
    simulator's direct-only render and the rest of the floodlit render (white minus direct) within 5 % of the
    floodlit light, away from the object's edges (the goal of the issue)."""
    s = ProcamScene.model_validate({"scene": "broad", "background": {"albedo": 0.3}, "objects": [BROAD], "rig": RIG})
    out = separate_direct_global(_boards(s, "floodlit"))
    white = tr.render_frame(s, -100.0, 2000.0, shutter="global")
    direct = tr.render_frame(s, -100.0, 2000.0, shutter="global", effects=DIRECT_ONLY)
    inside = _interior(white.shape)
    assert (white - direct)[inside].mean() > 0.05 * white[inside].mean()  # global light is there to separate
    for got, want in ((out["direct"].values, direct), (out["global"].values, white - direct)):
        assert np.abs(got - want)[inside].max() < 0.05 * white[inside].max()


def test_nayar_keeps_a_specular_interreflection_that_the_epipolar_separation_removes():
    """The known failure as a number: a mirror-like inter-reflection (light displaced 12 rows and 20 columns, as
    sharp as direct light) counts as direct for Nayar's floodlit method; separated from epipolar frames it is gone,
    since it comes from another epipolar plane. Measured on the region it lands on: Nayar's direct keeps 49 % of
    the reflection's energy (the reflection's lobe is a few pixels wide, so the 4-px board partly averages it);
    the epipolar direct under 10 % of it (≥ 90 % removed, the issue's goal)."""
    s = ProcamScene.model_validate({"scene": "mirror", "background": {"albedo": 0.3}, "objects": [MIRROR],
                                    "rig": RIG})
    white = tr.render_frame(s, -100.0, 2000.0, shutter="global")
    true_direct = tr.render_frame(s, -100.0, 2000.0, shutter="global", effects=DIRECT_ONLY)
    specular = white - true_direct
    region = _interior(white.shape) & (specular > 0.2 * specular.max())
    assert region.sum() > 50
    nayar = separate_direct_global(_boards(s, "floodlit"))["direct"].values
    epipolar = separate_direct_global(_boards(s, "epipolar"))["direct"].values
    epipolar_direct = tr.render_frame(s, 0.0, s.rig.line_time, effects=DIRECT_ONLY)
    kept_by_nayar = (nayar - true_direct)[region].sum() / specular[region].sum()
    kept_by_epipolar = (epipolar - epipolar_direct)[region].sum() / specular[region].sum()
    assert kept_by_nayar > 0.4, kept_by_nayar
    assert abs(kept_by_epipolar) < 0.1, kept_by_epipolar


def test_the_dark_level_is_subtracted_and_a_missing_frame_is_flagged():
    """Frames on a 64-count sensor offset: L_g = 2·(min − dark), not 2·min; saturation is judged on raw counts; a
    NaN frame flags its pixel nonfinite."""
    from selpath.stages.procam.separate import NONFINITE

    frames = np.full((2, 2, 3), 100.0)
    frames[0] += 30.0
    frames[1, 0, 0] = np.nan
    out = separate_direct_global(stack(frames, [(0, 0), (0, 4)], dark_level_counts=64.0, saturation_counts=130.0))
    assert out["flags"].values[0, 0] & NONFINITE and np.isnan(out["global"].values[0, 0])
    assert (out["flags"].values.ravel()[1:] == SATURATED).all()  # 130 raw counts: at the saturation level
    below = separate_direct_global(stack(frames, [(0, 0), (0, 4)], dark_level_counts=64.0, saturation_counts=4095.0))
    np.testing.assert_array_equal(below["global"].values.ravel()[1:], 2 * (100.0 - 64.0))
    np.testing.assert_array_equal(below["direct"].values.ravel()[1:], 30.0)
