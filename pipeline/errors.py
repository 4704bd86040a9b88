"""The project's exceptions: one small hierarchy, every message saying what, where and how to mend it.

Errors that can have several causes at once (a workflow file, a store's schema) carry a list of
:class:`Problem` and render all of them, so a user fixes everything in one pass.
"""

from __future__ import annotations

import errno
import os
from dataclasses import dataclass


@dataclass(frozen=True)
class Problem:
    """One thing wrong, with where it is and how to mend it.

    ``where`` is a human location (``workflow.yaml:12``, a store path); ``path`` a location inside it
    (``steps[2].with.n_theta``, ``variable target``); ``fix`` a hint, may be empty.
    """

    message: str
    where: str = ""
    path: str = ""
    fix: str = ""

    def __str__(self) -> str:
        head = ": ".join(part for part in (self.where, self.path) if part)
        text = f"{head}: {self.message}" if head else self.message
        return f"{text} (fix: {self.fix})" if self.fix else text


class SelpathError(Exception):
    """Base of every error selpath raises on purpose."""


class _ProblemsError(SelpathError):
    """An error made of one or more problems, all listed in the message."""

    title = "problems"

    def __init__(self, problems: list[Problem] | Problem | str):
        if isinstance(problems, str):
            problems = [Problem(problems)]
        elif isinstance(problems, Problem):
            problems = [problems]
        self.problems: list[Problem] = list(problems)
        super().__init__(self._render())

    def _render(self) -> str:
        if len(self.problems) == 1:
            return str(self.problems[0])
        lines = [f"{len(self.problems)} {self.title}:"]
        lines += [f"  - {p}" for p in self.problems]
        return "\n".join(lines)


class SpecError(_ProblemsError):
    """A workflow file is invalid: unknown stage, bad parameter, dangling reference, cycle, ..."""

    title = "problems in the workflow"


class ConfigError(SpecError):
    """A YAML file other than a workflow (a scene, a rig) is invalid."""

    title = "problems in the file"


class StoreError(_ProblemsError):
    """A store is missing, corrupt, of a newer format, or breaks the schema of its cube kind."""

    title = "problems in the store"


class StageError(_ProblemsError):
    """A stage got inputs it cannot work on (wrong dims, missing variables, ...)."""

    title = "problems with a stage's inputs"


class EnvironmentFault(_ProblemsError):
    """This machine refused what selpath asked of it: a folder it may not write, a name too long for the file
    system, a full disk, a dask scheduler that does not answer. Not a bug: the message says what to change."""

    title = "problems with this machine"


#: errno → (what happened, the fix) for the faults of the environment a user can mend
_FAULTS = {
    errno.EACCES: ("permission denied", "use a folder you may write to (the workflow's output `store:` paths, or "
                   "`selpath demo --out`), or change the folder's permissions"),
    errno.EPERM: ("operation not permitted", "write to a folder you own, or change its permissions"),
    errno.EROFS: ("the file system is read-only", "write the outputs to a writable disk"),
    errno.ENAMETOOLONG: ("a file name is too long for the file system", "shorten the store's name or path (most file "
                         "systems take 255 bytes a name; selpath adds up to 30 for its lock and staging files)"),
    errno.ENOSPC: ("no space left on the device", "free space or write elsewhere; every finished output and "
                   "captured frame is kept, so running again resumes"),
    errno.EDQUOT: ("the disk quota is exceeded", "free space or write elsewhere; running again resumes"),
    errno.EMFILE: ("too many open files", "raise the limit (ulimit -n) or use fewer dask workers"),
}


def environment_fault(exc: BaseException, doing: str = "") -> EnvironmentFault | None:
    """The :class:`EnvironmentFault` an OSError of the environment stands for (naming the file and the fix), or None
    for any other error (a bug, to be reported as one). ``doing``: what selpath was doing, for the message."""
    while exc is not None and not (isinstance(exc, OSError) and exc.errno in _FAULTS):
        exc = exc.__cause__ or exc.__context__  # an OSError wrapped by a library (dask, zarr, fsspec)
    if exc is None:
        return None
    what, fix = _FAULTS[exc.errno]
    where = os.fsdecode(exc.filename) if exc.filename is not None else ""
    if exc.errno == errno.ENAMETOOLONG and where:
        what += f" (its last part has {len(os.fsencode(os.path.basename(where)))} bytes)"
    return EnvironmentFault(Problem(what + (f" while {doing}" if doing else ""), where=where, fix=fix))


class DeviceError(SelpathError):
    """An instrument timed out, answered garbage or went away; names port, command and reply.

    ``port``, ``command`` and ``reply`` are kept as attributes so callers (and tests) can act on them.
    """

    def __init__(self, message: str, *, port: str = "", command: str = "", reply: str | bytes | None = None,
                 fix: str = ""):
        self.message, self.port, self.command, self.reply, self.fix = message, port, command, reply, fix
        parts = [f"port {port}" if port else "", f"command {command!r}" if command else ""]
        head = ", ".join(p for p in parts if p)
        text = f"{head}: {message}" if head else message
        if reply is not None:
            text += f" (reply {reply!r})"
        if fix:
            text += f" (fix: {fix})"
        super().__init__(text)


class DeviceTimeout(DeviceError):
    """No (complete) reply arrived in time."""


class DeviceProtocolError(DeviceError):
    """A reply arrived but is garbled, fails its checksum, or is an error from the firmware."""


class DeviceDisconnected(DeviceError):
    """The port went away (cable pulled, device reset, port closed)."""
