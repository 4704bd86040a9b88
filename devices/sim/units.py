"""Quantities with units in the simulator's scene files: ``"20 mm"``, ``"0.15 /mm"``, ``"45 deg"``, ``"800 px"``,
``"50 ms"``, each read into the unit the simulator works in (mm, 1/mm, degrees, px, seconds).

A scene may instead declare its lengths **dimensionless** (``length_unit: "1"``, as an import spec may): lengths in
a unit the user keeps consistent (a renderer's scene units), written as bare numbers or with the unit ``1``
(``"0.18"``, ``"0.18 1"``), and coefficients per that unit, bare or ``/1`` (``"60"``, ``"60 /1"``). Physical length
units are refused in such a scene, and dimensionless ones in a scene of physical lengths: a length is never
converted between the two. :func:`lengths_in` sets the unit a scene's fields are read and written in (a context
variable the scene sets while it validates or serialises itself: the fields cannot see their model's own
``length_unit``). So a whole ``Scene`` validates and dumps in its unit; a part of a dimensionless scene (its
``light``, its ``object``) validated or dumped on its own is read and written in mm, unless inside
``lengths_in("1")``.

>>> import pydantic
>>> adapter = pydantic.TypeAdapter(Length)
>>> adapter.validate_python("2 cm")
20.0
>>> with lengths_in("1"):
...     adapter.validate_python("0.18"), pydantic.TypeAdapter(InvLength).validate_python("60 /1")
(0.18, 60.0)
"""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
import re
from typing import Annotated, Any

import numpy as np
import pydantic

_TO_MM = {"m": 1000.0, "cm": 10.0, "mm": 1.0, "um": 1e-3}
_TO_DEG = {"deg": 1.0, "degree": 1.0, "rad": 180.0 / np.pi}
_TO_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6}
#: the length units a scene may declare: millimetres (every physical unit is read into them) or dimensionless
SCENE_LENGTH_UNITS = ("mm", "1")
_QUANTITY = re.compile(r"^\s*(?P<value>[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)\s*(?P<unit>\S+)\s*$")
_NUMBER = re.compile(r"^\s*[-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?\s*$")
_FREE = 'length_unit: "1"'
_LENGTH_UNIT: contextvars.ContextVar[str] = contextvars.ContextVar("selpath_scene_length_unit", default="mm")


def scene_length_unit(value: Any) -> Any:
    """A scene's ``length_unit`` as text: YAML reads an unquoted ``1`` as a number, which means ``"1"`` here."""
    return "1" if not isinstance(value, bool) and isinstance(value, int | float) and value == 1 else value


@contextlib.contextmanager
def lengths_in(unit: str):
    """Read and write lengths and coefficients in ``unit`` (``"mm"`` or ``"1"``) inside the block."""
    token = _LENGTH_UNIT.set(unit)
    try:
        yield
    finally:
        _LENGTH_UNIT.reset(token)


def _finite(number: float, value: Any, what: str) -> float:
    if not math.isfinite(number):
        raise ValueError(f"{value!r} is not a finite {what.removeprefix('a ').removeprefix('an ')}")
    return number


def unit_parser(units: dict[str, float], example: str, what: str, dimensionless: tuple[str, ...] = ()):
    """A validator reading ``<number> <unit>`` (one of ``units``, each its factor to the canonical unit). A quantity of
    length (``dimensionless``: the unit spellings it takes in a dimensionless scene, e.g. ``("1",)``) reads a bare
    number or one of those instead when the scene's lengths are dimensionless (:func:`lengths_in`)."""

    def parse(value: Any) -> float:
        if isinstance(value, bool) or not isinstance(value, str | int | float):
            raise ValueError(f"expected {what} such as {example!r}")
        free = dimensionless and _LENGTH_UNIT.get() == "1"
        if free:
            if not isinstance(value, str) or _NUMBER.match(value):
                return _finite(float(value), value, what)
            match = _QUANTITY.match(value)
            if not match or match["unit"] not in dimensionless:
                number = match["value"] if match else "0.18"
                raise ValueError(f"{value!r}: this scene's lengths are dimensionless ({_FREE}), so {what} is a bare "
                                 f"number (or {number} {dimensionless[0]}), never in a physical unit")
            return _finite(float(match["value"]), value, what)
        if not isinstance(value, str):
            hint = f" (or declare {_FREE} at the scene's top: dimensionless lengths)" if dimensionless else ""
            raise ValueError(f"{value} has no unit; write it as {what}, e.g. {example!r}{hint}")
        match = _QUANTITY.match(value)
        if match and match["unit"] in dimensionless:
            raise ValueError(f"{value!r} is dimensionless; declare {_FREE} at the scene's top to write every length "
                             f"so, or give a unit, e.g. {example!r}")
        if not match or match["unit"] not in units:
            raise ValueError(f"{value!r} is not {what}; write e.g. {example!r} (units: {', '.join(units)})")
        return _finite(float(match["value"]) * units[match["unit"]], value, what)

    return pydantic.BeforeValidator(parse)


@dataclasses.dataclass(frozen=True)
class Quantity:
    """What a quantity field reads, for people and for the generated docs (``selpath.pipeline.reference``): ``what``
    it is, an ``example``, the ``units`` it accepts and the ``canonical`` one the simulator works in (in a scene of
    dimensionless lengths, ``dimensionless`` instead)."""

    what: str
    example: str
    units: tuple[str, ...]
    canonical: str
    dimensionless: tuple[str, ...] = ()


def quantity(units: dict[str, float], example: str, what: str, dimensionless: tuple[str, ...] = ()):
    """A float read as ``<number> <unit>`` (:func:`unit_parser`) and dumped to JSON in the canonical unit (the one
    of factor 1; in a dimensionless scene the first of ``dimensionless``), so that a model dumped with
    ``model_dump(mode="json")`` validates again."""
    canonical = next(unit for unit, factor in units.items() if factor == 1.0)

    def dump(value: float) -> str:
        unit = dimensionless[0] if dimensionless and _LENGTH_UNIT.get() == "1" else canonical
        return f"{value!r} {unit}"

    return Annotated[float, unit_parser(units, example, what, dimensionless),
                     pydantic.PlainSerializer(dump, when_used="json"),
                     Quantity(what, example, tuple(units), canonical, dimensionless)]


Length = quantity(_TO_MM, "20 mm", "a length", ("1",))
#: a length in a file with no ``length_unit`` (the projector–camera scenes): always physical
PhysicalLength = quantity(_TO_MM, "20 mm", "a length")
#: absorption or scattering coefficient, per mm
InvLength = quantity({f"/{u}": 1.0 / f for u, f in _TO_MM.items()} | {f"1/{u}": 1.0 / f for u, f in _TO_MM.items()},
                     "0.1 /mm", "a coefficient per length", ("/1", "1/1"))
Angle = quantity(_TO_DEG, "45 deg", "an angle")
Pixels = quantity({"px": 1.0}, "800 px", "a pixel quantity")
Duration = quantity(_TO_S, "50 ms", "a duration")
