"""Scene files: every shipped scene loads; a bad one fails naming file:line, field and fix."""

from __future__ import annotations

import pytest

from selpath import workflows
from selpath.devices.sim.scene import load_scene
from selpath.pipeline.errors import ConfigError

SCENES = sorted((workflows.folder() / "scenes").glob("*.yaml"))

GOOD = """\
scene: ok
object:
  shape: {kind: cylinder, radius: 20 mm}
  height: 60 mm
  inclusions:
    - {shape: {kind: polygon, vertices: [[0 mm, 0 mm], [4 mm, 0 mm], [0 mm, 4 mm]]}, sigma: 0.1 /mm}
light: {kind: beam, angle: 45 deg, distance: 300 mm}
camera: {model: perspective, rows: 10, cols: 10, distance: 200 mm, fov: 20 deg}
effects:
  noise: {read_std: 2}
"""


PROCAM_SCENES = {"book-candle-mirrorball", "white-materials", "white-materials-shuffled", "material-atlas", "arm-vein",
                 "disco-glass-marble", "flat-white"}
#: scenes of the pinhole projector–camera pair that films a calibration target (devices.sim.stereo_target)
TARGET_SCENES = {"stereo-target"}


def test_the_shipped_scenes_of_chapter_4_load():
    names = {load_scene(p).scene for p in SCENES if p.stem not in PROCAM_SCENES | TARGET_SCENES}
    assert {"phantom-cylinder", "gelatin-bin", "triangle-prism", "grape-ellipsoid"} <= names
    assert {f"cylinder-in-cylinder-s{s}" for s in (1, 2, 3, 5)} <= names
    sigma_s = {load_scene(p).effects.scattering.sigma_s for p in SCENES if "cylinder-in-cylinder" in p.name}
    assert sigma_s == {1.0, 2.0, 3.0, 5.0}


def test_units_are_converted():
    scene = load_scene(GOOD.replace("radius: 20 mm", "radius: 2 cm"))
    assert scene.object.shape.radius == pytest.approx(20.0)
    assert scene.object.inclusions[0].sigma == pytest.approx(0.1)


@pytest.mark.parametrize(("old", "new", "message"), [
    ("noise: {read_std: 2}", "refraction: {index: 1.33}",
     r"<scene>:9: effects: unknown effect 'refraction'; the tomography simulator computes: scattering, noise"),
    ("[0 mm, 4 mm]]", "[1 mm, 1 mm], [0 mm, 4 mm]]",
     r"<scene>:6: object.inclusions\[0\].shape.vertices: polygon is not convex: .* at vertex 2 \[1.0, 1.0\]"),
    ("radius: 20 mm", "radius: 20",
     r"<scene>:3: object.shape.radius: 20 has no unit; write it as a length, e.g. '20 mm'"),
    ("angle: 45 deg", "angle: 45 degrees",
     r"<scene>:7: light.angle: '45 degrees' is not an angle; write e.g. '45 deg' \(units: deg, degree, rad\)"),
    ("fov: 20 deg", "focal_length: 800 px, fov: 20 deg",
     r"<scene>:8: camera: give exactly one of focal_length \(px\) and fov \(deg\)"),
    ("kind: cylinder, radius: 20 mm", "kind: sphere, radius: 20 mm",
     r"<scene>:3: object.shape: Input tag 'sphere' found using 'kind' does not match"),
    ("noise: {read_std: 2}", "scattering: {sigma_s: 0 /mm}",
     r"<scene>:10: effects.scattering.sigma_s: Input should be greater than 0"),
])
def test_one_mistake_one_exact_error(old, new, message):
    assert old in GOOD
    with pytest.raises(ConfigError, match=message):
        load_scene(GOOD.replace(old, new))


def test_inclusion_outside_the_object_is_refused():
    with pytest.raises(ConfigError, match=r"inclusions\[0\] .* reaches outside the object"):
        load_scene(GOOD.replace("[4 mm, 0 mm]", "[40 mm, 0 mm]"))


def test_the_shipped_target_scene_loads_with_a_projector_whose_rows_span_the_cameras():
    from selpath.devices.sim.stereo_target import load_stereo_target

    scene = load_stereo_target(next(p for p in SCENES if p.stem == "stereo-target"))
    camera, projector = scene.camera, scene.projector
    # the sync pairs projector row (s + ½)·P/C − ½ with camera row s: f and the principal row scale alike
    assert projector.focal_px * camera.height / projector.height == pytest.approx(camera.focal_px, rel=1e-5)
    assert (projector.principal_px[1] + 0.5) * camera.height / projector.height == pytest.approx(
        (camera.height - 1) / 2 + 0.5)
    assert scene.pose.roll == pytest.approx(0.5)


def test_the_shipped_projector_camera_scenes_of_chapter_5_load():
    from selpath.devices.sim.procam_scene import load_procam_scene

    scenes = {p.stem: load_procam_scene(p) for p in SCENES if p.stem in PROCAM_SCENES}
    assert set(scenes) == PROCAM_SCENES
    assert set(scenes["book-candle-mirrorball"].effect_names()) == {
        "subsurface", "diffuse_interreflection", "specular_interreflection"}
    assert set(scenes["disco-glass-marble"].effect_names()) == {"subsurface", "specular_interreflection",
                                                               "refraction"}
    assert scenes["book-candle-mirrorball"].rig.camera_rows == 1200  # the default rig: 1600 × 1200 camera


@pytest.mark.parametrize(("old", "new", "message"), [
    ("shape: {kind: cylinder, radius: 20 mm}\n  height: 60 mm",
     "shape: {kind: ellipsoid, semi_axes: [20 mm, 20 mm, 30 mm]}\n  height: 60 mm",
     r"an ellipsoid has its own height .*: leave out object.height"),
    ("  height: 60 mm\n", "", r"a cylinder is a cross-section: give object.height"),
    ("sigma: 0.1 /mm}", "sigma: 0.1 /mm, z_range: [0 mm, 1 mm]}\n    - {shape: {kind: ellipsoid, "
     "semi_axes: [1 mm, 1 mm, 1 mm]}, sigma: 0.1 /mm, z_range: [0 mm, 1 mm]}",
     r"an ellipsoid inclusion has its own height: leave out z_range"),
    ("sigma: 0.1 /mm}", "sigma: 0.1 /mm}\n    - {shape: {kind: ellipsoid, semi_axes: [1 mm, 1 mm, 1 mm], "
     "centre: [0 mm, 0 mm, 29.5 mm]}, sigma: 0.1 /mm}",
     r"inclusions\[1\] \(ellipsoid\) reaches outside the object"),
    ("sigma: 0.1 /mm}", "sigma: 0.1 /mm}\n    - {shape: {kind: ellipsoid, semi_axes: [1 mm, 1 mm, 1 mm], "
     "centre: [10 mm, 0 mm, 5 mm]}, sigma: -0.2 /mm}", r"negative absorption"),
])
def test_solids_are_checked_in_three_dimensions(old, new, message):
    """An ellipsoid has its own height; an inclusion must lie inside the object and keep σ ≥ 0 in 3-D (a seed poking
    out of the top cap, a negative inclusion above the medium's zero)."""
    assert old in GOOD
    with pytest.raises(ConfigError, match=message):
        load_scene(GOOD.replace(old, new))


def test_a_band_of_rows_keeps_every_pixels_ray_and_the_records_move_with_it():
    """Scene.rows(first, count): pixel (r, c) of the band sees what pixel (first + r, c) of the sensor sees, in the
    true geometry and in the one the records state."""
    import numpy as np

    scene = load_scene(GOOD.replace("effects:", "stated: {principal_point: [4.0 px, 6.5 px]}\neffects:"))
    band = scene.rows(3, 4)
    for geometry in ("geometry", "stated_geometry"):
        full, part = getattr(scene, geometry)().camera, getattr(band, geometry)().camera
        want = full.back_project(np.repeat(np.arange(3.0, 7.0), 10), np.tile(np.arange(10.0), 4))
        np.testing.assert_allclose(part.pixel_rays()[0], want[0], atol=1e-12)
        np.testing.assert_allclose(part.pixel_rays()[1], want[1], atol=1e-12)
    assert band.camera.rows == 4 and band.stated.principal_point == (4.0, 3.5)


#: GOOD with dimensionless lengths: the same numbers, bare or in the unit 1, coefficients per that unit
DIMENSIONLESS = (GOOD.replace("scene: ok\n", 'scene: ok\nlength_unit: "1"\n').replace(" mm", "").replace(" /mm", "")
                 .replace("distance: 300,", "distance: 300 1,"))


def test_a_dimensionless_scene_reads_the_same_numbers_and_records_length_unit_1():
    """#57: ``length_unit: "1"`` as in an import spec: lengths in the user's own unit (bare, or ``1``), coefficients
    per that unit (bare, or ``/1``). Every value equals GOOD's in mm, the geometry records ``1``, and a dumped scene
    validates again to itself."""
    from selpath.devices.sim.scene import Scene

    mm, free = load_scene(GOOD), load_scene(DIMENSIONLESS.replace("sigma: 0.1}", "sigma: 0.1 /1}"))
    assert free.length_unit == "1" and mm.length_unit == "mm"
    assert free.model_dump(exclude={"length_unit"}) == mm.model_dump(exclude={"length_unit"})
    assert free.geometry().length_unit == "1" and free.geometry().attrs()["length_unit"] == "1"
    assert Scene.model_validate_json(free.model_dump_json()) == free
    assert '"300.0 1"' in free.model_dump_json() and '"0.1 /1"' in free.model_dump_json()


@pytest.mark.parametrize(("text", "old", "new", "message"), [
    ("dimensionless", "radius: 20}", "radius: 2 cm}",
     r"<scene>:4: object.shape.radius: '2 cm': this scene's lengths are dimensionless \(length_unit: \"1\"\), so a "
     r"length is a bare number \(or 2 1\), never in a physical unit"),
    ("dimensionless", "sigma: 0.1}", "sigma: 0.1 /mm}", r"<scene>:7: object.inclusions\[0\].sigma: '0.1 /mm': this "),
    ("mm", "radius: 20 mm", "radius: 20 1",
     r"<scene>:3: object.shape.radius: '20 1' is dimensionless; declare length_unit: \"1\" at the scene's top"),
    ("mm", "radius: 20 mm", "radius: 20",
     r"20 has no unit; write it as a length, e.g. '20 mm' \(or declare length_unit: \"1\" at the scene's top"),
    ("dimensionless", 'length_unit: "1"', "length_unit: cm",
     r"^<scene>:2: length_unit: neither 'mm' nor '1' \(dimensionless lengths\) \(got 'cm'\)$"),  # that alone
])
def test_lengths_of_the_other_kind_are_refused_naming_the_scenes_length_unit(text, old, new, message):
    source = DIMENSIONLESS if text == "dimensionless" else GOOD
    assert old in source
    with pytest.raises(ConfigError, match=message):
        load_scene(source.replace(old, new))


def test_an_unquoted_1_is_the_dimensionless_unit():
    """YAML reads ``length_unit: 1`` as a number: it means "1", as quoted."""
    assert load_scene(DIMENSIONLESS.replace('length_unit: "1"', "length_unit: 1")) == load_scene(DIMENSIONLESS)


def test_a_dimensionless_scenes_exact_sinogram_and_truth_are_labelled_1(tmp_path):
    """``simulate_sinogram`` and ``phantom_truth`` of a dimensionless scene: the same numbers as the scene in mm, with
    every coordinate and the store's length_unit in ``1``."""
    import numpy as np

    from selpath.stages.tomography.phantom import phantom_truth, simulate_sinogram

    paths = {"mm": tmp_path / "mm.yaml", "1": tmp_path / "free.yaml"}
    paths["mm"].write_text(GOOD)
    paths["1"].write_text(DIMENSIONLESS)
    made = {}
    for unit, path in paths.items():
        sinogram = simulate_sinogram(scene=str(path), n_theta=12, n_x=16)
        made[unit] = sinogram, phantom_truth(sinogram, scene=str(path), n_pixels=8)
    for mm, free in zip(made["mm"], made["1"], strict=True):
        for name in mm.data_vars:
            np.testing.assert_array_equal(mm[name].values, free[name].values, err_msg=name)
        assert free.attrs.get("length_unit", "1") == "1" and mm.attrs.get("length_unit", "mm") == "mm"
        assert {free[c].attrs.get("units") for c in ("x", "y", "z") if c in free.coords} == {"1"}
        assert {mm[c].attrs.get("units") for c in ("x", "y", "z") if c in mm.coords} == {"mm"}
    assert made["1"][0].attrs["length_unit"] == "1"  # the sinogram records it; the truth carries it in its axes


def test_a_dimensionless_scenes_capture_and_sinogram_are_the_mm_scenes_numbers_in_unit_1():
    """The same cylinder with an absorbing rod in mm and dimensionless: the simulated frames, the rays' X and the
    sinogram are equal to the last bit, and every length the chain records is in ``1``, not ``mm``."""
    import numpy as np

    from selpath.stages.tomography.calibrate import absorption
    from selpath.stages.tomography.hull import silhouettes, visual_hull
    from selpath.stages.tomography.paths import align_paths
    from selpath.stages.tomography.sinogram import bin_sinogram
    from tests.helpers.tomography import capture, cylinder_camera, make_scene

    rod = [{"shape": {"kind": "ellipse", "semi_axes": ["2 mm", "2 mm"], "centre": ["3 mm", "0 mm"]},
            "sigma": "0.2 /mm"}]
    mm = make_scene({"kind": "cylinder", "radius": "10 mm"}, cylinder_camera(None, 64), 60.0, rod)
    free = type(mm).model_validate_json(mm.model_dump_json().replace(" mm", " 1").replace(" /mm", " /1")
                                        .replace('"length_unit":"mm"', '"length_unit":"1"'))
    chains = []
    for scene in (mm, free):
        cap = capture(scene, np.arange(0.0, 360.0, 15.0))
        hull = visual_hull(silhouettes(cap))
        rays = align_paths(absorption(cap), hull)
        chains.append((cap, hull, rays, bin_sinogram(rays, n_theta=12, n_x=16, x_extent=10.0)))
    for a, b in zip(*chains, strict=True):
        for name in a.data_vars:
            np.testing.assert_array_equal(a[name].values, b[name].values, err_msg=name)
        assert a.attrs.get("length_unit") == "mm" and b.attrs.get("length_unit") == "1"
    assert chains[1][3]["x"].attrs.get("units") == "1"
