"""The project's exceptions: one small hierarchy, every message saying what, where and how to mend it.

Errors that can have several causes at once (a workflow file, a store's schema) carry a list of
:class:`Problem` and render all of them, so a user fixes everything in one pass.
"""

from __future__ import annotations

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


class StoreError(_ProblemsError):
    """A store is missing, corrupt, of a newer format, or breaks the schema of its cube kind."""

    title = "problems in the store"


class StageError(_ProblemsError):
    """A stage got inputs it cannot work on (wrong dims, missing variables, ...)."""

    title = "problems with a stage's inputs"


class DeviceError(SelpathError):
    """An instrument timed out, answered garbage or went away; names port, command and reply."""
