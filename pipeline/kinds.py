"""What a cube kind is (DESIGN §2), and how a dataset is checked against one.

A kind fixes, for each variable, its dims in order (an optional trailing ``channel`` dim is always allowed), its
``units`` and ``long_name`` (:class:`Variable`), which dims need a coordinate with a ``units`` attr (and which units),
which attrs the store must carry, which dims may stack cubes (``slice``) and whether a variable is an image to save
beside the store (:class:`CubeKind`). The engine knows what a kind *is*, never which kinds exist: each is declared
beside the stage that makes it (``@stage("bin_sinogram", kind=SINOGRAM)``) and registered with it through the
``selpath.stages`` entry points (:class:`~selpath.pipeline.registry.StageRegistry`), so a plugin's kinds are stored,
checked and opened like the built-in ones. With them: the store format's version (:data:`FORMAT_VERSION`) and the
units every kind draws from.
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field

import xarray as xr

from selpath.pipeline.errors import Problem, SelpathError

#: Schema version written into every store as ``selpath_format``. Bump it (and add a migration in
#: :data:`selpath.pipeline.migrations.MIGRATIONS`) whenever a kind's dims, units or required attrs change.
#: Format 2 (2026-11): every chunk carries a crc32c checksum and is written even when it holds only the fill
#: value, and a manifest in ``_selpath`` records completion and units. Its cubes are those of format 1.
#: Format 3 (2026-12): the hull is indexed by ``slice`` (a coordinate: the camera row), as sinograms and
#: reconstructions are; formats 1–2 named that dim ``row``, without a coordinate.
#: Format 4 (2026-12): every variable a kind declares has the ``units`` and ``long_name`` the kind fixes
#: (:class:`Variable`), written by :meth:`CubeKind.label` and checked on open.
#: Format 5 (2026-12): the solvers' and calibrations' extra variables (iterations, convergence, objective,
#: residuals, masks) are declared too, optional, with their units and long names; format 4 left them bare.
#: Format 6 (2026-11): transports keep clipped frames as lower bounds and flag pixels whose light was seen only
#: clipped (``censored``, ``censored_offsets``, ``frames_clipped``, ``clip_ratio``); formats ≤ 5 masked clipped
#: frames, so their ``converged`` says nothing of clipped light (a note says so on open).
FORMAT_VERSION = 6


PIXEL_DIMS = ("row", "col")
CHANNEL_DIM = "channel"
#: length units of a tomography store; "1": dimensionless (lengths in a unit the user keeps consistent, e.g. a
#: renderer's scene units with the object's radius 1; σ is then per that unit, written "1")
LENGTH_UNITS = frozenset({"m", "cm", "mm", "um", "px", "1"})
ANGLE_UNITS = frozenset({"degree"})
TIME_UNITS = frozenset({"us"})
PX_UNITS = frozenset({"px"})
#: ``Variable(dims, **SENSOR_COUNTS)``: frames in raw sensor counts
SENSOR_COUNTS = {"units": "counts", "long_name": "sensor counts"}
#: ``Variable(dims, **FLAGS)``: CF flag bits saying why a pixel is invalid (0: valid; attrs ``flag_masks`` and
#: ``flag_meanings``, read by :func:`selpath.pipeline.quality.valid_shares`)
FLAGS = {"units": None, "long_name": "why a pixel is invalid (CF flags; 0: valid)"}

_NAME = re.compile(r"^[a-z][a-z0-9_]*$")


def in_length(template: str, length: str) -> str:
    """``template`` with ``{length}`` replaced by ``length``; a dimensionless length ("1") gives σ the unit "1",
    not "1/1"."""
    units = template.replace("{length}", str(length))
    return "1" if units == "1/1" else units


@dataclass(frozen=True)
class Variable:
    """One variable of a kind: dims in order, whether required, and its CF metadata.

    ``units``: the ``units`` attr every store of the kind gives it (``{length}`` is the store's length unit:
    its ``length_unit`` attr, else its x/y coordinates'); ``None``: none (flags, masks, images); ``""``:
    not fixed by the kind. ``long_name`` is written with it.
    """

    dims: tuple[str, ...]
    required: bool = True
    description: str = ""
    units: str | None = ""
    long_name: str = ""


@dataclass(frozen=True)
class CubeKind:
    """The schema of one kind of capture cube, and what a store of it is for.

    >>> import numpy as np, xarray as xr
    >>> MAP = CubeKind("height_map", {"height": Variable(("y", "x"), units="mm", long_name="surface height")},
    ...                coord_units={"y": LENGTH_UNITS, "x": LENGTH_UNITS}, description="a height per point")
    >>> ds = MAP.label(xr.Dataset({"height": (("y", "x"), np.zeros((2, 2)))}))
    >>> ds.attrs["selpath_kind"], ds["height"].attrs
    ('height_map', {'units': 'mm', 'long_name': 'surface height'})
    >>> [p.message for p in MAP.check(ds)]  # doctest: +NORMALIZE_WHITESPACE
    ['dim y has no coordinate; it needs one with attrs units in [1, cm, m, mm, px, um]',
     'dim x has no coordinate; it needs one with attrs units in [1, cm, m, mm, px, um]']
    """

    #: lower_snake_case; stored in every store of the kind as its ``selpath_kind`` attr
    name: str
    variables: Mapping[str, Variable]
    #: dims whose coordinate must exist and carry one of these units
    coord_units: Mapping[str, frozenset[str]] = field(default_factory=dict)
    #: attrs every store of this kind carries, with a description for errors and docs
    attrs: Mapping[str, str] = field(default_factory=dict)
    #: extra checks on attr values; each returns problems
    attr_checks: tuple[Callable[[Mapping], list[str]], ...] = ()
    #: checks of a store's data against what its attrs state (a stated geometry its frames contradict), run by
    #: ``selpath import`` once the frames are in: each takes the opened store and returns advice, one paragraph
    #: each (what disagrees, by how much, the likely cause, the fix). They read data: workflows do not run them
    data_checks: tuple[Callable[[xr.Dataset], list[str]], ...] = ()
    description: str = ""
    #: dims a cube may add before its variables' own, to stack cubes (sinograms and reconstructions: ``slice``)
    batch_dims: tuple[str, ...] = ()
    #: a variable holding an RGBA image (dims ``(y, x, rgba)``, uint8) that a workflow output also saves as
    #: ``<store>.png`` beside the store, for people (the figures)
    png: str | None = None
    #: the module that declared the kind (where it was made, as namedtuple finds its module), written into every
    #: store of the kind as ``selpath_kind_module``: opening the store imports that module alone to find the kind,
    #: where it is one the ``selpath.stages`` entry points name, instead of every installed stage package
    module: str = field(init=False, default="", compare=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "module", sys._getframe(2).f_globals.get("__name__", ""))  # the caller of __init__
        if not _NAME.match(self.name):
            raise SelpathError(f"cube kind name {self.name!r} must be lower_snake_case")
        if self.png is not None and (self.png not in self.variables or len(self.variables[self.png].dims) != 3):
            raise SelpathError(f"cube kind {self.name!r}: png names {self.png!r}, which must be one of its "
                               "variables with dims (height, width, rgba)")

    def frame_dims(self, variable: str) -> tuple[str, ...]:
        """Dims that index whole frames (everything but row/col/channel): the unit of a region write."""
        return tuple(d for d in self.variables[variable].dims if d not in (*PIXEL_DIMS, CHANNEL_DIM))

    def metadata(self, ds: xr.Dataset) -> dict[str, tuple[str | None, str]]:
        """``{variable: (units, long_name)}`` this kind fixes for the variables ``ds`` has (``{length}`` resolved;
        a variable whose length unit ``ds`` does not tell is left out)."""
        length = ds.attrs.get("length_unit") or next(
            (ds[c].attrs["units"] for c in ("x", "y") if c in ds.coords and "units" in ds[c].attrs), None)
        out = {}
        for name, var in self.variables.items():
            if name not in ds.data_vars or var.units == "" or (var.units and "{length}" in var.units and not length):
                continue
            out[name] = (in_length(var.units, str(length)) if var.units else None, var.long_name)
        return out

    def label(self, ds: xr.Dataset) -> xr.Dataset:
        """``ds`` as a cube of this kind: its ``selpath_kind`` attr, and the ``units`` and ``long_name`` this kind
        fixes on each of its variables (no ``units`` where it fixes none). What a stage returns, so that its result
        carries its labels in a notebook as in a store; nothing is checked (:meth:`check`)."""
        fixed = {}
        for name, (units, long_name) in self.metadata(ds).items():
            attrs = {k: v for k, v in ds[name].attrs.items() if k != "units"}
            attrs |= ({"units": units} if units is not None else {}) | ({"long_name": long_name} if long_name else {})
            fixed[name] = ds[name].copy(deep=False)
            fixed[name].attrs = attrs
        out = ds.assign(fixed) if fixed else ds.copy(deep=False)
        out.attrs = ({k: v for k, v in ds.attrs.items() if k != "selpath_kind_module"} | {"selpath_kind": self.name}
                     | ({"selpath_kind_module": self.module} if self.module else {}))
        return out

    def __hash__(self) -> int:  # equal kinds have one name (the dict fields could not be hashed)
        return hash(self.name)

    def _dims_ok(self, actual: tuple[str, ...], expected: tuple[str, ...]) -> bool:
        core = tuple(d for d in actual if d not in self.batch_dims)
        if core and core[-1] == CHANNEL_DIM:
            core = core[:-1]
        return core == expected

    def check(self, ds: xr.Dataset) -> list[Problem]:
        """Every way ``ds`` breaks this kind's schema, as problems (empty list: it conforms)."""
        problems: list[Problem] = []
        for name, var in self.variables.items():
            if name not in ds.data_vars:
                if var.required:
                    problems.append(Problem(f"variable {name!r} is missing", path=name,
                                            fix=f"add it with dims {var.dims}"
                                            + (f" ({var.description})" if var.description else "")))
                continue
            dims = tuple(ds[name].dims)
            if not self._dims_ok(dims, var.dims):
                batch = "".join(f"'{d}' + " for d in self.batch_dims)
                problems.append(Problem(f"variable {name!r} has dims {dims}; expected {var.dims} (optionally "
                                        f"{'led by ' + batch.removesuffix(' + ') + ', ' if batch else ''}+ 'channel')",
                                        path=name, fix="transpose or rename the dims (xarray .transpose / .rename)"))
        for name, (units, _) in self.metadata(ds).items():
            got = ds[name].attrs.get("units")
            if got != units:
                problems.append(Problem(f"variable {name!r} is in {got!r}; a {self.name} holds it in {units!r}",
                                        path=name,
                                        fix="convert the values, or correct attrs['units'] if only the label is wrong"
                                        if units is not None else "drop its units attr (it has none)"))
        for dim, units in self.coord_units.items():
            if not any(dim in ds[v].dims for v in self.variables if v in ds):
                continue  # the variables using this dim are missing: already reported
            want = "[" + ", ".join(sorted(units)) + "]"
            if dim not in ds.coords:
                problems.append(Problem(f"dim {dim} has no coordinate; it needs one with attrs units in {want}"))
                continue
            got = ds.coords[dim].attrs.get("units")
            if got is None:
                problems.append(Problem(f"coordinate {dim!r} has no units",
                                        fix=f"set ds[{dim!r}].attrs['units'] to one of {want}"))
            elif got not in units:
                problems.append(Problem(f"coordinate {dim!r} is in {got!r}; expected one of {want}",
                                        fix="convert the values and set attrs['units']"))
        for attr, description in self.attrs.items():
            if attr not in ds.attrs:
                problems.append(Problem(f"attr {attr!r} is missing", fix=f"set ds.attrs[{attr!r}]: {description}"))
        for check in self.attr_checks:
            problems.extend(Problem(msg) for msg in check(ds.attrs))
        return problems


def describe_kinds(kinds: Iterable[CubeKind]) -> str:
    """A Markdown table of ``kinds`` (docs/format.md shows every built-in one: ``selpath kinds --markdown``)."""
    rows = ["| kind | what | variable: dims | coordinate units | required attrs |", "|---|---|---|---|---|"]
    for kind in kinds:
        variables = "<br>".join(
            f"`{n}`{'' if v.required else ' (optional)'}: ({', '.join(v.dims)})"
            + ("" if v.units == "" else " [no units]" if v.units is None else f" [{v.units}]")
            for n, v in kind.variables.items()
        )
        units = "<br>".join(f"{d}: {'/'.join(sorted(u))}" for d, u in kind.coord_units.items()) or "—"
        attrs = "<br>".join(f"`{a}`" for a in kind.attrs) or "—"
        notes = [kind.description or "—"]
        if kind.batch_dims:
            notes.append(f"Stacks over {', '.join(f'`{d}`' for d in kind.batch_dims)}.")
        if kind.png:
            notes.append(f"`{kind.png}` is also saved as `<store>.png`.")
        stop = "." if len(notes) > 1 and not notes[0].endswith(".") else ""
        what = notes[0] + stop + "".join(f" {n}" for n in notes[1:])
        rows.append(f"| `{kind.name}` | {what} | {variables} | {units} | {attrs} |")
    return "\n".join(rows)
