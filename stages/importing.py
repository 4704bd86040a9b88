"""Captures made elsewhere into selpath stores: the ``import_capture`` stage and ``selpath import`` (#24).

A lab brings image stacks (a folder of TIFF or PNG frames, a multi-page TIFF, ``.npy``/``.npz``, an HDF5 dataset)
and says in a small YAML *import spec* what they are: the cube kind, where each variable's frames lie, and the
geometry or timing the stages read, every field with its unit (:class:`TomographyImport`,
:class:`PlaneToRayImport`; ``selpath schema`` shows neither, ``docs/format.md`` lists both). Frames are read
lazily (one dask task per frame; ``.npy`` memory-mapped, HDF5 and image files opened per frame), so a capture
larger than memory imports frame by frame; an ``.npz`` member is read whole (the format cannot be memory-mapped).
The spec's relative paths resolve against the spec's folder.

Pixel centres: selpath puts pixel j's centre at coordinate j (its area is [j − ½, j + ½]). A renderer or a
calibration that puts it at j + ½ (pixel j spans [j, j + 1]: OpenGL, Mitsuba, many ray tracers) says
``pixel_centres: half`` and its ``principal_point_px`` is converted by −½ on import; passing such a principal
point verbatim shifts every ray by half a pixel (in one test it doubled the reconstruction's RMSE).
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Annotated, Any, Literal

import dask.array as da
import numpy as np
import pydantic
import xarray as xr
from pydantic import BaseModel, ConfigDict, Field

from selpath.pipeline.constraints import StorePath
from selpath.pipeline.errors import Problem, SelpathError, StageError
from selpath.pipeline.kinds import LENGTH_UNITS
from selpath.pipeline.provenance import hash_file
from selpath.pipeline.registry import resolve_kind, stage
from selpath.pipeline.yaml_source import load_yaml_model
from selpath.stages.frame_files import check_values, frame_file_list, read_frames, split_source


class _Spec(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class AngleRange(_Spec):
    """Stage angles φ = start + i · step, i = 0 … count − 1, degree."""

    start_deg: float = Field(0.0, description="first stage angle, degree")
    step_deg: float = Field(description="angle between consecutive frames, degree (negative: turning back)")
    count: int = Field(gt=0, description="number of angles (frames per variable)")

    def values(self) -> np.ndarray:
        return self.start_deg + self.step_deg * np.arange(self.count)


class TomographyFrames(_Spec):
    """Where each variable's frames lie: ``path`` or ``path:key`` (an ``.npz`` member or an HDF5 dataset)."""

    target: str = Field(description="frames of the object with the inclusion, (angle, row, col), raw counts")
    reference: str = Field(description="frames of the same object without it (§4.4.2), (angle, row, col)")
    backlit: str | None = Field(None, description="silhouettes against a lit plane, (angle, row, col)")
    dark: str | None = Field(None, description="one frame with all lights off, (row, col), or a stack to average")


class TomographyImport(_Spec):
    """A tomography capture (``tomography_capture``): frames plus the rig geometry of docs/format.md."""

    kind: Literal["tomography_capture"]
    frames: TomographyFrames
    angles_deg: list[float] | AngleRange = Field(description="stage angle φ of each frame, degree")
    camera_model: Literal["perspective", "orthographic"]
    light_angle_deg: float = Field(description="θ_l, angle between the beam and the camera axis, degree")
    length_unit: str = Field(description=f"unit of every length below: one of {sorted(LENGTH_UNITS)}")
    pixel_centres: Literal["integer", "half"] = Field(
        "integer", description="'integer': pixel j's centre at j (selpath's); 'half': at j + 0.5 (converted)")
    focal_length_px: float | None = Field(None, gt=0, description="perspective: focal length, px")
    principal_point_px: tuple[float, float] | None = Field(
        None, description="perspective: [cx, cy] (column, row), px, in the convention of pixel_centres")
    camera_distance: float | None = Field(None, gt=0, description="perspective: D_c, camera to axis, length unit")
    light_distance: float | None = Field(None, gt=0, description="D_l, light source to axis, length unit "
                                         "(optional: it only places the beam's origin on its line)")
    pixel_size: float | None = Field(None, gt=0, description="orthographic: object-space size of a pixel")
    light_kind: Literal["beam", "sheet"] = Field("beam", description="a narrow beam, or a vertical light sheet")
    beam_height: float = Field(0.0, description="height of the beam above the stage's origin, length unit")
    saturation_counts: float | None = Field(None, description="raw counts at and above which the sensor clips")

    @pydantic.model_validator(mode="after")
    def _camera(self) -> TomographyImport:
        needs = {"perspective": ("focal_length_px", "camera_distance"),
                 "orthographic": ("pixel_size",)}[self.camera_model]
        missing = [name for name in needs if getattr(self, name) is None]
        if missing:
            raise ValueError(f"a {self.camera_model} camera needs {', '.join(missing)}")
        if self.length_unit not in LENGTH_UNITS:
            raise ValueError(f"length_unit {self.length_unit!r} is not one of {sorted(LENGTH_UNITS)}")
        return self


class PlaneToRayFrames(_Spec):
    image: str = Field(description="the stack: (delay, exposure, row, col), or (frame, row, col) in `order`")


class PlaneToRayImport(_Spec):
    """A projector–camera delay–exposure sweep (``plane_to_ray_capture``), §5.2.3."""

    kind: Literal["plane_to_ray_capture"]
    frames: PlaneToRayFrames
    delays_us: list[float] = Field(min_length=1, description="sync delays t_d of the sweep, µs")
    exposures_us: list[float] = Field(min_length=1, description="exposures t_e of the sweep, µs")
    order: Literal["delay_major", "exposure_major"] = Field(
        "delay_major", description="a 3-D stack's frame order: delay_major = every exposure of the first delay first")
    scan_speed_px_per_us: float = Field(gt=0, description="projector scan speed v_p, camera rows per µs")
    line_time_us: float = Field(gt=0, description="projector line time t_p, µs")
    saturation_counts: float = Field(description="raw counts at and above which a pixel is clipped")
    dark_level_counts: float = Field(description="raw counts of an unlit pixel (black level)")


class FullTransportImport(_Spec):
    """A projector–camera line sweep (``full_transport_capture``), §5.3: a vertical line at each l_p × every
    (delay, exposure)."""

    kind: Literal["full_transport_capture"]
    frames: PlaneToRayFrames
    delays_us: list[float] = Field(min_length=1, description="sync delays t_d of the sweep, µs")
    exposures_us: list[float] = Field(min_length=1, description="exposures t_e of the sweep, µs")
    lines_px: list[float] = Field(min_length=1, description="line centres l_p, projector columns (pixel centres at "
                                  "whole numbers)")
    order: tuple[Literal["delay", "exposure", "line"], ...] = Field(
        ("delay", "exposure", "line"), description="a 3-D stack's frame order, slowest first: [delay, exposure, "
        "line] = every line of the first (delay, exposure) first")
    line_width_px: float = Field(gt=0, description="width l_w of the projected line, projector columns")
    scan_speed_px_per_us: float = Field(gt=0, description="projector scan speed v_p, camera rows per µs")
    line_time_us: float = Field(gt=0, description="projector line time t_p, µs")
    saturation_counts: float = Field(description="raw counts at and above which a pixel is clipped")
    dark_level_counts: float = Field(description="raw counts of an unlit pixel (black level)")

    @pydantic.field_validator("order")
    @classmethod
    def _permutation(cls, order):
        if sorted(order) != ["delay", "exposure", "line"]:
            raise ValueError(f"order {list(order)} must name delay, exposure and line once each")
        return order


ImportSpec = Annotated[TomographyImport | PlaneToRayImport | FullTransportImport, Field(discriminator="kind")]


class _SpecFile(pydantic.RootModel):
    root: ImportSpec


def read_spec(path: str | os.PathLike) -> TomographyImport | PlaneToRayImport | FullTransportImport:
    """The import spec at ``path``, validated (one ConfigError lists every problem with its line)."""
    return load_yaml_model(path, _SpecFile, what="import spec").root


# -- building the capture ------------------------------------------------------------------------------------


def _frames(spec, base: Path) -> dict[str, da.Array]:
    fields = spec.frames.model_dump(exclude_none=True)
    return {name: read_frames(source, base, field=f"frames.{name}") for name, source in fields.items()}


def _tomography(spec: TomographyImport, base: Path) -> xr.Dataset:
    frames = _frames(spec, base)
    angles = spec.angles_deg.values() if isinstance(spec.angles_deg, AngleRange) else np.asarray(spec.angles_deg)
    problems = []
    stacks = {name: a for name, a in frames.items() if name != "dark"}
    for name, array in stacks.items():
        if array.ndim == 4 and array.shape[-1] in (3, 4):
            problems.append(f"frames.{name} are colour images {array.shape}; import one channel (raw counts)")
        elif array.ndim != 3:
            problems.append(f"frames.{name} is {array.ndim}-D {array.shape}; expected (angle, row, col)")
        elif array.shape[0] != angles.size:
            problems.append(f"frames.{name} has {array.shape[0]} frames for {angles.size} angles")
    shapes = {a.shape[1:] for a in stacks.values() if a.ndim == 3}
    if len(shapes) > 1:
        problems.append(f"the stacks' frames differ in size: {sorted(shapes)}")
    dark = frames.get("dark")
    if dark is not None and dark.ndim == 3:
        dark = dark.mean(axis=0)  # a stack of dark frames: their mean
    if dark is not None and shapes and dark.shape != next(iter(shapes)):
        problems.append(f"frames.dark is {dark.shape}; the stacks' frames are {next(iter(shapes))}")
    if problems:
        raise StageError([Problem(p, where="import spec") for p in problems])
    attrs: dict[str, Any] = spec.model_dump(exclude={"kind", "frames", "angles_deg", "pixel_centres"},
                                            exclude_none=True)
    if "principal_point_px" in attrs:
        shift = 0.5 if spec.pixel_centres == "half" else 0.0
        attrs["principal_point_px"] = [float(v) - shift for v in spec.principal_point_px]
    elif spec.camera_model == "perspective":  # the sensor's centre, in selpath's convention
        rows, cols = next(iter(shapes))
        attrs["principal_point_px"] = [(cols - 1) / 2.0, (rows - 1) / 2.0]
    variables = {name: (("angle", "row", "col"), array) for name, array in stacks.items()}
    if dark is not None:
        variables["dark"] = (("row", "col"), dark)
    for name, (_, array) in variables.items():
        check_values(array, f"frames.{name}")
    return xr.Dataset(variables, coords={"angle": ("angle", angles.astype(float),
                                                  {"units": "degree", "long_name": "stage angle φ"})},
                      attrs={"selpath_kind": spec.kind, **attrs})


def _plane_to_ray(spec: PlaneToRayImport, base: Path) -> xr.Dataset:
    image = _frames(spec, base)["image"]
    n_d, n_e = len(spec.delays_us), len(spec.exposures_us)
    if image.ndim == 3:
        if image.shape[0] != n_d * n_e:
            raise StageError(Problem(f"frames.image has {image.shape[0]} frames for {n_d} delays × {n_e} exposures",
                                     where="import spec"))
        image = (image.reshape(n_d, n_e, *image.shape[1:]) if spec.order == "delay_major"
                 else image.reshape(n_e, n_d, *image.shape[1:]).transpose(1, 0, 2, 3))
    elif image.ndim != 4 or image.shape[:2] != (n_d, n_e):
        raise StageError(Problem(f"frames.image is {image.shape}; expected ({n_d}, {n_e}, row, col) or "
                                 f"({n_d * n_e}, row, col)", where="import spec"))
    check_values(image, "frames.image")
    attrs = spec.model_dump(exclude={"kind", "frames", "delays_us", "exposures_us", "order"})
    return xr.Dataset({"image": (("delay", "exposure", "row", "col"), image)},
                      coords={"delay": ("delay", np.asarray(spec.delays_us, float),
                                        {"units": "us", "long_name": "sync delay t_d"}),
                              "exposure": ("exposure", np.asarray(spec.exposures_us, float),
                                           {"units": "us", "long_name": "exposure t_e"})},
                      attrs={"selpath_kind": spec.kind, **attrs})


def _full_transport(spec: FullTransportImport, base: Path) -> xr.Dataset:
    image = _frames(spec, base)["image"]
    sizes = {"delay": len(spec.delays_us), "exposure": len(spec.exposures_us), "line": len(spec.lines_px)}
    want = (sizes["delay"], sizes["exposure"], sizes["line"])
    count = int(np.prod(want))
    if image.ndim == 3:
        if image.shape[0] != count:
            raise StageError(Problem(f"frames.image has {image.shape[0]} frames for {sizes['delay']} delays × "
                                     f"{sizes['exposure']} exposures × {sizes['line']} lines", where="import spec"))
        stacked = image.reshape(*(sizes[d] for d in spec.order), *image.shape[1:])
        image = stacked.transpose(*(spec.order.index(d) for d in ("delay", "exposure", "line")), 3, 4)
    elif image.ndim != 5 or image.shape[:3] != want:
        raise StageError(Problem(f"frames.image is {image.shape}; expected ({', '.join(map(str, want))}, row, col) "
                                 f"or ({count}, row, col)", where="import spec"))
    check_values(image, "frames.image")
    attrs = spec.model_dump(exclude={"kind", "frames", "delays_us", "exposures_us", "lines_px", "order"})
    return xr.Dataset({"image": (("delay", "exposure", "line", "row", "col"), image)},
                      coords={"delay": ("delay", np.asarray(spec.delays_us, float),
                                        {"units": "us", "long_name": "sync delay t_d"}),
                              "exposure": ("exposure", np.asarray(spec.exposures_us, float),
                                           {"units": "us", "long_name": "exposure t_e"}),
                              "line": ("line", np.asarray(spec.lines_px, float),
                                       {"units": "px", "long_name": "line centre l_p"})},
                      attrs={"selpath_kind": spec.kind, **attrs})


def spec_identity(settings) -> dict[str, str]:
    """The spec's text and every byte of the frames it names (SHA-256; never paths or modification times)."""
    path = Path(settings.spec).resolve()  # as import_capture reads it: a symlinked spec's frames lie by its target
    digest = hashlib.sha256(path.read_bytes() if path.is_file() else b"")
    try:
        spec = read_spec(path)
    except Exception:  # noqa: BLE001 - the precheck reports it
        return {"spec_sha256": digest.hexdigest()}
    for source in spec.frames.model_dump(exclude_none=True).values():
        target, _ = split_source(source, path.parent)
        for file in [target] if target.is_file() else frame_file_list(target):
            hash_file(digest, file, file.name)
    return {"spec_and_frames_sha256": digest.hexdigest()}


def _precheck(settings) -> list[str]:
    try:
        import_capture(spec=settings.spec)
    except SelpathError as exc:  # a bad spec (ConfigError) or frames that do not fit it (StageError)
        return [str(p) for p in getattr(exc, "problems", [exc])]
    return []


@stage("import_capture", precheck=_precheck, identity=spec_identity)
def import_capture(*, spec: StorePath) -> xr.Dataset:
    """A capture made elsewhere, as the cube its import spec names (lazily, one task per frame).

    Parameters
    ----------
    spec : str
        Path of the import spec (YAML): ``kind`` (``tomography_capture``, ``plane_to_ray_capture`` or
        ``full_transport_capture``), ``frames``
        (where each variable's frames lie: a folder or glob of TIFF/PNG files, a multi-page TIFF, ``.npy``,
        ``file.npz:member`` or ``file.h5:/dataset``, relative to the spec's folder) and the geometry or timing
        the stages read, with units (docs/format.md, "Importing captures").

    Returns
    -------
    xr.Dataset
        The capture as the kind its spec names (``tomography_capture``, ``plane_to_ray_capture`` or
        ``full_transport_capture``), lazily one task per frame, with the spec's geometry or timing in its attrs.
    """
    parsed = read_spec(spec)
    base = Path(spec).resolve().parent
    build = (_tomography if isinstance(parsed, TomographyImport) else
             _plane_to_ray if isinstance(parsed, PlaneToRayImport) else _full_transport)
    return resolve_kind(parsed.kind).label(build(parsed, base))  # the kind's units and long names (counts)
