"""``selpath inspect``: one store in full (kind, dims, coordinates with units, variables and their valid shares,
missing frames, chunk checks, provenance), or an archive's stores in one table."""

from __future__ import annotations

import json
import warnings
from pathlib import Path
from typing import Annotated

import typer
from rich.markup import escape
from rich.table import Table

from selpath.pipeline.cli_common import console, errors, fail, flag, guard
from selpath.pipeline.errors import SelpathError, StoreError

# what reads stores (numpy, dask, zarr, xarray) is imported by the function that reads: the command line answers
# --help and --version without them

#: ``inspect`` computes valid shares by default for stores of at most this many values (reading more takes long)
VALID_LIMIT = 2e8


def _print_archive(folder: Path) -> None:
    """One table of the stores under ``folder`` and where each came from (``selpath inspect FOLDER``)."""
    from selpath.pipeline.provenance import archive_stores

    stores = archive_stores(folder)
    if not stores:
        fail(SelpathError(f"{folder} holds no selpath store (a folder whose zarr.json carries selpath_format)"))
    table = Table(title=f"{escape(str(folder))}: {len(stores)} store(s)")
    for column in ("store", "kind", "workflow", "output", "created (UTC)"):
        table.add_column(column, overflow="fold")
    for row in stores:
        made = row["workflow"] is not None
        created = str(row["created"] or "")[:16].replace("T", " ")
        table.add_row(*(escape(str(row[k])) for k in ("store", "kind")),
                      *(("[red]provenance record unreadable[/]", "", "") if row.get("problem") else
                        (escape(str(row["workflow"])), escape(str(row["output"])), created) if made else
                        ("[dim]outside a workflow[/]", "", "")))
    console.print(table)
    console.print("selpath inspect STORE shows one store in full, with its provenance.")


def inspect(
    store: Annotated[Path, typer.Argument(help="a selpath zarr store, or a folder of stores (an archive)",
                                          metavar="STORE", show_default=False)],
    verify: Annotated[bool, flag("verify", "read every chunk and list the missing and corrupt ones")] = False,
    recapture: Annotated[bool, flag("recapture", "mark capture frames with bad chunks as not captured, so the "
                                     "next run of the acquisition captures them again")] = False,
    valid: Annotated[bool | None, typer.Option("--valid/--no-valid", metavar="",
                                               help="compute each variable's valid share (reads every value; "
                                               f"default: for stores of at most {VALID_LIMIT:.0e} values)")] = None,
) -> None:
    """Check a store and show its kind, dims, coords with units, variables, missing frames and provenance; or,
    given a folder that is not a store (an archive), list every store under it with its provenance in one table.

    Every chunk's size is compared with the one recorded when the store was written (one listing, contents not
    read); --verify reads every chunk and checks its checksum. Exit status 0: complete, and every chunk of its
    recorded size (with --verify: every chunk readable); 1: incomplete (frames missing, or no record that writing
    finished) or bad chunks; 2: it cannot be opened or breaks its kind's schema.
    """
    import numpy as np

    from selpath.pipeline.capture_store import missing_frames
    from selpath.pipeline.integrity import resized_chunks, verify_store
    from selpath.pipeline.provenance import read_provenance
    from selpath.pipeline.store import is_complete, open_store

    if store.is_dir() and not (store / "zarr.json").exists():
        _print_archive(store)
        return
    with guard(), warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            ds = open_store(store, keep_flags=True)
        except StoreError as exc:
            if not verify:
                raise
            bad = verify_store(store)  # say which chunks, even where the store cannot be opened for use
            errors.print(f"[bold red]error:[/] {escape(str(exc))}", highlight=False, soft_wrap=True)
            _print_bad(bad, recapture and store)
            raise typer.Exit(1 if bad else 2) from None
        missing = missing_frames(store)
        resized = None if verify else resized_chunks(store)  # one listing: sizes against the manifest's record
        bad = verify_store(store) if verify else resized or []
        provenance = read_provenance(store)
        complete = is_complete(store) or bool(missing)
    with guard(), np.errstate(all="ignore"):
        _describe_store(store, ds.drop_vars([v for v in ds.data_vars if str(v).startswith("written__")]), valid,
                        readable=not bad)
    incomplete = not complete
    for variable, frames in missing.items():
        state = "[green]complete[/]" if not frames else f"[yellow]{len(frames)} frames missing[/], first {frames[0]}"
        console.print(f"capture of {escape(variable)}: {state}")
        incomplete |= bool(frames)
    for warning in caught:
        console.print(f"[yellow]warning[/]: {escape(str(warning.message))}")
    if not missing and not complete:
        console.print("[yellow]incomplete[/]: no record that writing this store finished (a killed run leaves "
                      "such stores); write it again")
    if verify:
        _print_bad(bad, recapture and store)
    elif resized is None:
        console.print("chunks: no record of their sizes (written before selpath 0.2, or a capture not finished); "
                      "contents not read: `selpath inspect --verify` reads every chunk and checks its checksum")
    elif bad:
        _print_bad(bad, recapture and store, how="check (sizes against the record; contents not read)")
        console.print("a chunk changed since it was written: `selpath inspect --verify` reads every chunk; running "
                      "the workflow that wrote the store computes it again (a capture: captures those frames again)")
    else:
        console.print("chunks: every one has the size it was written with (contents not read: `selpath inspect "
                      "--verify` reads every chunk and checks its checksum)")
    if provenance and provenance.get("imported"):
        console.print("[underline]provenance[/]")
        digest = provenance.get("spec_and_frames_sha256") or provenance.get("spec_sha256")
        for key, value in {"imported": f"by `{provenance.get('command')}`",
                           "spec": str(provenance.get("spec")),
                           "spec and frames sha256": str(digest),
                           "selpath": str(provenance.get("versions", {}).get("selpath"))}.items():
            console.print(f"  {key}: {escape(value)}", highlight=False, soft_wrap=True)
    elif provenance:
        console.print("[underline]provenance[/]")
        step = provenance.get("step_record", {})
        lines = {"workflow": f"{provenance.get('workflow')} ({provenance.get('workflow_source')}), output "
                             f"{provenance.get('output')}",
                 "step": f"stage {step.get('stage')}, settings {json.dumps(step.get('settings', {}))}",
                 "created": f"{provenance.get('created')} with selpath {provenance.get('versions', {}).get('selpath')}"
                            f" ({provenance.get('scheduler')} scheduler)",
                 "step hash": str(provenance.get("step_hash"))}
        for key, value in lines.items():
            console.print(f"  {key}: {escape(value)}", highlight=False, soft_wrap=True)
    else:
        console.print("provenance: none recorded (a store written by selpath.to_store or another tool; a workflow "
                      "records it once an output is complete, and `selpath import` once the frames are in)")
    if incomplete or bad:
        raise typer.Exit(1)


def _describe_store(path: Path, ds, valid: bool | None, readable: bool) -> None:
    """Kind, dims, coordinates with units, attrs and each variable with units and valid share."""
    import dask
    import numpy as np

    from selpath.pipeline.integrity import open_group
    from selpath.pipeline.quality import valid_shares
    from selpath.pipeline.registry import resolve_kind

    kind = ds.attrs.get("selpath_kind")
    about = resolve_kind(kind, module=ds.attrs.get("selpath_kind_module")).description  # (opened: a known kind)
    on_disk = open_group(path).attrs.get("selpath_format")
    migrated = f", migrated to {ds.attrs.get('selpath_format')} on open" if on_disk != ds.attrs.get(
        "selpath_format") else ""
    console.print(f"[bold]{escape(str(path))}[/]: {escape(str(kind))} store, format {on_disk}{migrated}"
                  f" ({escape(about)})", highlight=False)
    console.print("dims: " + ", ".join(f"{d} {n:,}" for d, n in ds.sizes.items()), highlight=False)
    total = sum(int(v.size) for v in ds.data_vars.values())
    shares, scalar_values, unread = {}, {}, "valid share not computed (--valid reads every value)"
    if readable:
        try:
            shares = valid_shares(ds) if valid or (valid is None and total <= VALID_LIMIT) else {}
            scalars = [n for n, v in ds.data_vars.items() if v.ndim == 0]
            scalar_values = dict(zip(scalars, dask.compute(*(ds[n].data for n in scalars)), strict=True))
        except StoreError:
            shares, unread = {}, "values not read: a chunk is bad (--verify lists every bad chunk)"
    else:
        unread = "values not read: bad chunks (below)"
    for title, group in (("coordinates", ds.coords), ("variables", ds.data_vars)):
        console.print(f"[underline]{title}[/]")
        for name, array in group.items():
            units = array.attrs.get("units")
            head = (f"  [bold cyan]{escape(str(name))}[/] ({escape(', '.join(map(str, array.dims)))}) {array.dtype}"
                    + (f" \\[{escape(str(units))}]" if units else ""))
            if name in scalar_values:
                head += f" = {_scalar_text(np.asarray(scalar_values[name]).item())}"
            elif title == "coordinates" and array.size and np.issubdtype(array.dtype, np.number):
                head += f": {array.values.min():g} … {array.values.max():g}"
            elif title == "variables":
                share = shares.get(str(name))
                head += (f": {unread}" if not shares else
                         "" if share is None else f": {share:.1%} {'true' if array.dtype == bool else 'finite'}"
                         if isinstance(share, float) else
                         ": " + ", ".join(f"{k} {v:.1%}" for k, v in share.items() if v or k == "valid"))
            console.print(head, highlight=False, soft_wrap=True)
            if array.attrs.get("long_name"):
                console.print(f"      {escape(str(array.attrs['long_name']))}", highlight=False, soft_wrap=True)
    hidden = ("selpath_kind", "selpath_format", "selpath_kind_module")
    attrs = {k: v for k, v in ds.attrs.items() if k not in hidden and not k.startswith("_")}
    if attrs:
        console.print("[underline]attrs[/]")
        for key, value in attrs.items():
            text = json.dumps(value, default=str, ensure_ascii=False)
            console.print(f"  {escape(key)}: {escape(text if len(text) <= 200 else text[:197] + '…')}",
                          highlight=False, soft_wrap=True)


def _scalar_text(value) -> str:
    if isinstance(value, bool):
        return "yes" if value else "no"
    return f"{value:.6g}" if isinstance(value, int | float) else escape(str(value))


def _print_bad(bad: list, recapture_store: Path | bool, how: str = "verify") -> None:
    from selpath.pipeline.capture_store import forget_frames
    from selpath.pipeline.locks import store_lock

    console.print(f"{how}: {'[green]every chunk reads[/]' if not bad else f'[red]{len(bad)} bad chunk(s)[/]'}")
    for chunk in bad:
        console.print(f"  {escape(str(chunk))}")
    if bad and recapture_store:
        with guard(), store_lock(recapture_store, purpose="inspect --recapture"):
            frames = forget_frames(recapture_store, bad)
        console.print(f"marked {frames} frame(s) as not captured: run the acquisition again to capture them")
