"""``selpath import``: frames made elsewhere into a checked capture store, with its provenance and the advice of its
kind's data checks."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape

from selpath.pipeline.cli_common import console, errors, guard
from selpath.pipeline.errors import Problem, StoreError


def import_(spec: Annotated[Path, typer.Argument(help="import spec (YAML): kind, frames, geometry or timing",
                                                 metavar="SPEC", show_default=False)],
            store: Annotated[Path, typer.Argument(help="capture store to write (a new .zarr path)", metavar="STORE",
                                                  show_default=False)]) -> None:
    """Turn frames made elsewhere (TIFF/PNG folders, .npy/.npz, HDF5) into a checked capture store.

    The spec says the cube kind, where each variable's frames lie and the geometry or timing the stages read,
    with units (docs/format.md, "Importing captures"). Frames are copied one by one; nothing is written into
    the sources, and an existing store is never replaced. The store records its provenance: the spec's text, a
    SHA-256 of the spec and every frame file, the command and selpath's version (`selpath inspect STORE`).
    """
    import dask

    from selpath.pipeline.provenance import write_provenance
    from selpath.pipeline.registry import registry_for
    from selpath.pipeline.store import to_store

    with guard():
        if store.exists():
            raise StoreError(Problem("exists; selpath import writes a new store and never replaces one",
                                     where=str(store), fix="choose another path, or delete that store yourself"))
        stage = registry_for(["import_capture"])["import_capture"]
        ds = stage.func(spec=str(spec))
        with dask.config.set(scheduler="threads"):
            to_store(ds, store, ds.attrs["selpath_kind"])
        write_provenance(store, import_provenance(spec, store, stage.identity(stage.params(spec=str(spec)))))
    sizes = ", ".join(f"{d} {n}" for d, n in ds.sizes.items())
    console.print(f"[green]ok[/]: {escape(str(store))}: {ds.attrs['selpath_kind']} ({escape(sizes)}); "
                  f"variables {escape(', '.join(map(str, ds.data_vars)))}")
    _advise(store)


def _advise(store: Path) -> None:
    """The imported kind's data checks (what the frames contradict of the spec), printed as warnings; the store is
    kept either way."""
    from selpath.pipeline.registry import resolve_kind
    from selpath.pipeline.store import open_store

    with guard():
        ds = open_store(store)
        kind = resolve_kind(ds.attrs["selpath_kind"], module=ds.attrs.get("selpath_kind_module"))
    for check in kind.data_checks:
        try:
            advice = check(ds)
        except Exception as exc:  # noqa: BLE001 - the store is written and kept: a check that fails says so
            advice = [f"the check {getattr(check, '__name__', check)} could not run ({type(exc).__name__}: {exc}); "
                      "the store is written and kept"]
        for line in advice:
            errors.print(f"[yellow]warning:[/] {escape(line)}", highlight=False, soft_wrap=True)


def import_provenance(spec: Path, store: Path, identity: dict) -> dict:
    """What an imported capture records of how it was made (read by ``selpath inspect``): no time and no absolute
    path, so that importing the same frames with the same spec gives the same store, whose content identifies it
    to the steps that read it (:func:`selpath.pipeline.provenance.store_identity`)."""
    from selpath.pipeline.identity import package_versions

    return {"imported": True, "command": f"selpath import {spec.name} {store.name}", "spec": spec.name,
            "spec_text": spec.read_text(), **identity, "output": store.name, "versions": package_versions()}
