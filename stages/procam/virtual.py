"""Virtual illumination as stages (§5.4.1, §5.4.2, §5.4.5): the scene relit under a user's patterns, and the
epipolar and non-epipolar images of offset bands, stored by a workflow like any other result.

``relight`` takes patterns from the workflow (projector rows lit, or a list of values per row, or rows × columns)
and from an image file (PNG, TIFF or .npy); a plane-to-ray transport relights under row patterns (it holds no
projector column), a full transport under any 2-D pattern. ``epipolar_images`` synthesises, for each band
|offset| ≤ b, the light from those planes and from every other. The arithmetic is
:mod:`selpath.stages.procam.relight`'s; ``relit_figure`` draws a ``relit_images`` store.
"""

from __future__ import annotations

import os
from typing import Annotated, Literal

import numpy as np
import pydantic
import xarray as xr

from selpath.pipeline.constraints import Count, Fraction, Index, StorePath
from selpath.pipeline.errors import Problem, StageError
from selpath.pipeline.kinds import PX_UNITS, CubeKind, Variable
from selpath.pipeline.registry import stage
from selpath.stages._common import file_identity, require_variables
from selpath.stages._figures import FIGURE, as_figure
from selpath.stages.procam.figures import CHECKERBOARD_SIZE, censored_note, censored_of, draw_relit
from selpath.stages.procam.relight import epipolar_image, non_epipolar_image, pattern_rows, relight_pattern

_IMAGE = ("row", "col")
_CENSORED = Variable(_IMAGE, False, units=None,
                     long_name="light seen only clipped: the images are lower bounds there")
RELIT_IMAGES = CubeKind(
    name="relit_images",
    description="the scene relit from its transport under named virtual projector patterns (§5.4.1–5.4.2)",
    variables={"image": Variable(("pattern", *_IMAGE), units="counts",
                                 long_name="image relit under a virtual projector pattern"),
               "lit_share": Variable(("pattern",), units="1",
                                     long_name="share of the projector the pattern lights (1 = white)"),
               "censored": _CENSORED},
    attrs={"patterns": "pattern name → how it was given (rows, values or file) and its shape"},
)
EPIPOLAR_IMAGES = CubeKind(
    name="epipolar_images",
    description="light from the epipolar planes |offset| ≤ band and from every other plane (Eq. 35–36, §5.4.5)",
    variables={"epipolar": Variable(("band", *_IMAGE), units="counts",
                                    long_name="epipolar image: light from the planes |offset| ≤ band"),
               "non_epipolar": Variable(("band", *_IMAGE), units="counts",
                                        long_name="non-epipolar image: light from the planes |offset| > band"),
               "censored": _CENSORED},
    coord_units={"band": PX_UNITS},
)


class Pattern(pydantic.BaseModel):
    """One virtual pattern: exactly one of ``rows`` (the rows lit, whole rows), ``band`` ([first, last] rows lit,
    both included) or ``values`` (a value in [0, 1] per row, or rows × columns); on the projector's rows unless
    the stage's ``space`` is ``camera``."""

    model_config = pydantic.ConfigDict(extra="forbid", frozen=True)
    rows: tuple[Index, ...] | None = None
    band: tuple[Index, Index] | None = None
    values: tuple[Fraction, ...] | tuple[tuple[Fraction, ...], ...] | None = None

    @pydantic.model_validator(mode="after")
    def _one(self) -> Pattern:
        if sum(x is not None for x in (self.rows, self.band, self.values)) != 1:
            raise ValueError("give exactly one of rows (the rows lit), band ([first, last] rows lit) or values (a "
                             "value in [0, 1] per row, or a list of rows of values)")
        if self.band is not None and self.band[1] < self.band[0]:
            raise ValueError(f"band {list(self.band)} ends before it starts: give [first, last]")
        if self.values is not None and len(self.values) == 0:
            raise ValueError("values is empty")
        if self.values is not None and isinstance(self.values[0], tuple) and len({len(r) for r in self.values}) > 1:
            raise ValueError("values' rows have different lengths")
        return self

    def array(self, rows: int) -> np.ndarray:
        """The pattern over ``rows`` rows (1-D), or rows × columns."""
        if self.values is not None:
            return np.asarray(self.values, dtype=float)
        lit = list(self.rows) if self.rows is not None else list(range(self.band[0], self.band[1] + 1))
        beyond = [r for r in lit if r >= rows]
        if beyond:
            raise ValueError(f"rows {beyond[:5]} are beyond the {rows} rows of the pattern's space")
        out = np.zeros(rows)
        out[lit] = 1.0
        return out

    def what(self) -> str:
        if self.rows is not None:
            return f"rows {list(self.rows)[:8]}{' …' if len(self.rows) > 8 else ''} lit"
        if self.band is not None:
            return f"rows {self.band[0]}–{self.band[1]} lit"
        return f"values, shape {list(np.shape(self.values))}"


Patterns = dict[Annotated[str, pydantic.Field(pattern=r"^[A-Za-z0-9_.-]+$")], Pattern]


def read_pattern(path: str) -> np.ndarray:
    """A pattern image in [0, 1]: a .npy of floats in [0, 1], or a gray PNG/TIFF scaled by its integer type's
    largest value (uint8: 255, uint16: 65 535; a float image as is)."""
    if path.endswith(".npy"):
        image = np.load(path, allow_pickle=False)
    else:
        import imageio.v3 as iio

        image = iio.imread(path)
    if image.ndim != 2:
        raise StageError(Problem(f"the pattern image {path} has shape {image.shape}; a pattern is one gray "
                                 "channel", where="pattern_file", fix="save it as a gray (single-channel) image"))
    if np.issubdtype(image.dtype, np.integer):
        image = image / float(np.iinfo(image.dtype).max)
    image = np.asarray(image, dtype=float)
    if not np.all(np.isfinite(image)) or image.min() < 0 or image.max() > 1:
        raise StageError(Problem(f"the pattern image {path} has values outside [0, 1] or not finite",
                                 where="pattern_file", fix="scale it to [0, 1] (1 = lit for a whole line time)"))
    return image


def _transport(transport: xr.Dataset, stage_name: str) -> xr.DataArray:
    require_variables(transport, ("transport",), stage_name)
    t = transport["transport"]
    if not ({"offset"} <= set(t.dims) or {"du", "dv"} <= set(t.dims)):
        raise StageError(Problem(f"{stage_name}: the transport has dims {t.dims}; expected (offset, row, col) or "
                                 "(du, dv, row, col)", fix="wire in demux_plane_to_ray's or demux_full's output"))
    return t


def _pattern_rows(transport: xr.Dataset, projector_rows: int | None, space: str) -> int:
    try:
        return pattern_rows(transport, space, projector_rows)
    except ValueError as exc:
        raise StageError(Problem(str(exc), where="projector_rows")) from None


def _relit(transport: xr.Dataset, pattern: np.ndarray, name: str, projector_rows: int | None) -> xr.DataArray:
    try:
        return relight_pattern(transport, pattern, projector_rows=projector_rows)
    except ValueError as exc:
        raise StageError(Problem(f"pattern {name!r}: {exc}", where=name)) from None


def _identity(settings) -> dict:
    return file_identity(settings.pattern_file) if settings.pattern_file else {}


def _precheck(settings) -> list[str]:
    problems = []
    if settings.pattern_file and not os.path.isfile(settings.pattern_file):
        problems.append(f"pattern_file {settings.pattern_file!r} is not a file")
    if not settings.patterns and not settings.pattern_file:
        problems.append("no pattern: give patterns (name → rows or values) or a pattern_file")
    return problems


@stage("relight", kind=RELIT_IMAGES, identity=_identity, precheck=_precheck)
def relight_images(transport: xr.Dataset, /, *, patterns: Patterns | None = None, pattern_file: StorePath = "",
                   space: Literal["projector", "camera"] = "projector",
                   projector_rows: Count | None = None) -> xr.Dataset:
    """The scene relit from its transport under named virtual patterns (§5.4.1 with plane-to-ray transport, §5.4.2
    with full transport), lazily: I(s, t) = Σ_o T(o, s, t)·b(s + o), or Σ T(du, dv, s, t)·P̄(t + dv, u₀ + du).

    Parameters
    ----------
    transport : xr.Dataset
        A ``plane_to_ray_transport`` (``demux_plane_to_ray``: row patterns only, as it sums over projector columns)
        or ``full_transport`` (``demux_full``: any 2-D pattern; a row pattern lights every column) store; attr
        ``projector_shape`` [rows, cols] where the patterns are on the projector's rows.
    patterns : dict or None
        name → ``{rows: [v, …]}`` (the rows lit, whole rows), ``{band: [first, last]}`` (those rows and every one
        between lit), ``{values: [b_0, …]}`` (a value in [0, 1] per row, 1 = lit for a whole line time) or
        ``{values: [[…], …]}`` (rows × projector columns).
    pattern_file : str
        One more pattern, named by the file's stem: a gray PNG/TIFF (scaled by its integer type's largest value)
        or a .npy of floats in [0, 1], rows × projector columns (or one column). Empty: none.
    space : str
        ``projector``: patterns are on the projector's rows (``projector_rows``, else the transport's
        ``projector_shape``), averaged onto the camera-rectified rows each camera row covers; ``camera``: on the
        transport's camera-rectified rows, as is.
    projector_rows : int or None
        The projector's rows where the transport does not record them.

    Returns
    -------
    xr.Dataset
        A ``relit_images`` cube: the relit ``image`` [counts] over (pattern, row, col), each pattern's ``lit_share`` and
        ``censored`` where clipped light was used, lazily.

    References
    ----------
    Thesis §5.4.2 Relighting.
    """
    _transport(transport, "relight")
    rows = _pattern_rows(transport, projector_rows, space)
    given: dict[str, tuple[np.ndarray, str]] = {}
    for name, spec in (patterns or {}).items():
        try:
            given[name] = (spec.array(rows), spec.what())
        except ValueError as exc:
            raise StageError(Problem(f"pattern {name!r}: {exc}", where=name)) from None
    if pattern_file:
        image = read_pattern(pattern_file)
        given[os.path.splitext(os.path.basename(pattern_file))[0]] = (
            image[:, 0] if image.shape[1] == 1 else image, f"file {os.path.basename(pattern_file)}")
    if not given:
        raise StageError(Problem("no pattern to relight under", fix="give patterns or a pattern_file"))
    images = [_relit(transport, array, name, None if space == "camera" else rows) for name, (array, _) in given.items()]
    censored = {"censored": transport["censored"]} if "censored" in transport.data_vars else {}
    return RELIT_IMAGES.label(xr.Dataset(
        {"image": xr.concat([i.drop_attrs() for i in images], dim="pattern"),
         "lit_share": ("pattern", [float(np.mean(a)) for a, _ in given.values()]), **censored},
        coords={"pattern": ("pattern", list(given), {"long_name": "virtual pattern"})},
        attrs={"patterns": {name: f"{what}, {space} rows" for name, (_, what) in given.items()}, "space": space,
               **{k: transport.attrs[k] for k in ("projector_shape", "scene") if k in transport.attrs}}))


@stage("epipolar_images", kind=EPIPOLAR_IMAGES)
def epipolar_images(transport: xr.Dataset, /, *,
                    bands: Annotated[tuple[Index, ...], pydantic.Field(min_length=1)] = (0,)) -> xr.Dataset:
    """Epipolar and non-epipolar images (Eq. 35–36) for offset bands: the light from the planes |offset| ≤ b
    (b = 0: the pixel's own, the sharpened epipolar image of §5.4.5) and from every other plane; the two sum to
    the floodlit image.

    Parameters
    ----------
    transport : xr.Dataset
        A ``plane_to_ray_transport`` or ``full_transport`` store (a full one is summed over du first).
    bands : list of int
        Half-widths b of the bands [camera rows], each ≥ 0.

    Returns
    -------
    xr.Dataset
        An ``epipolar_images`` cube: ``epipolar`` and ``non_epipolar`` [counts] over (band, row, col), summing to the
        floodlit image, and ``censored`` where the transport was seen only clipped.

    References
    ----------
    Thesis §5.4.5 Sharpening epipolar imaging.
    """
    t = _transport(transport, "epipolar_images")
    if "du" in t.dims:
        t = t.sum("du").rename(dv="offset")
    band = ("band", np.asarray(bands, dtype=int), {"units": "px", "long_name": "half-width b of |offset| ≤ b, rows"})
    censored = {"censored": transport["censored"]} if "censored" in transport.data_vars else {}
    return EPIPOLAR_IMAGES.label(xr.Dataset(
        {"epipolar": xr.concat([epipolar_image(t, b).drop_attrs() for b in bands], dim="band"),
         "non_epipolar": xr.concat([non_epipolar_image(t, b).drop_attrs() for b in bands], dim="band"),
         **censored}, coords={"band": band},
        attrs={k: transport.attrs[k] for k in ("scene",) if k in transport.attrs}))


@stage("relit_figure", kind=FIGURE)
def relit_figure(relit: xr.Dataset, /) -> xr.Dataset:
    """The images of a ``relit_images`` store (``relight``) side by side on one colour scale in counts.

    Parameters
    ----------
    relit : xr.Dataset
        A ``relit_images`` store: ``image`` over (pattern, row, col).

    Returns
    -------
    xr.Dataset
        A ``figure``: the RGBA ``image`` (y, x, rgba) and its ``caption`` attr; a workflow output also saves it as
        ``<store>.png``.

    References
    ----------
    Thesis §5.4.2 Relighting.
    """
    require_variables(relit, ("image",), "relit_figure")
    names = [str(n) for n in relit["pattern"].values]
    described = relit.attrs.get("patterns", {})
    titles = [f"({chr(97 + i)}) {name}" for i, name in enumerate(names)]
    caption = f"""The scene relit from its light transport under virtual projector patterns of the workflow's own, as
        the thesis's Fig. 40 relights it under lines (§5.4.1; Fig. 41 and §5.4.2 for 2-D patterns from full transport):
        {"; ".join(f"({chr(97 + i)}) {n}: {described.get(n, '')}" for i, n in enumerate(names))}; all on one
        colour scale in counts (0 to the largest of the images' 99.5th percentiles), axes in camera pixels.
        {censored_note(relit)}"""
    censored = censored_of(relit)

    def render(*arrays):
        images, mask = arrays[:len(names)], arrays[len(names):]
        return draw_relit([np.asarray(a) for a in images], titles, CHECKERBOARD_SIZE,
                          censored=np.asarray(mask[0]) if mask else None, scale_by_last=False)

    return as_figure(render, *(relit["image"].isel(pattern=i).data for i in range(len(names))),
                     *([censored] if censored is not None else []), caption=caption, size=CHECKERBOARD_SIZE)
