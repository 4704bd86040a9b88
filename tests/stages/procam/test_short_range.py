"""Short-range sweeps (§5.4.4): the energy a delay range keeps, against the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest
import xarray as xr

from selpath.devices.sim import procam_transport as tr
from selpath.pipeline import StageError
from selpath.stages.procam.demux import demux_plane_to_ray
from selpath.stages.procam.short_range import short_range_images
from tests.helpers.procam import capture_of, scene

RANGES = (0.0, 68.0, 136.0, 272.0)  # µs: 0, 4, 8 and 16 rows at v_p = 1/17 rows/µs
OFFSETS = np.arange(-23, 24)


def truth_transport(s) -> xr.Dataset:
    truth = s.rig.intensity * np.concatenate([tr.truth_tile(s, t, OFFSETS) for t in tr.tiles(s)], axis=-1)
    return xr.Dataset({"transport": (("offset", "row", "col"),
                                     truth.reshape(len(OFFSETS), s.rig.camera_rows, s.rig.camera_cols),
                                     {"units": "counts"})},
                      coords={"offset": ("offset", OFFSETS, {"units": "px"})}, attrs=s.rig.attrs())


def test_energy_within_each_range_is_the_truths():
    """On the simulator's own transport the kept energy is, for each T_dmax, the truth's energy within
    |offset| < v_p·(T_dmax + (t_e + t_p)/2), summed independently here, and so is the floodlit image; the
    capture counts are 2·⌊T/step⌋ + 1."""
    s = scene()
    truth = truth_transport(s)
    out = short_range_images(truth, max_delays=RANGES, delay_step=34.0, exposure=34.0).compute()
    t = truth["transport"].values
    for k, delay in enumerate(RANGES):
        reach = (delay + (34.0 + 17.0) / 2) / 17.0
        kept = t[np.abs(OFFSETS) < reach].sum() / t.sum()
        assert float(out["energy_fraction"][k]) == pytest.approx(kept, rel=1e-12)
    widest = np.abs(OFFSETS) < (RANGES[-1] + 25.5) / 17.0
    np.testing.assert_allclose(out["image"].isel(max_delay=-1).values, t[widest].sum(0), rtol=1e-12)
    assert out["captures"].values.tolist() == [1, 5, 9, 17]
    assert np.all(np.diff(out["energy_fraction"].values) >= 0)


def test_a_demultiplexed_transport_keeps_what_the_truth_keeps():
    """From a simulated sweep (±306 µs every 34 µs, two exposures) demultiplexed at the stage's defaults: the
    kept energy per range within 0.02 of the truth's (measured: 0.859, 0.935, 0.971, 0.998 against 0.853, 0.932,
    0.966, 0.997; the smoothness prior spreads the direct peak over a few rows), growing with the range as the
    truth's does."""
    s = scene()
    transport = demux_plane_to_ray(capture_of(s)).compute()
    got = short_range_images(transport, max_delays=RANGES, delay_step=34.0, exposure=34.0)
    want = short_range_images(truth_transport(s), max_delays=RANGES, delay_step=34.0, exposure=34.0)
    np.testing.assert_allclose(got["energy_fraction"].values, want["energy_fraction"].values, atol=0.02)
    assert np.all(np.diff(got["energy_fraction"].values) >= -1e-9)


def test_a_transport_without_offsets_or_scan_speed_is_refused():
    with pytest.raises(StageError, match="demux_plane_to_ray or demux_full"):
        short_range_images(xr.Dataset({"transport": (("row", "col"), np.zeros((2, 2)))}))


def test_transport_matrix_slices_place_each_offset_at_its_projector_row():
    """Fig. 46's matrix M[s, v] = T(v − s, s, col) for plane-to-ray transport (and T(du = 0, ·) for full): on the
    simulator's truth the direct light sits on the diagonal and every other entry is the truth's own offset cell;
    offsets that would leave the projector are 0, and the matrix holds the column's whole transport."""
    from selpath.stages.procam.application_figures import column_slice, transport_matrix

    s = scene()
    truth = truth_transport(s)
    col = 10
    matrix = transport_matrix(column_slice(truth, col).values, truth["offset"].values)
    t = truth["transport"].isel(col=col).values  # (offset, row)
    rows = s.rig.camera_rows
    for k, o in enumerate(truth["offset"].values):
        for r in range(rows):
            if 0 <= r + o < rows:
                assert matrix[r, r + o] == t[k, r]
    assert matrix.sum() == pytest.approx(t.sum(), rel=1e-12)  # truth carries nothing off the projector
    assert np.all(np.argmax(matrix, axis=1)[matrix.max(axis=1) > 0] == np.flatnonzero(matrix.max(axis=1) > 0))
    full = xr.Dataset({"transport": (("du", "dv", "row", "col"), np.stack([0 * truth["transport"].values,
                                                                            truth["transport"].values]))},
                      coords={"du": [-10.0, 0.0], "dv": truth["offset"].values})
    np.testing.assert_array_equal(transport_matrix(column_slice(full, col).values, full["dv"].values), matrix)
