"""Reading stores into a workflow: the ``load_store`` stage."""

from __future__ import annotations

import xarray as xr

from selpath.pipeline.constraints import StorePath
from selpath.pipeline.errors import StoreError
from selpath.pipeline.provenance import store_identity
from selpath.pipeline.registry import stage
from selpath.pipeline.store import open_store


def _precheck(settings) -> list[str]:
    """Open the store's metadata at validation time, so a bad input fails before anything runs."""
    try:
        open_store(settings.store, settings.kind)
    except StoreError as exc:
        return [str(p) for p in exc.problems]
    return []


def _variables(settings) -> list[str]:
    """The store's data variables (frame flags aside), read from its metadata at validation time."""
    return [str(v) for v in open_store(settings.store, settings.kind).data_vars]


@stage("load_store", precheck=_precheck, identity=lambda settings: store_identity(settings.store),
       variables=_variables)
def load_store(*, store: StorePath, kind: str | None = None) -> xr.Dataset:
    """Open a selpath store lazily, checked against its cube kind.

    Parameters
    ----------
    store : str
        Path of the zarr store, relative to the workflow file's folder.
    kind : str or None
        Cube kind the store must hold (default: the store's own ``selpath_kind``).

    Returns
    -------
    xr.Dataset
        The store's Dataset, lazy and checked against its kind (any kind: its ``selpath_kind`` attr names it).
    """
    return open_store(store, kind)
