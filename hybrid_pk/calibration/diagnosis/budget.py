"""Bounded worst cases: the optional stages of a diagnosis share a work budget.

The main search (frames, forward selection with elimination, each cause's gain) is the
diagnosis; the stages after it that only add a finding (the swaps for fewer causes, the
swaps of a named group for the one cause it stands in for, the search for a structural
error, the check of a search that stopped at its limit) get,
together, a share (the tuning's ``optional_share``) of the main search's work. Work is
counted, not timed (:mod:`hybrid_pk.calibration.work`: model evaluations of one row, a
Jacobian row weighing one per column): the same campaign is cut at the same step on an
idle or a loaded machine, and the budget still scales with the campaign as the main
search does. A stage that the budget cuts short says what it left undone
(:meth:`Budget.cut`), and the diagnosis reports it (``budget`` in its JSON, with the
work and the wall time of each stage).

Every stage does its first unit of work whatever the budget (the structural search
fits the joints named by implausible causes from the plain start), so that a cut
leaves the most likely answer in place. A unit is one step that stands alone, as small
as the stage allows: the swaps and the group swaps try one cause in place of another
per unit (a refit and its backward elimination; :meth:`Budget.allows`), an exchange is
one cause taken out and the search's two choices in its place with what follows them.
What a stage's first unit may cost beyond the budget is then one such step, not all the
swaps of its first cause.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager

from hybrid_pk.calibration.tuning import diagnosis_tuning
from hybrid_pk.calibration.work import done as work_done

__all__ = ["WORK_UNIT", "Budget"]

WORK_UNIT = "row evaluations (a residual row 1, a Jacobian row 1 + its columns)"


class Budget:
    """Work budget of the optional stages, started when the main search is."""

    def __init__(self, share: float | None = None) -> None:
        self.share = diagnosis_tuning().optional_share if share is None else share
        self.start, self.start_s = work_done(), time.perf_counter()
        self.main: int | None = None
        self.main_s: float | None = None
        self.cuts: list[dict] = []
        self._stages: dict[str, list] = {}  # name -> [work, seconds]
        self._current: tuple[int, float] | None = None  # the optional stage under way
        self._units: dict[str, int] = {}  # units of work done by stage (:meth:`allows`)

    @contextmanager
    def aside(self) -> Iterator[None]:
        """Work done inside counts neither as the main search's nor as an optional
        stage's: the checks of the data (set-ups, conventions), which only work where
        they are about to refuse the rows, would otherwise widen the optional stages'
        budget on exactly the campaigns they let through."""
        work, seconds = work_done(), time.perf_counter()
        try:
            yield
        finally:
            self.start += work_done() - work
            self.start_s += time.perf_counter() - seconds

    def main_done(self) -> None:
        """The main search ends here: the optional stages' budget is fixed from now."""
        if self.main is None:
            self.main = work_done() - self.start
            self.main_s = time.perf_counter() - self.start_s

    @property
    def allowed(self) -> float:
        """The optional stages' budget [row evaluations] (of the main search so far,
        if not done yet)."""
        main = self.main if self.main is not None else work_done() - self.start
        return self.share * main

    def used(self) -> int:
        """Work of the optional stages so far, the one under way included."""
        used = sum(w for w, _ in self._stages.values())
        if self._current is not None:
            used += work_done() - self._current[0]
        return used

    def spent(self, next_work: float = 0.0) -> bool:
        """True when the optional stages together used up the budget, or would with
        a next step of ``next_work`` (e.g. the largest such step so far)."""
        return self.used() + next_work >= self.allowed

    def allows(self, stage: str, left: list[str]) -> bool:
        """Whether ``stage`` does its next unit of work: the first whatever the budget,
        each later one while the budget lasts. Where it does not, the cut is recorded
        (:meth:`cut`; ``left``: what stays undone, this unit first) and every later
        call for ``stage`` says no as well."""
        if self.stopped(stage):
            return False
        if self._units.get(stage, 0) and self.spent():
            self.cut(stage, left)
            return False
        self._units[stage] = self._units.get(stage, 0) + 1
        return True

    def stopped(self, stage: str) -> bool:
        """Whether the budget cut ``stage`` short."""
        return any(c["stage"] == stage for c in self.cuts)

    def stage(self, name: str) -> _Stage:
        """Context manager counting optional stage ``name`` against the budget."""
        return _Stage(self, name)

    def cut(self, stage: str, left: list[str]) -> None:
        """Record that ``stage`` stopped on the budget, leaving ``left`` undone."""
        self.cuts.append({"stage": stage, "not_done": list(left)})

    def warnings(self) -> list[dict]:
        """A diagnosis warning (``{"cause", "why"}``) per stage the budget cut short."""
        return [
            {
                "cause": c["stage"],
                "why": f"stopped on its work budget ({self.allowed:.3g} row evaluations, "
                f"{100 * self.share:g} % of the main search's {self.main or 0:.3g}) "
                f"before: {', '.join(c['not_done']) or 'its last step'}",
            }
            for c in self.cuts
        ]

    def to_json(self) -> dict:
        """``{"unit", "main_search", "optional", "share", "stages", "seconds",
        "cut_short"}``: work in ``unit``, wall times in ``seconds``."""
        seconds = {"main search": round(self.main_s or 0.0, 3)}
        return {
            "unit": WORK_UNIT,
            "main_search": self.main,
            "optional": self.allowed,
            "share": self.share,
            "stages": {k: w for k, (w, _) in self._stages.items()},
            "seconds": seconds | {k: round(s, 3) for k, (_, s) in self._stages.items()},
            "cut_short": self.cuts,
        }


class _Stage:
    def __init__(self, budget: Budget, name: str) -> None:
        self.budget, self.name = budget, name

    def __enter__(self) -> Budget:
        self.budget._current = (work_done(), time.perf_counter())
        return self.budget

    def __exit__(self, *exc) -> None:
        b = self.budget
        w0, t0 = b._current
        entry = b._stages.setdefault(self.name, [0, 0.0])
        entry[0] += work_done() - w0
        entry[1] += time.perf_counter() - t0
        b._current = None
