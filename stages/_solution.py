"""What every solver returns (DESIGN §6, STYLE 5): a value, a result code per item and statistics.

Modelled on optimistix's ``Solution(value, result, stats)`` and its ``RESULTS`` enumeration: a solve that
did not converge is data, not an exception, unless the solver was built with ``throw=True``; then
:func:`raise_if_failed` names the codes and how many items (slices, pixels) ended with each.

Used by both instruments' solvers (:class:`selpath.stages.tomography._admm.TVADMM`,
:class:`selpath.stages.procam._demux_solver.DemuxADMM`); it imports neither.
"""

from __future__ import annotations

import enum
from typing import Any, NamedTuple

import numpy as np

from selpath.pipeline.errors import Problem, SelpathError


class Result(enum.IntEnum):
    """How one item's solve ended (stored as ``int8`` codes in :attr:`Solution.result`)."""

    converged = 0  # the stopping test (residuals within tol) was met
    max_steps = 1  # stopped at the iteration cap before meeting tol
    nonfinite = 2  # the value is not finite (NaN or ±inf): the solve broke down
    censored = 3  # the stopping test was met, but part of the value is a lower bound (clipped observations)
    unproven = 4  # the value's certified error bound exceeds what a converged item may have (whatever the residuals)

    @property
    def message(self) -> str:
        return _MESSAGES[self]


_MESSAGES = {
    Result.converged: "converged: the residuals met the tolerance",
    Result.max_steps: "stopped at the iteration cap (max_iter) before meeting the tolerance",
    Result.nonfinite: "the value is not finite (NaN or inf)",
    Result.censored: "met the tolerance, but part of the value is only a lower bound: it was seen only in clipped "
                     "(saturated) observations",
    Result.unproven: "its certified error bound (e.g. the objective-gap bound) is above the largest a converged item "
                     "may have (e.g. max_gap), whether or not it reached the iteration cap",
}


def outcome(converged, finite, xp=np):
    """Result codes (int8) from the stopping test and a finiteness check: ``converged`` where the test was met,
    else ``nonfinite`` where the value is not finite, else ``max_steps``. ``xp``: numpy, or ``jax.numpy`` inside
    a jitted solve."""
    codes = xp.where(converged, int(Result.converged), xp.where(finite, int(Result.max_steps), int(Result.nonfinite)))
    return codes.astype(xp.int8)


class Solution(NamedTuple):
    """A solver's answer: ``value``, ``result`` (a :class:`Result` code, one per item of a batched solve)
    and ``stats`` (named arrays: iterations, objective, residuals …, one leading item axis where batched).

    A NamedTuple, so a pytree: it passes through ``jax.jit`` and ``jax.vmap`` as it is.
    """

    value: Any
    result: Any
    stats: dict[str, Any]

    @property
    def converged(self):
        """Per item: True where the result is :attr:`Result.converged`."""
        return self.result == int(Result.converged)


class SolverError(SelpathError):
    """A solver built with ``throw=True`` finished with items that did not converge.

    ``counts`` maps each failing :class:`Result` to its number of items; ``total`` is the number of items.
    """

    def __init__(self, problem: Problem, counts: dict[Result, int], total: int):
        self.problem, self.counts, self.total = problem, counts, total
        super().__init__(str(problem))


def raise_if_failed(solution: Solution, solver: str, *, items: str = "items", fix: str = "") -> None:
    """Raise :class:`SolverError` if any item of ``solution`` did not end converged (host side, after the solve)."""
    codes = np.atleast_1d(np.asarray(solution.result))
    counts = {code: int(np.sum(codes == code)) for code in Result if code != Result.converged}
    counts = {code: n for code, n in counts.items() if n}
    if not counts:
        return
    failed = sum(counts.values())
    detail = "; ".join(f"{n} {code.name} ({code.message})" for code, n in counts.items())
    if not fix and set(counts) == {Result.censored}:
        fix = ("censored items are solved; their clipped part is a lower bound: lower the light (projector power, a "
               "filter) or the exposure and measure again, or build the solver with throw=False to keep them")
    raise SolverError(Problem(f"{solver}: {failed} of {codes.size} {items} did not end converged: {detail}",
                              fix=fix or "raise max_iter or loosen tol; or build the solver with throw=False "
                                         "to keep the unconverged items as data (their result codes say which)"),
                      counts, codes.size)
