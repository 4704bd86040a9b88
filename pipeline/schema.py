"""The schema check run whenever a store is opened or written, against the kinds of :mod:`selpath.pipeline.kinds`.

:func:`check_dataset` returns *every* way a dataset breaks its kind at once; callers raise them together as one
:class:`~selpath.pipeline.errors.StoreError`. :func:`metadata` and :func:`with_metadata` give a dataset the ``units``
and
``long_name`` its kind fixes; :func:`describe_kinds` is the Markdown table of docs/format.md.
"""

from __future__ import annotations

import xarray as xr
from selpath.pipeline.errors import Problem
from selpath.pipeline.kinds import CHANNEL_DIM, KINDS

# Dims a kind may add after its own (sinograms and reconstructions are batched over slices).
_EXTRA_LEADING_OK = {"sinogram": ("slice",), "reconstruction": ("slice",)}


def _dims_ok(actual: tuple[str, ...], expected: tuple[str, ...], kind: str) -> bool:
    core = tuple(d for d in actual if d not in _EXTRA_LEADING_OK.get(kind, ()))
    if core and core[-1] == CHANNEL_DIM:
        core = core[:-1]
    return core == expected


def in_length(template: str, length: str) -> str:
    """``template`` with ``{length}`` replaced by ``length``; a dimensionless length ("1") gives σ the unit "1",
    not "1/1"."""
    units = template.replace("{length}", str(length))
    return "1" if units == "1/1" else units


def metadata(ds: xr.Dataset, kind: str) -> dict[str, tuple[str | None, str]]:
    """``{variable: (units, long_name)}`` the kind fixes for the variables ``ds`` has (``{length}`` resolved;
    a variable whose length unit ``ds`` does not tell is left out)."""
    length = ds.attrs.get("length_unit") or next(
        (ds[c].attrs["units"] for c in ("x", "y") if c in ds.coords and "units" in ds[c].attrs), None)
    out = {}
    for name, var in KINDS[kind].variables.items():
        if name not in ds.data_vars or var.units == "" or (var.units and "{length}" in var.units and not length):
            continue
        out[name] = (in_length(var.units, str(length)) if var.units else None, var.long_name)
    return out


def with_metadata(ds: xr.Dataset, kind: str) -> xr.Dataset:
    """``ds`` with the ``units`` and ``long_name`` its kind fixes (no ``units`` where it fixes none)."""
    fixed = {}
    for name, (units, long_name) in metadata(ds, kind).items():
        attrs = {k: v for k, v in ds[name].attrs.items() if k != "units"}
        attrs |= ({"units": units} if units is not None else {}) | ({"long_name": long_name} if long_name else {})
        fixed[name] = ds[name].copy(deep=False)
        fixed[name].attrs = attrs
    return ds.assign(fixed) if fixed else ds


def check_dataset(ds: xr.Dataset, kind: str) -> list[Problem]:
    """Every way ``ds`` breaks the schema of ``kind``, as problems (empty list: it conforms).

    >>> import numpy as np, xarray as xr
    >>> ds = xr.Dataset({"sigma": (("y", "x"), np.zeros((2, 2)))})
    >>> [p.message for p in check_dataset(ds, "reconstruction")]  # doctest: +NORMALIZE_WHITESPACE
    ['dim y has no coordinate; it needs one with attrs units in [1, cm, m, mm, px, um]',
     'dim x has no coordinate; it needs one with attrs units in [1, cm, m, mm, px, um]']
    """
    if kind not in KINDS:
        known = ", ".join(sorted(KINDS))
        return [Problem(f"unknown cube kind {kind!r}", fix=f"use one of: {known}")]
    spec = KINDS[kind]
    problems: list[Problem] = []
    for name, var in spec.variables.items():
        if name not in ds.data_vars:
            if var.required:
                problems.append(
                    Problem(
                        f"variable {name!r} is missing",
                        path=name,
                        fix=f"add it with dims {var.dims}" + (f" ({var.description})" if var.description else ""),
                    )
                )
            continue
        dims = tuple(ds[name].dims)
        if not _dims_ok(dims, var.dims, kind):
            problems.append(
                Problem(
                    f"variable {name!r} has dims {dims}; expected {var.dims} (optionally + 'channel')",
                    path=name,
                    fix="transpose or rename the dims (xarray .transpose / .rename)",
                )
            )
    for name, (units, _) in metadata(ds, kind).items():
        got = ds[name].attrs.get("units")
        if got != units:
            problems.append(Problem(f"variable {name!r} is in {got!r}; a {kind} holds it in {units!r}", path=name,
                                    fix="convert the values, or correct attrs['units'] if only the label is wrong"
                                    if units is not None else "drop its units attr (it has none)"))
    for dim, units in spec.coord_units.items():
        if not any(dim in ds[v].dims for v in spec.variables if v in ds):
            continue  # the variables using this dim are missing: already reported
        want = "[" + ", ".join(sorted(units)) + "]"
        if dim not in ds.coords:
            problems.append(Problem(f"dim {dim} has no coordinate; it needs one with attrs units in {want}"))
            continue
        got = ds.coords[dim].attrs.get("units")
        if got is None:
            problems.append(
                Problem(f"coordinate {dim!r} has no units", fix=f"set ds[{dim!r}].attrs['units'] to one of {want}")
            )
        elif got not in units:
            problems.append(
                Problem(
                    f"coordinate {dim!r} is in {got!r}; expected one of {want}",
                    fix="convert the values and set attrs['units']",
                )
            )
    for attr, description in spec.attrs.items():
        if attr not in ds.attrs:
            problems.append(Problem(f"attr {attr!r} is missing", fix=f"set ds.attrs[{attr!r}]: {description}"))
    for check in spec.attr_checks:
        problems.extend(Problem(msg) for msg in check(ds.attrs))
    return problems


def describe_kinds() -> str:
    """A Markdown table of every kind, used by docs/format.md and ``selpath stages``."""
    rows = ["| kind | what | variable: dims | coordinate units | required attrs |", "|---|---|---|---|---|"]
    for kind in KINDS.values():
        variables = "<br>".join(
            f"`{n}`{'' if v.required else ' (optional)'}: ({', '.join(v.dims)})"
            + ("" if v.units == "" else " [no units]" if v.units is None else f" [{v.units}]")
            for n, v in kind.variables.items()
        )
        units = "<br>".join(f"{d}: {'/'.join(sorted(u))}" for d, u in kind.coord_units.items()) or "—"
        attrs = "<br>".join(f"`{a}`" for a in kind.attrs) or "—"
        rows.append(f"| `{kind.name}` | {kind.description or '—'} | {variables} | {units} | {attrs} |")
    return "\n".join(rows)
