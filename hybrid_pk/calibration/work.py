"""Work of a fit, counted rather than timed: the unit of the diagnosis budget.

The unit is one evaluation of the model at one measured row: a residual row counts 1,
a Jacobian row ``1 + k`` for its ``k`` columns (forward mode pushes one direction per
column through the same evaluation). Counted by :class:`~.problem.Problem`, per thread
(two diagnoses in two threads of one process count apart), so the same campaign gives
the same count on an idle or a loaded machine.
"""

from __future__ import annotations

import threading

__all__ = ["count", "done"]

_local = threading.local()


def count(rows: int, columns: int = 0) -> None:
    """Add ``rows`` row evaluations with ``columns`` Jacobian columns each."""
    _local.n = getattr(_local, "n", 0) + rows * (1 + columns)


def done() -> int:
    """Row evaluations this thread has counted so far (only differences mean anything)."""
    return getattr(_local, "n", 0)
