"""Ctrl-C while ``hybrid-pk`` starts: one line and exit code 130, whatever is importing.

Importing torch, numpy and every command takes seconds on a loaded machine. An
interrupt raised as ``KeyboardInterrupt`` inside that import can be caught by the
library being imported: numpy's lazy ``__getattr__`` then recursed until a
``RecursionError`` (seen in CI, 3 of 60 interrupts on 2 loaded cores). So while the
command line starts, SIGINT does not raise at all: :func:`guard` installs a handler that
writes the line and leaves the process at once (nothing has been written yet, so
nothing is lost); :func:`release` hands SIGINT back to Python once the commands are
imported, and the commands' own ``KeyboardInterrupt`` handling takes over. Importing this
module guards (``hybrid_pk/__init__`` imports it first).

Only the ``hybrid-pk`` command is guarded: a script or a notebook importing
``hybrid_pk`` keeps its own interrupt.

While a command runs, SIGTERM (``kill``, a scheduler stopping a job) is raised as
:class:`Terminated` (:func:`terminable`), a ``KeyboardInterrupt``: the output being
written is removed and the file it would replace kept, as on Ctrl-C (the default
SIGTERM ended the process at once and left the temporary file beside it).
"""

from __future__ import annotations

import os
import signal
import sys
import threading
from collections.abc import Iterator
from contextlib import contextmanager

__all__ = ["LINE", "Terminated", "guard", "is_command", "release", "terminable"]

LINE = b"hybrid-pk: interrupted while starting\n"
EXIT_INTERRUPTED = 130  # 128 + SIGINT, as a shell reports an interrupted command
EXIT_TERMINATED = 143  # 128 + SIGTERM


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the command as Ctrl-C is: every ``finally`` runs."""


def is_command() -> bool:
    """Whether this process is the ``hybrid-pk`` command (its entry-point script)."""
    return bool(sys.argv) and os.path.basename(sys.argv[0]).startswith("hybrid-pk")


def _leave(signum, frame) -> None:
    os.write(2, LINE)
    os._exit(EXIT_INTERRUPTED)


def guard() -> None:
    """While the command starts, Ctrl-C leaves at once with :data:`LINE`."""
    if is_command() and signal.getsignal(signal.SIGINT) is signal.default_int_handler:
        signal.signal(signal.SIGINT, _leave)


def release() -> None:
    """Ctrl-C raises ``KeyboardInterrupt`` again (the commands handle it)."""
    if signal.getsignal(signal.SIGINT) is _leave:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _terminate(signum, frame) -> None:
    raise Terminated()


@contextmanager
def terminable() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` inside the block (main thread only: a signal
    handler can be set nowhere else); the previous handler is restored after it."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


guard()  # on import: the package imports this module before anything slow
