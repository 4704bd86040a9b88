"""The camera models of selpath.geometry.rig: one declaration of their attrs, projection against back-projection."""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest

from selpath.devices.hardware import GeometryConfig
from selpath.geometry.rig import (
    CAMERA_ATTRS,
    CAMERAS,
    GEOMETRY_ATTRS,
    RIG_ATTRS,
    OrthographicCamera,
    PerspectiveCamera,
    RigGeometry,
)
from selpath.pipeline import StageError

CAMERA_CASES = {
    "perspective": PerspectiveCamera(rows=7, cols=11, focal_length_px=40.0, camera_distance=80.0,
                                     principal_point_px=(5.5, 2.25)),
    "orthographic": OrthographicCamera(rows=7, cols=11, pixel_size=0.3),
}


def rig(camera) -> RigGeometry:
    return RigGeometry(camera, light_angle_deg=60.0, length_unit="mm", light_distance=300.0, light_kind="beam",
                       beam_height=0.45)


def test_the_camera_classes_and_the_schema_declare_the_same_models_and_attrs():
    assert set(CAMERAS) == set(CAMERA_ATTRS)
    for model, cls in CAMERAS.items():
        known = {f.name for f in fields(cls)} | {f.name for f in fields(RigGeometry)}
        assert set(CAMERA_ATTRS[model]) <= known, model
    assert set(RIG_ATTRS) <= set(GEOMETRY_ATTRS)


def test_the_hardware_config_takes_exactly_the_geometry_attrs():
    assert set(GeometryConfig.model_fields) == set(GEOMETRY_ATTRS)
    with pytest.raises(ValueError, match="attr 'focal_length_px' is required for a perspective camera"):
        GeometryConfig(camera_model="perspective", light_angle_deg=45, length_unit="mm", camera_distance=400,
                       light_distance=300)
    GeometryConfig(camera_model="perspective", light_angle_deg=45, length_unit="mm", focal_length_px=2400,
                   camera_distance=400, light_distance=300)  # the principal point defaults to the sensor's centre


def test_the_hardware_config_refuses_the_other_camera_models_settings():
    """They used to be written into the capture's attrs and now would be ignored: a config mistake, said so."""
    with pytest.raises(ValueError, match="focal_length_px is not a setting of an orthographic camera"):
        GeometryConfig(camera_model="orthographic", light_angle_deg=0, length_unit="mm", pixel_size=0.1,
                       focal_length_px=2400)
    with pytest.raises(ValueError, match="pixel_size is not a setting of a perspective camera"):
        GeometryConfig(camera_model="perspective", light_angle_deg=45, length_unit="mm", focal_length_px=2400,
                       camera_distance=400, light_distance=300, pixel_size=0.1)
    GeometryConfig(camera_model="orthographic", light_angle_deg=0, length_unit="mm", pixel_size=0.1,
                   light_distance=300)  # the light's distance is the light's, for either camera


@pytest.mark.parametrize("model", CAMERA_CASES)
def test_attrs_round_trip(model):
    geometry = rig(CAMERA_CASES[model])
    attrs = geometry.attrs()
    assert attrs["camera_model"] == model and set(attrs) <= set(GEOMETRY_ATTRS)
    assert RigGeometry.from_attrs(attrs, 7, 11) == geometry


def test_from_attrs_names_every_missing_attr():
    attrs = rig(CAMERA_CASES["perspective"]).attrs()
    del attrs["camera_distance"], attrs["light_angle_deg"]
    with pytest.raises(StageError) as info:
        RigGeometry.from_attrs(attrs, 7, 11, where="align_paths: hull")
    message = str(info.value)
    assert "align_paths: hull: attr 'light_angle_deg' is missing; the rig geometry needs it" in message
    assert "align_paths: hull: attr 'camera_distance' is required for a perspective camera" in message
    with pytest.raises(StageError, match="attr camera_model is 'fisheye'; expected 'perspective' or 'orthographic'"):
        RigGeometry.from_attrs(attrs | {"camera_model": "fisheye", "light_angle_deg": 0.0}, 7, 11)


@pytest.mark.parametrize("model", CAMERA_CASES)
def test_points_on_a_pixel_ray_project_to_the_pixel(model):
    camera = CAMERA_CASES[model]
    rng = np.random.default_rng(0)
    row, col = rng.uniform(-0.5, 6.5, 50), rng.uniform(-0.5, 10.5, 50)
    origins, directions = camera.back_project(row, col)
    np.testing.assert_allclose(np.linalg.norm(directions, axis=1), 1.0, rtol=1e-15)
    points = origins + rng.uniform(20.0, 150.0, (50, 1)) * directions
    got_row, got_col = camera.project(points)
    np.testing.assert_allclose(got_row, row, atol=1e-12)
    np.testing.assert_allclose(got_col, col, atol=1e-12)
    index, inside = camera.pixel_index(got_row, got_col)
    np.testing.assert_array_equal(index[inside], (np.rint(row) * 11 + np.rint(col))[inside])


@pytest.mark.parametrize("model", CAMERA_CASES)
def test_slice_rays_are_the_pixel_rays_seen_from_above(model):
    camera = CAMERA_CASES[model]
    origins, directions = camera.pixel_rays()
    slice_origins, slice_directions = camera.slice_rays(np.arange(11.0))
    np.testing.assert_array_equal(slice_directions[:, 1], 1.0)  # per unit depth
    unit = slice_directions / np.linalg.norm(slice_directions, axis=1, keepdims=True)
    flat = directions[:, :2] / np.linalg.norm(directions[:, :2], axis=1, keepdims=True)
    for r in range(7):
        np.testing.assert_allclose(unit, flat[r * 11:(r + 1) * 11], atol=1e-15)
        np.testing.assert_allclose(slice_origins, origins[r * 11:(r + 1) * 11, :2], atol=1e-15)


def test_pixel_centres_are_integers_and_pixels_span_half_a_pixel_each_side():
    camera = OrthographicCamera(rows=4, cols=5, pixel_size=2.0)
    assert camera.centre_px == (2.0, 1.5)
    np.testing.assert_array_equal(camera.slice_rays([0, 2, 4])[0][:, 0], [-4.0, 0.0, 4.0])
    np.testing.assert_array_equal(camera.rows_at(1.5), [1, 2])  # on the edge: both pixels
    np.testing.assert_array_equal(camera.rows_at(1.2), [1])
    np.testing.assert_array_equal(camera.rows_at(-0.7), [])
    assert camera.outer_edges(1, 3) == (0.5, 3.5)
    assert camera.view_half_width == 5.0 and camera.subtended_angle_deg(1.0) is None


@pytest.mark.parametrize("model", CAMERA_CASES)
def test_the_beam_lights_the_row_that_sees_its_height(model):
    geometry = rig(CAMERA_CASES[model])
    row, _ = geometry.camera.project(np.array([[0.0, 0.0, geometry.beam_height]]))
    assert list(geometry.lit_rows()) == list(geometry.camera.rows_at(float(row[0]))) != []
    sheet = RigGeometry(geometry.camera, light_angle_deg=60.0, light_kind="sheet")
    np.testing.assert_array_equal(sheet.lit_rows(), np.arange(7))


def test_the_perspective_camera_subtends_the_closed_form_angle():
    camera = PerspectiveCamera(focal_length_px=100.0, camera_distance=20.0)  # optics only: no sensor needed
    assert camera.subtended_angle_deg(10.0) == pytest.approx(60.0)
    assert camera.axis_pixel_size == 0.2


def test_an_unknown_light_kind_is_refused_not_taken_for_a_beam():
    import pytest

    from selpath.geometry.rig import OrthographicCamera, RigGeometry
    from selpath.pipeline.errors import StageError

    attrs = RigGeometry(OrthographicCamera(rows=4, cols=4, pixel_size=0.1), 30.0).attrs() | {"light_kind": "Sheet"}
    with pytest.raises(StageError, match="light_kind is 'Sheet'; expected 'beam' or 'sheet'"):
        RigGeometry.from_attrs(attrs, 4, 4)


@pytest.mark.parametrize("model", CAMERA_CASES)
def test_a_row_is_read_as_the_height_where_it_sees_the_axis(model):
    """axis_height inverts projection on the axis: the axis point at that height projects into the row; closed
    forms (cy − r)·D_c/f and (cy − r)·pixel_size."""
    camera = CAMERA_CASES[model]
    rows = np.array([-0.5, 0.0, 2.25, 3.7, 6.5])
    z = camera.axis_height(rows)
    got_row, got_col = camera.project(np.column_stack([np.zeros(5), np.zeros(5), z]))
    np.testing.assert_allclose(got_row, rows, atol=1e-12)
    np.testing.assert_allclose(got_col, camera.centre_px[0], atol=1e-12)
    pitch = 80.0 / 40.0 if model == "perspective" else 0.3
    np.testing.assert_allclose(z, (camera.centre_px[1] - rows) * pitch, rtol=1e-14)
