"""Every variable a kind declares carries the units and long name the kind fixes: written so whatever a stage
(or a user) handed in, checked on open, and corrected on open for stores of formats 1–3 (whose sinograms and
coverages carried θ's attrs, and flags and hull vertices "counts")."""

from __future__ import annotations

import numpy as np
import pytest
import zarr

from selpath.pipeline import StoreError, open_store, to_store
from selpath.pipeline.kinds import FORMAT_VERSION
from selpath.pipeline.store import IncompleteStoreWarning
from tests.helpers.stores import KINDS, minimal


def expected(kind: str, length: str = "mm") -> dict[str, tuple[str | None, str]]:
    """The kind's declared (units, long_name), resolved by hand (an independent reading of the table)."""
    out = {}
    for name, var in KINDS[kind].variables.items():
        if var.units == "":
            continue
        units = None if var.units is None else var.units.replace("{length}", length)
        out[name] = (units, var.long_name)
    return out


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_a_store_of_every_kind_carries_its_kinds_metadata_whatever_it_was_given(tmp_path, kind):
    ds = minimal(kind).assign_attrs(length_unit="mm")
    for name in ds.data_vars:  # what apply_ufunc hands a stage: the first input's attrs
        ds[name].attrs.update(units="degree", long_name="normal angle θ of the ray")
    to_store(ds, tmp_path / "s.zarr", kind)
    back = open_store(tmp_path / "s.zarr")
    want = expected(kind)
    assert want, f"{kind} declares no variable metadata"
    for name, (units, long_name) in want.items():
        assert back[name].attrs.get("units") == units, name
        assert back[name].attrs.get("long_name") == long_name, name
    assert KINDS[kind].metadata(back) == want


def test_a_store_whose_units_were_edited_is_refused(tmp_path):
    to_store(minimal("sinogram"), tmp_path / "s.zarr", "sinogram")
    zarr.open_array(str(tmp_path / "s.zarr" / "absorption"), mode="r+").attrs["units"] = "degree"
    with pytest.raises(StoreError, match=r"'absorption' has units 'degree' but was written in '1'"):
        open_store(tmp_path / "s.zarr")


def test_a_format_3_store_with_a_coordinates_attrs_opens_with_the_right_ones(tmp_path):
    """The reported case: sinogram.zarr's absorption, count and observed said 'degree', 'normal angle θ'."""
    ds = minimal("sinogram").assign_attrs(selpath_format=3, selpath_kind="sinogram")
    theta = {"units": "degree", "long_name": "normal angle θ of the ray"}
    for name in ("absorption", "observed", "count"):
        ds[name].attrs.update(theta)
    ds.to_zarr(tmp_path / "old.zarr", consolidated=False)
    with pytest.warns(IncompleteStoreWarning):  # written by plain xarray: no completion record
        back = open_store(tmp_path / "old.zarr")
    assert back["absorption"].attrs["units"] == "1" and back["count"].attrs["units"] == "1"
    assert "units" not in back["observed"].attrs
    assert back["absorption"].attrs["long_name"].startswith("total absorption")


def test_a_format_4_transport_gets_its_solver_variables_metadata_on_open(tmp_path):
    """Format 4 wrote a transport's iterations, converged, frames_used and objective bare; format 5 declares them."""
    ds = minimal("plane_to_ray_transport").assign_attrs(selpath_format=4, selpath_kind="plane_to_ray_transport")
    for name in ("iterations", "converged", "frames_used", "objective"):
        ds[name].attrs.clear()
    ds.to_zarr(tmp_path / "old.zarr", consolidated=False)
    with pytest.warns(IncompleteStoreWarning):  # written by plain xarray: no completion record
        back = open_store(tmp_path / "old.zarr")
    assert back["iterations"].attrs == {"units": "1", "long_name": "ADMM iterations run for the pixel"}
    # a mask: no units; its meaning then (clipped frames masked), and a note on what that hides
    assert back["converged"].attrs == {
        "long_name": "the pixel's solve met its tolerance (clipped frames masked: not censoring-aware)"}
    assert back["objective"].attrs["units"] == "1" and back["frames_used"].attrs["units"] == "1"
    assert "may hold T ≈ 0" in back.attrs["selpath_note"]


def test_a_format_6_transport_has_no_note_and_the_censoring_aware_meaning(tmp_path):
    to_store(minimal("plane_to_ray_transport"), tmp_path / "new.zarr", kind="plane_to_ray_transport")
    back = open_store(tmp_path / "new.zarr")
    assert "selpath_note" not in back.attrs
    assert "no offset's light is censored" in back["converged"].attrs["long_name"]


def test_a_current_store_in_wrong_units_is_refused_naming_the_variable(tmp_path):
    ds = minimal("reconstruction").assign_attrs(selpath_format=FORMAT_VERSION, selpath_kind="reconstruction")
    ds["sigma"].attrs["units"] = "1/cm"  # the grid is in mm
    ds.to_zarr(tmp_path / "r.zarr", consolidated=False)
    wrong = r"variable 'sigma' is in '1/cm'; a reconstruction holds it in '1/mm'"
    with pytest.raises(StoreError, match=wrong):  # (refused before the missing completion record is reported)
        open_store(tmp_path / "r.zarr")


def test_stage_outputs_carry_the_metadata_before_they_are_stored():
    """In a notebook, without a store: the sinogram and coverage no longer inherit θ's attrs."""
    from tests.helpers.tomography import lazy_chain

    _, hull, sino, cover = lazy_chain()
    for ds, kind in ((hull, "hull"), (sino, "sinogram"), (cover, "coverage")):
        for name, (units, long_name) in KINDS[kind].metadata(ds).items():
            assert ds[name].attrs.get("units") == units and ds[name].attrs.get("long_name") == long_name, name
    for name in ("analytic_d_min", "analytic_d_max", "analytic_coverage", "radius", "observed_fraction"):
        ds = cover if name in cover else sino
        assert ds[name].attrs.get("units") != "degree", name
    assert np.isfinite(float(sino["observed_fraction"].compute()))


def test_a_format_5_tomography_capture_names_its_clip_level_as_projector_camera_captures_do(tmp_path):
    """One name for the sensor's clip level across both instruments: format ≤ 5 tomography stores wrote
    ``saturation_level``; on open it is ``saturation_counts``, and the stages still read the old name."""
    ds = KINDS["tomography_capture"].label(minimal("tomography_capture")).assign_attrs(
        selpath_format=5, selpath_kind="tomography_capture", saturation_level=1000.0)
    ds.to_zarr(tmp_path / "old.zarr", consolidated=False)
    with pytest.warns(IncompleteStoreWarning):
        back = open_store(tmp_path / "old.zarr")
    assert back.attrs["saturation_counts"] == 1000.0 and "saturation_level" not in back.attrs
