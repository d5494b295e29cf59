"""How many threads torch uses, on a machine shared with other jobs.

The policy, in the order it is decided:

1. ``--threads N`` of any command, else the ``HYBRID_PK_THREADS`` environment variable
   (a count, at most the usable cores, or ``torch``: leave torch's own settings, the
   behaviour before the policy);
2. else the cores this process may use (:func:`usable_cores`: its CPU affinity and its
   cgroup's CPU quota), and no more than the work can use: one thread per
   ``ROWS_PER_THREAD`` rows of a batch (:func:`threads_for`), and one thread for the
   fits and the diagnosis (``FIT_THREADS``: :func:`fit_work`); never more than torch's
   setting when the call began (``OMP_NUM_THREADS=1`` or ``torch.set_num_threads(1)``
   keep one thread);
3. inter-op threads: one (nothing here forks torch work in parallel); numpy's and
   scipy's BLAS (their own OpenBLAS, which threads large products on every core and
   spins while it waits) get the same count as torch for the duration of a library
   call (:func:`work_threads`, through ``threadpoolctl``), and for the process from
   :func:`configure` where they are loaded by then;
4. OpenMP threads that wait for work sleep instead of spinning (``OMP_WAIT_POLICY=
   PASSIVE``, set by :func:`quiet_waiting` before torch loads OpenMP, unless the user
   set it): a spinning thread takes a core the other jobs need. Measured on 2 shared
   cores (load 4), a 1,000-row UR5 diagnosis with 2 threads took 72 s wall / 31 s CPU
   spinning and 28 s wall / 10 s CPU waiting passively (one thread: 20 s / 9 s).

The command line applies the policy once (:func:`configure`); the library entry points
of the fits (:func:`hybrid_pk.calibration.diagnose`, :func:`hybrid_pk.calibration.fit.fit`)
set their threads for the duration of the call (:func:`fit_work`) and restore the
caller's setting after.
"""

from __future__ import annotations

import functools
import math
import os
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

__all__ = [
    "ENV",
    "FIT_THREADS",
    "ROWS_PER_THREAD",
    "cgroup_quota",
    "configure",
    "fit_work",
    "parse_threads",
    "quiet_waiting",
    "requested_threads",
    "threads_for",
    "usable_cores",
    "work_threads",
]

ENV = "HYBRID_PK_THREADS"
# ATen runs an element-wise op on one thread below 32,768 elements (its GRAIN_SIZE);
# the batched kinematics hold a 4x4 pose (16 elements) per row, so below 2,048 rows per
# thread a second thread has no work of its own to take.
ROWS_PER_THREAD = 32_768 // 16
# The fits and the diagnosis are many small operations (per joint, per parameter block,
# per held-out block), none larger than one chunk of rows (calibration.problem), so
# their size does not grow with the campaign's. Measured on 2 cores (bench/threads.py),
# a second thread bought nothing (a fit of 13,406 / 50,000 rows 0.95x / 1.06x, the
# diagnosis of 13,406 rows 1.00x) and takes a core another job needs.
FIT_THREADS = 1
_TORCH = "torch"  # HYBRID_PK_THREADS=torch / --threads torch: torch's own setting
_state = {"explicit": None, "depth": 0}  # threads fixed by --threads / env; nesting


def quiet_waiting() -> None:
    """``OMP_WAIT_POLICY=PASSIVE`` unless the user chose a policy or ``torch``; takes
    effect only when called before torch is first imported (OpenMP reads it once)."""
    if os.environ.get(ENV, "").strip().lower() != _TORCH:
        os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


def cgroup_quota(root: Path = Path("/sys/fs/cgroup")) -> float | None:
    """CPUs the cgroup quota allows (cgroup v2 ``cpu.max``, v1 ``cfs_quota_us``)."""
    try:
        quota, period = (root / "cpu.max").read_text().split()[:2]
        return None if quota == "max" else int(quota) / int(period)
    except (OSError, ValueError):
        pass
    try:
        quota = int((root / "cpu" / "cpu.cfs_quota_us").read_text())
        period = int((root / "cpu" / "cpu.cfs_period_us").read_text())
        return None if quota <= 0 else quota / period
    except (OSError, ValueError):
        return None


def usable_cores() -> int:
    """Cores this process may run on: its CPU affinity, capped by the cgroup quota
    (a quota of 1.5 CPUs keeps 2 threads busy half the time: rounded up)."""
    try:
        cores = len(os.sched_getaffinity(0))
    except AttributeError:  # not Linux
        cores = os.cpu_count() or 1
    quota = cgroup_quota()
    if quota is not None:
        cores = min(cores, max(1, math.ceil(quota)))
    return max(1, cores)


def threads_for(rows: int | None) -> int:
    """Intra-op threads for work on ``rows`` measured rows: one per ``ROWS_PER_THREAD``
    rows, at least one, at most :func:`usable_cores` (all of them when ``rows`` is None)."""
    cores = usable_cores()
    if rows is None:
        return cores
    return max(1, min(cores, rows // ROWS_PER_THREAD))


def parse_threads(text: str | int | None) -> int | str | None:
    """``N`` (>= 1), ``torch`` or ``auto``/empty (None: the policy) from ``--threads`` or
    ``HYBRID_PK_THREADS``; ValueError with the accepted forms otherwise."""
    if text is None:
        return None
    word = str(text).strip().lower()
    if word in ("", "auto"):
        return None
    if word == _TORCH:
        return _TORCH
    n = int(word) if word.isdecimal() else 0
    if n < 1:
        raise ValueError(f"threads: expected a count >= 1, 'auto' or 'torch', got {text!r}")
    return n


def requested_threads() -> int | str | None:
    """What the user fixed: ``--threads`` (via :func:`configure`), else ``HYBRID_PK_THREADS``."""
    if _state["explicit"] is not None:
        return _at_most_cores(_state["explicit"])
    try:
        return _at_most_cores(parse_threads(os.environ.get(ENV)))
    except ValueError as exc:
        raise ValueError(f"{ENV}: {exc}") from None


def _at_most_cores(choice: int | str | None) -> int | str | None:
    """A count above :func:`usable_cores` cut to them: threads beyond the cores only
    take turns on them, each spinning or switching (the collapse this policy is for)."""
    return min(choice, usable_cores()) if isinstance(choice, int) else choice


def _set(n: int) -> None:
    import torch

    torch.set_num_threads(n)


def _blas_limits(n: int):
    """numpy's and scipy's BLAS libraries loaded so far held to ``n`` threads (a
    ``threadpoolctl`` limiter: a context manager, or in force until restored)."""
    from threadpoolctl import threadpool_limits

    return threadpool_limits(limits=n, user_api="blas")


def configure(threads: str | int | None = None) -> int | str:
    """Apply the policy for a whole process (the command line): ``threads`` as given
    to ``--threads`` (None: ``HYBRID_PK_THREADS``, else every usable core until a
    library call sizes them to its rows). Returns the count set, or ``"torch"``."""
    import torch

    _state["explicit"] = parse_threads(threads)
    choice = requested_threads()
    if choice == _TORCH:
        return _TORCH
    try:
        torch.set_num_interop_threads(1)
    except RuntimeError:  # already started (torch allows setting it once)
        pass
    # auto never raises torch's setting (OMP_NUM_THREADS=1 keeps one thread)
    n = choice if isinstance(choice, int) else min(threads_for(None), torch.get_num_threads())
    _set(n)
    _blas_limits(n)  # for the process; each library call sets its own again
    return n


@contextmanager
def work_threads(rows: int | None, at_most: int | None = None) -> Iterator[int]:
    """Intra-op threads for a library call on ``rows`` rows, restored after: the
    user's fixed count if any, else :func:`threads_for` ``(rows)`` but never more than
    ``at_most`` nor the caller's torch setting. Calls nested in one that already sized
    the threads keep its choice."""
    import torch

    previous = torch.get_num_threads()
    choice = requested_threads()
    if _state["depth"] or choice == _TORCH:
        yield previous
        return
    cap = previous if at_most is None else min(previous, at_most)
    n = choice if isinstance(choice, int) else min(threads_for(rows), cap)
    _state["depth"] += 1
    try:
        if n != previous:
            _set(n)
        with _blas_limits(n):  # restored after, as torch's
            yield n
    finally:
        _state["depth"] -= 1
        if torch.get_num_threads() != previous:
            _set(previous)


def fit_work(func: Callable) -> Callable:
    """Run ``func(x, data, ...)`` (a fit or the diagnosis) under :func:`work_threads`
    sized to ``data.n`` rows (``data`` its second argument or keyword) and at most
    ``FIT_THREADS``, unless the user fixed a count."""

    @functools.wraps(func)
    def wrapper(*args, **kwargs):
        data = args[1] if len(args) > 1 else kwargs.get("data")
        with work_threads(getattr(data, "n", None), at_most=FIT_THREADS):
            return func(*args, **kwargs)

    return wrapper


quiet_waiting()  # on import: the package imports this module before torch
