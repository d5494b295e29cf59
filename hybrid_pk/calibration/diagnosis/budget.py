"""Bounded worst cases: the optional stages of a diagnosis share a time budget.

The main search (frames, forward selection with elimination, each cause's gain) is
the diagnosis; the stages after it that only add a finding (the swaps for fewer
causes, the search for a structural error, the check of a search that stopped at
its limit) get, together, a share of the main search's wall time (the tuning's
``optional_share``). Measured
in the same process, the budget scales with the machine's speed and load as the
main search does. A stage that the budget cuts short says what it left undone
(:meth:`Budget.cut`), and the diagnosis reports it (``budget`` in its JSON).

Every stage does its first unit of work whatever the budget (the structural search
fits the joints named by implausible causes from the plain start), so that a cut
leaves the most likely answer in place.
"""

from __future__ import annotations

import time

from hybrid_pk.calibration.tuning import diagnosis_tuning

__all__ = ["Budget"]


class Budget:
    """Wall-time budget of the optional stages, started when the main search is."""

    def __init__(self, share: float | None = None) -> None:
        self.share = diagnosis_tuning().optional_share if share is None else share
        self.start = time.perf_counter()
        self.main_s: float | None = None
        self.cuts: list[dict] = []
        self._stages: dict[str, float] = {}
        self._current: float | None = None  # start of the optional stage under way

    def main_done(self) -> None:
        """The main search ends here: the optional stages' budget is fixed from now."""
        if self.main_s is None:
            self.main_s = time.perf_counter() - self.start

    @property
    def seconds(self) -> float:
        """The optional stages' budget [s] (the main search so far, if not done yet)."""
        main = self.main_s if self.main_s is not None else time.perf_counter() - self.start
        return self.share * main

    def spent(self, next_s: float = 0.0) -> bool:
        """True when the optional stages together used up the budget, or would with
        a next step of ``next_s`` seconds (e.g. the longest such step so far)."""
        used = next_s + sum(self._stages.values())
        if self._current is not None:
            used += time.perf_counter() - self._current
        return used >= self.seconds

    def stage(self, name: str) -> _Stage:
        """Context manager timing optional stage ``name`` against the budget."""
        return _Stage(self, name)

    def cut(self, stage: str, left: list[str]) -> None:
        """Record that ``stage`` stopped on the budget, leaving ``left`` undone."""
        self.cuts.append({"stage": stage, "not_done": list(left)})

    def warnings(self) -> list[dict]:
        """A diagnosis warning (``{"cause", "why"}``) per stage the budget cut short."""
        return [
            {
                "cause": c["stage"],
                "why": f"stopped on its time budget ({self.seconds:.3g} s, "
                f"{100 * self.share:g} % of the main search's {self.main_s or 0.0:.3g} s) "
                f"before: {', '.join(c['not_done']) or 'its last step'}",
            }
            for c in self.cuts
        ]

    def to_json(self) -> dict:
        """``{"main_search_s", "optional_s", "share", "stages", "cut_short"}``."""
        return {
            "main_search_s": self.main_s,
            "optional_s": self.seconds,
            "share": self.share,
            "stages": {k: round(v, 3) for k, v in self._stages.items()},
            "cut_short": self.cuts,
        }


class _Stage:
    def __init__(self, budget: Budget, name: str) -> None:
        self.budget, self.name = budget, name

    def __enter__(self) -> Budget:
        self.budget._current = time.perf_counter()
        return self.budget

    def __exit__(self, *exc) -> None:
        b = self.budget
        b._stages[self.name] = b._stages.get(self.name, 0.0) + time.perf_counter() - b._current
        b._current = None
