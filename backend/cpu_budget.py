"""CPU budgets of the no-ids final solves: stop cleanly, keep what is finished (issue 15).

A final solve (:func:`lampsam.backend.online_final.final_solve`: the re-association
passes, their duplicate merges, the description-length moves, the final pass, the
placement of the left-out sightings) can take far longer on one log than on the others
(a grid of pillars whose sighting noise is understated 2x: more than 30 min of CPU in
the duplicate merges). A :class:`CpuBudget` is handed down the stages; each stage asks
it between its units of work (a re-association pass, a block of merge pairs, a stage)
and, once it is spent, stops and keeps the last state it had accepted. The stage that
stopped first is recorded (:attr:`CpuBudget.stopped`) and logged once, as a warning
naming the stage and the budget: never a silent cut.

Units: process CPU seconds (:func:`time.process_time`), so a loaded machine does not
stop a run early.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import math
import signal
import threading
import time
from collections.abc import Iterator

from lampsam.errors import LampsamError

log = logging.getLogger(__name__)


class BudgetSpent(LampsamError):
    """Raised inside a stage whose :class:`CpuBudget` is spent (:meth:`CpuBudget.check`);
    the stage's caller catches it and keeps its last accepted state."""


@dataclasses.dataclass
class CpuBudget:
    """A CPU budget of one job, shared by its stages.

    Attributes:
        limit_s: process CPU seconds allowed from ``c0`` (inf: no budget).
        what: the budget's name for the warning (e.g. ``"[reassociation]
            final_solve_cpu_per_sighting"`` with its value).
        c0: :func:`time.process_time` at the start.
        stopped: the stage that found the budget spent first ("" while not spent).
    """

    limit_s: float
    what: str = "the CPU budget"
    c0: float = dataclasses.field(default_factory=time.process_time)
    stopped: str = ""

    def used(self) -> float:
        """Process CPU seconds since ``c0``."""
        return time.process_time() - self.c0

    def spent(self, stage: str) -> bool:
        """Whether the budget is spent; the first time it is, ``stage`` is recorded as the
        one that stopped and a warning names it and the budget."""
        if self.stopped:
            return True
        if not math.isfinite(self.limit_s) or self.used() <= self.limit_s:
            return False
        self.stopped = stage
        log.warning("%s stopped by its CPU budget (%.1f s, %s) after %.1f s of CPU: the "
                    "answer is the last one it finished", stage, self.limit_s, self.what,
                    self.used())
        return True

    def check(self, stage: str) -> None:
        """Raise :class:`BudgetSpent` when :meth:`spent`."""
        if self.spent(stage):
            raise BudgetSpent(f"{stage}: stopped by its CPU budget ({self.limit_s:.1f} s, "
                              f"{self.what})")


@contextlib.contextmanager
def interrupt_past(budget: CpuBudget | None, stage: str) -> Iterator[None]:
    """Inside: :class:`BudgetSpent` is raised at the first Python bytecode after
    ``budget`` is spent (a process-CPU timer, ``ITIMER_PROF``), for stages that have no
    look at the budget of their own (GTSAM's calls finish first). The caller catches it
    and keeps the state before the stage. Outside the main thread, or with no finite
    budget, nothing is armed (the stage runs to its end); a budget already spent raises
    at once."""
    if budget is None or not math.isfinite(budget.limit_s):
        yield
        return
    budget.check(stage)
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def fire(_sig: int, _frame: object) -> None:
        signal.setitimer(signal.ITIMER_PROF, 0.0)
        budget.spent(stage)  # records the stage and warns (the timer and process_time agree)
        budget.stopped = budget.stopped or stage
        raise BudgetSpent(f"{stage}: stopped by its CPU budget ({budget.limit_s:.1f} s, "
                          f"{budget.what})")

    old = signal.signal(signal.SIGPROF, fire)
    signal.setitimer(signal.ITIMER_PROF, max(budget.limit_s - budget.used(), 1e-3))
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_PROF, 0.0)
        signal.signal(signal.SIGPROF, old)


def sighting_budget(per_sighting_s: float, n_sightings: int, floor_s: float) -> float:
    """A budget from the log's size: ``max(per_sighting_s * n_sightings, floor_s)`` CPU
    seconds (inf when ``per_sighting_s`` is inf)."""
    if not math.isfinite(per_sighting_s):
        return math.inf
    return max(per_sighting_s * n_sightings, floor_s)


def unlimited() -> CpuBudget:
    """A budget that is never spent."""
    return CpuBudget(math.inf, "none")
