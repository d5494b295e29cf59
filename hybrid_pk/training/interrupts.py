"""Ctrl-C during a training is never lost, and leaves Ctrl-C working after it.

Python raises SIGINT as ``KeyboardInterrupt`` wherever the main thread happens to be.
Inside a ``__del__`` or a weakref callback (a progress bar or a log writer closed at an
epoch's end) the exception is printed as "Exception ignored in ..." and dropped: the
training then ran on to its last epoch and the command ended with exit code 0, as if
never interrupted (seen once in CI, in the test that interrupts ``hybrid-pk train``
right after an epoch's line). So while a fit runs, :class:`InterruptLatch` takes SIGINT
(where Python's own handler had it): it notes the interrupt and raises it, and, as a
Lightning callback, raises it again at the next batch's or epoch's end if it was
dropped. SIGTERM needs no latch: Lightning notes it (``trainer.received_sigterm``) and
raises at the next batch itself.

Lightning's answer to an interrupt ignores SIGINT from then on (against a second
Ctrl-C during its clean-up) and never restores it: in a notebook or a script that
goes on after the interrupted training, Ctrl-C did nothing any more. The latch puts
back the handler that was in place before the fit.
"""

from __future__ import annotations

import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

from lightning.pytorch.callbacks import Callback

__all__ = ["InterruptLatch"]


class InterruptLatch(Callback):
    """SIGINT noted as well as raised while :meth:`armed`; raised again by
    :meth:`check` (every batch's and epoch's end) if it was dropped."""

    def __init__(self) -> None:
        self.pressed = False

    def _handler(self, signum, frame) -> None:
        self.pressed = True
        raise KeyboardInterrupt

    @contextmanager
    def armed(self) -> Iterator[InterruptLatch]:
        """Take SIGINT in the block (where Python's own handler has it: a process that
        ignores SIGINT, e.g. a background job, keeps ignoring it) and restore the handler
        found before it afterwards. Off the main thread (no handler can be set there)
        nothing is changed."""
        if threading.current_thread() is not threading.main_thread():
            yield self
            return
        previous = signal.getsignal(signal.SIGINT)
        if previous is signal.default_int_handler:
            signal.signal(signal.SIGINT, self._handler)
        try:
            yield self
        finally:
            signal.signal(signal.SIGINT, previous)

    def check(self) -> None:
        """Raise the interrupt noted, if any (it was dropped where it was raised)."""
        if self.pressed:
            raise KeyboardInterrupt

    def on_train_batch_end(self, *args, **kwargs) -> None:
        self.check()

    def on_validation_batch_end(self, *args, **kwargs) -> None:
        self.check()

    def on_train_epoch_end(self, *args, **kwargs) -> None:
        self.check()
