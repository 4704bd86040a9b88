"""One writer per store: a lock file beside each output store while a run or an acquisition writes it.

The lock is ``.<name>.lock`` next to the store, held with ``fcntl.flock`` and holding the owner's pid,
host, start time and command as JSON. The kernel drops a flock when its process dies, so a lock left by
a killed run is simply taken over; a live owner gets a :class:`~selpath.pipeline.errors.StoreError` that names
it. Within one process a lock already held is entered again (the engine locks an acquisition's store,
then the acquisition locks it too). Written by hand: ``filelock`` locks the same way but records no
owner to name in the error. Remote stores (``scheme://…``) are not locked. POSIX only.
"""

from __future__ import annotations

import datetime as _dt
import json
import os
import socket
import sys
from collections.abc import Iterable, Iterator
from contextlib import ExitStack, contextmanager
from pathlib import Path

from selpath.pipeline.errors import Problem, StoreError, environment_fault

try:
    import fcntl
except ImportError:  # pragma: no cover - Windows
    fcntl = None


def lock_path(store: str | os.PathLike) -> Path:
    target = Path(store).resolve()  # one lock file whatever link the store is reached through
    return target.parent / f".{target.name}.lock"


def _owner(purpose: str) -> dict:
    return {"pid": os.getpid(), "host": socket.gethostname(), "purpose": purpose,
            "since": _dt.datetime.now(_dt.UTC).isoformat(timespec="seconds"), "command": " ".join(sys.argv)[:300]}


def _read_owner(path: Path) -> dict:
    try:
        owner = json.loads(path.read_text() or "{}")
    except (OSError, ValueError):
        return {}
    return owner if isinstance(owner, dict) else {}


@contextmanager
def store_lock(store: str | os.PathLike, purpose: str = "writing") -> Iterator[None]:
    """Hold the lock of ``store`` for the block; raise StoreError if another live process holds it."""
    if "://" in os.fspath(store) or fcntl is None:
        yield
        return
    path = lock_path(store)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        fault = environment_fault(exc, f"taking the lock of the output store {os.fspath(store)}")
        if fault is None:
            raise
        raise fault from exc
    while True:
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            os.close(fd)
            owner = _read_owner(path)
            if owner.get("pid") == os.getpid() and owner.get("host") == socket.gethostname():
                yield  # this process holds it already: re-entered, released by the outer holder
                return
            who = (f"process {owner.get('pid', '?')} on {owner.get('host', '?')} ({owner.get('purpose', '?')}, "
                   f"since {owner.get('since', '?')}: {owner.get('command', '?')})")
            raise StoreError(Problem(f"another selpath {who} is writing this store", where=os.fspath(store),
                                     fix="wait for it to finish or stop it; the lock of a process that died is "
                                     "taken over automatically")) from None
        try:  # the file may have been unlinked by its last holder between our open and our flock: retry
            same = os.fstat(fd).st_ino == os.stat(path).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    try:
        os.ftruncate(fd, 0)
        os.write(fd, json.dumps(_owner(purpose)).encode())
        yield
    finally:
        try:
            path.unlink()  # while still holding it, so no one locks a file that is about to vanish
        except FileNotFoundError:
            pass
        os.close(fd)


@contextmanager
def store_locks(stores: Iterable[str | os.PathLike], purpose: str = "writing") -> Iterator[None]:
    """Hold the locks of several stores, taken in sorted order (two runs never wait on each other in a cycle)."""
    with ExitStack() as stack:
        for store in sorted({os.fspath(s) for s in stores}):
            stack.enter_context(store_lock(store, purpose))
        yield
