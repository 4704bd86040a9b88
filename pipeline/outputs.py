"""Where outputs may be written, and how they land there without losing anything.

Rules for an output store (checked when a workflow is validated, and again before a run writes):

* its path ends in ``.zarr`` (``out/capture.zarr``, ``s3://bucket/run/capture.zarr``);
* if something is already there, it is a selpath store (its root ``zarr.json`` carries the
  ``selpath_format`` marker): selpath replaces only what it wrote;
* it is never the folder of, nor a parent folder of, another output, an input (a store or file a step
  reads), the workflow file or the working folder.

A store is written into a temporary sibling (``.<name>.partial-<token>``) and moved into place only
once its data, manifest and provenance are complete (:class:`Staging`), so a crash never leaves a
half-written store under the final name: either the old store or the new one is there. Stores on object
storage (``scheme://…``) cannot be renamed; they are written in place and their manifest, written last,
marks them complete (see :mod:`selpath.pipeline.integrity`). A ``figure`` output also writes ``<stem>.png``;
a PNG there that selpath did not write (no ``selpath_store`` text chunk) is never replaced. An existing
selpath store is replaced only for the workflow output that wrote it (its provenance names both), or where
the output says ``replace: true`` (then atomically, as above); a store with no provenance (``to_store``, or
made by hand) is kept likewise; an acquisition resumes an unfinished capture in place.
"""

from __future__ import annotations

import glob
import json
import os
import shutil
import uuid
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

from selpath.pipeline import remote
from selpath.pipeline.errors import Problem, StoreError
from selpath.pipeline.remote import is_url

STORE_SUFFIX = ".zarr"
_PARTIAL = ".partial-"
_REPLACED = ".replaced-"
#: PNG text key naming the store a figure PNG was rendered from (marks PNGs selpath may replace)
PNG_MARKER = "selpath_store"


def _is_selpath_store(path: str | os.PathLike) -> bool:
    """:func:`selpath.pipeline.integrity.is_selpath_store`, imported (with zarr) only where a path exists to ask
    about, so checking a new workflow's outputs reads no store library."""
    from selpath.pipeline.integrity import is_selpath_store

    return is_selpath_store(path)


def is_remote(path: str | os.PathLike) -> bool:
    """On object storage (an fsspec URL other than ``file://``): :func:`selpath.pipeline.remote.is_url`."""
    return is_url(path)


def _garbled_root(path: Path) -> bool:
    """True if ``path/zarr.json`` exists but is not JSON (torn, truncated or overwritten): a damaged store, not a
    folder of someone else's files."""
    try:
        json.loads((path / "zarr.json").read_text())
    except FileNotFoundError:
        return False
    except (OSError, ValueError):
        return True
    return False


def png_path(store: str | os.PathLike) -> str:
    """Where a figure output's PNG lands: ``<store without .zarr>.png``."""
    return f"{os.fspath(store).removesuffix(STORE_SUFFIX)}.png"


def png_written_by_selpath(path: str | os.PathLike) -> bool:
    from PIL import Image

    try:
        with Image.open(path) as image:
            return PNG_MARKER in getattr(image, "text", {})
    except (OSError, ValueError):
        return False


def _inside(child: Path, parent: Path) -> bool:
    """True if ``child`` is ``parent`` or lies anywhere under it."""
    return child == parent or parent in child.parents


@dataclass(frozen=True)
class OutputPath:
    """An output store to check: its resolved path and where the user wrote it (for messages)."""

    name: str
    store: str
    #: location of the field in the workflow file, e.g. ("outputs", "capture", "store")
    field: tuple
    #: the workflow writing it; a store another workflow (or output) made is never replaced
    workflow: str = ""
    #: the output fills its store frame by frame (an acquisition), resuming what is there
    self_written: bool = False
    #: the workflow file says ``replace: true``: a finished store of another owner may be replaced
    replace: bool = False


def output_problems(outputs: list[OutputPath], protected: Mapping[str, str | os.PathLike]) -> list[tuple[tuple,
                                                                                                         str, str]]:
    """Every way ``outputs`` break the rules above, as ``(field, message, fix)``.

    ``protected`` maps a label (``"input steps[2].with.store"``, ``"the workflow file"``) to a path no output
    may be or contain.
    """
    problems: list[tuple[tuple, str, str]] = []
    for out in outputs:
        text = out.store
        name = text.rstrip("/").rsplit("/", 1)[-1]
        if not name.endswith(STORE_SUFFIX) or name == STORE_SUFFIX:
            there = Path(text) if text.strip() and not is_remote(text) else None
            held = ("" if there is None or not (there.exists() or there.is_symlink()) else
                    ": it is an existing folder, and not a selpath store, so selpath never writes into it" if
                    there.is_dir() and not _is_selpath_store(there) else ": it is an existing file")
            problems.append((out.field, f"output {out.name!r} store {text!r} is not a path ending in "
                             f"'{STORE_SUFFIX}'{held}", f"name a new store, like out/{out.name}.zarr"))
            continue
        if is_remote(text):
            problems.extend((out.field, message, fix) for message, fix in _remote_problems(out, text))
            continue
        path = Path(text)
        if path.is_symlink() or (path.exists() and not path.is_dir()):
            problems.append((out.field, f"output {out.name!r}: {text} exists and is not a folder",
                             "choose another path; selpath replaces only stores it wrote"))
            continue
        if path.exists() and not _is_selpath_store(path):
            garbled = _garbled_root(path)
            problems.append((out.field, f"output {out.name!r}: {text} holds a store whose root metadata "
                             "(zarr.json) cannot be read; selpath never replaces it" if garbled
                             else f"output {out.name!r}: {text} holds files that are not a selpath store "
                             "(no selpath_format marker); selpath never replaces them",
                             "restore the store from a backup, or choose another path" if garbled
                             else "choose another path, or move those files away"))
        elif path.exists():
            problems.extend((out.field, message, fix) for message, fix in _ownership(out, path))
        for other in outputs:
            if other is not out and not is_remote(other.store) and path in Path(other.store).parents:
                problems.append((out.field, f"output {out.name!r} ({text}) is a parent folder of output "
                                 f"{other.name!r} ({other.store}); writing one would delete the other",
                                 "give each output its own .zarr path, side by side"))
        for label, value in protected.items():
            if not is_remote(value) and _inside(Path(value), path):
                problems.append((out.field, f"output {out.name!r} ({text}) would replace {label} ({value})",
                                 "write outputs to their own .zarr paths, e.g. under out/"))
    return problems


def _remote_problems(out: OutputPath, url: str) -> list[tuple[str, str]]:
    """The local rules on object storage: objects under the output's prefix that are no selpath store are never
    replaced, and a selpath store there is replaced only as :func:`_ownership` allows."""
    names = remote.members(url)
    if not names:
        return []
    if not _is_selpath_store(url):
        return [(f"output {out.name!r}: {url} holds objects that are not a selpath store (no selpath_format "
                 "marker); selpath never replaces them", "choose another prefix, or move those objects away")]
    return _ownership(out, url, names)


def _ownership(out: OutputPath, path: Path | str, names: list[str] | None = None) -> list[tuple[str, str]]:
    """An existing selpath store is replaced only by the workflow output that wrote it; an acquisition resumes
    only a capture (its own sweep is checked when it starts). ``names``: the store's top-level entries (None:
    listed here, for a local folder)."""
    from selpath.pipeline.integrity import read_manifest
    from selpath.pipeline.provenance import read_provenance

    try:
        provenance = read_provenance(path)
    except StoreError as exc:  # a garbled record: no proof of who wrote the store, so it is kept
        return [(f"output {out.name!r}: {exc.problems[0].message}; selpath does not replace a store it cannot "
                 "identify", exc.problems[0].fix)]
    names = [p.name for p in Path(path).iterdir()] if names is None else names
    capture = any(name.startswith("written__") for name in names)
    if provenance is not None and provenance.get("imported"):
        return [(f"output {out.name!r} of workflow {out.workflow!r}: {path} holds a capture imported with "
                 "`selpath import`; selpath never replaces it", "choose another path, or delete that store yourself")]
    if provenance is not None:
        owner = (provenance.get("workflow"), provenance.get("output"))
        if owner != (out.workflow, out.name) and not (out.replace and not out.self_written):
            return [(f"output {out.name!r} of workflow {out.workflow!r}: {path} holds output {owner[1]!r} of "
                     f"workflow {owner[0]!r}; selpath replaces a store only for the output that wrote it",
                     "choose another path, set `replace: true` on this output to replace that store, or delete it "
                     "yourself if it is no longer needed" if not out.self_written else
                     "choose another path for the capture, or delete that store yourself")]
        return []
    if out.replace and not out.self_written and not capture:
        return []  # a store written outside a workflow, replaced because the workflow file says so
    if out.self_written:
        return [] if capture else [(f"output {out.name!r}: {path} is a selpath store but not a capture to resume",
                                    "choose another path")]
    # Outputs land through a staging sibling, so a store at the final path without a manifest was not left half
    # written by a run: it was made by hand (xarray's to_zarr with selpath's attrs) or by an old selpath. Either
    # way it may be someone's only copy, so it is kept like the others.
    what = ("an unfinished capture" if capture else
            "a complete store written outside a workflow (to_store)" if (read_manifest(path) or {}).get("complete")
            else "a selpath store with no record of who wrote it (no provenance, no manifest: written by hand or by "
            "an older selpath)")
    return [(f"output {out.name!r} of workflow {out.workflow!r}: {path} holds {what}; selpath does not replace it",
             "choose another path, set `replace: true` on this output to replace it, or delete that store yourself"
             if not capture else "choose another path, or delete that store yourself if it is no longer needed")]


def check_png(store: str | os.PathLike) -> None:
    """Before a figure output is written: refuse if ``<stem>.png`` exists and selpath did not write it."""
    png = png_path(store)
    if Path(png).exists() and not png_written_by_selpath(png):
        raise StoreError(Problem(f"a figure output also writes {png}, which exists and was not written by selpath",
                                 where=os.fspath(store), fix="move that PNG away or rename the output store"))


class Staging:
    """A temporary sibling of ``final`` to write a store into, then :meth:`commit` (move into place) or
    :meth:`abort` (remove). For remote stores the staging path is ``final`` itself."""

    def __init__(self, final: str | os.PathLike):
        self.final = os.fspath(final) if is_remote(final) else str(Path(final).absolute())
        if is_remote(self.final):
            self.path = self.final
        else:
            target = Path(self.final)
            target.parent.mkdir(parents=True, exist_ok=True)
            self.path = str(target.parent / f".{target.name}{_PARTIAL}{uuid.uuid4().hex[:12]}")

    def commit(self) -> None:
        """Move the finished store into place; an older selpath store there is replaced, anything else refused."""
        if self.path == self.final:
            return
        final = Path(self.final)
        if final.exists() or final.is_symlink():
            if final.is_symlink() or not _is_selpath_store(final):
                self.abort()
                raise StoreError(Problem("something that is not a selpath store appeared at this path while the "
                                         "output was written; it was left untouched and the output not written",
                                         where=self.final, fix="move it away and run again"))
            old = final.parent / f".{final.name}{_REPLACED}{uuid.uuid4().hex[:12]}"
            os.rename(final, old)
            os.rename(self.path, final)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(self.path, final)

    def abort(self) -> None:
        if self.path != self.final:
            shutil.rmtree(self.path, ignore_errors=True)


def tidy_staging(final: str | os.PathLike) -> list[str]:
    """Clean up what a killed writer left beside ``final``: partial stores are removed; a replaced store whose
    successor never arrived is put back. Call it only while holding the store's lock. Returns what it did."""
    if is_remote(final):
        return []
    target = Path(final).absolute()
    if not target.parent.is_dir():
        return []
    done = []
    name = glob.escape(target.name)  # a store named "a*.zarr" must not match another's leftovers
    replaced = sorted(target.parent.glob(f".{name}{_REPLACED}*"))
    for leftover in sorted(target.parent.glob(f".{name}{_PARTIAL}*")) + replaced:
        if leftover in replaced and not target.exists() and _is_selpath_store(leftover):
            os.rename(leftover, target)
            done.append(f"restored {target} from {leftover.name}")
        else:
            shutil.rmtree(leftover, ignore_errors=True)
            done.append(f"removed {leftover.name}")
    return done
