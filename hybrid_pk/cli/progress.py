"""Progress of a long command on stderr: named stages, the inner step of each, elapsed time.

On a terminal: one tqdm status line (stage k of n when the count is known, the stage,
its elapsed seconds, its current inner step, the total elapsed time), redrawn twice a
second so the clocks move during a long fit. Elsewhere (logs, pipes, tests): one line
per stage and per inner step, ``name [  12.3 s] stage | step``, so a log shows when
each step started (``bench/demo.py`` measures the longest gap between such lines).

Lines of the first ``delay`` seconds are not printed: a quick command leaves only its
summary. Off a terminal, inner steps are printed at most once a second: a step that
comes sooner is printed a second after the previous line, with the time it came, unless
a newer one replaced it by then (every stage start is printed at once).

``--no-progress`` (every command) turns off every bar its command opens: ``main`` runs
the command inside :func:`shown` ``(False)``.
"""

from __future__ import annotations

import shutil
import sys
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import TextIO

__all__ = ["Progress", "progress", "shown"]

_SHOWN = [True]  # what a bar opened without ``enabled`` does; set by :func:`shown`


@contextmanager
def shown(on: bool) -> Iterator[None]:
    """Within the block, bars opened without ``enabled`` show (``on``) or not."""
    before = _SHOWN[0]
    _SHOWN[0] = on
    try:
        yield
    finally:
        _SHOWN[0] = before


class Progress:
    """Stages and inner steps of one command.

    Args:
        name: command name, first on every line (``demo``, ``calibrate``).
        total: number of stages, if known.
        stream: where to write (default: ``sys.stderr`` at construction).
        delay: seconds before anything is shown.
        enabled: False: nothing is shown (the stage times are still kept); default:
            shown unless inside ``shown(False)``.

    Attributes:
        seconds: wall time per finished stage [s], in order.
    """

    def __init__(
        self,
        name: str,
        total: int | None = None,
        *,
        stream: TextIO | None = None,
        delay: float = 0.5,
        enabled: bool | None = None,
    ) -> None:
        enabled = _SHOWN[0] if enabled is None else enabled
        self.name, self.total, self.delay, self.enabled = name, total, delay, enabled
        self.stream = sys.stderr if stream is None else stream
        self.start = time.monotonic()
        self.seconds: dict[str, float] = {}
        self.stage_name: str | None = None
        self.step_text: str | None = None
        self.count = 0
        self._stage_start = self.start
        self._last_line = -1.0
        self._pending: tuple[float, str] | None = None  # (time, line) to print
        self._lock = threading.Lock()
        self._bar = None
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if enabled and getattr(self.stream, "isatty", lambda: False)():
            self._start_bar()
        if enabled:
            self._thread = threading.Thread(target=self._tick, daemon=True)
            self._thread.start()

    def _start_bar(self) -> None:
        from tqdm import tqdm

        # Some terminals report a 0 x 0 size, on which tqdm would draw nothing.
        width, height = shutil.get_terminal_size((100, 24))
        count = "{n_fmt}/{total_fmt} " if self.total else ""
        self._bar = tqdm(
            total=self.total,
            file=self.stream,
            ncols=width if width >= 40 else 100,
            nrows=height if height >= 2 else 24,
            bar_format=f"{self.name}: {count}{{desc}} [{{elapsed}}]",
            delay=self.delay,
            leave=False,  # the summary says how long it took
        )

    def _tick(self) -> None:
        while not self._stop.wait(0.25):
            if self._bar is not None:
                self._redraw()
            else:
                self._flush(force=False)

    def _redraw(self) -> None:
        if self._bar is None or self.stage_name is None:
            return
        text = f"{self.stage_name} ({time.monotonic() - self._stage_start:.0f} s)"
        if self.step_text:
            text += f" | {self.step_text}"
        self._bar.set_description_str(text, refresh=True)

    def elapsed(self) -> float:
        """Seconds since the start."""
        return time.monotonic() - self.start

    def stage(self, text: str) -> None:
        """Start the next stage (the previous one's time goes to :attr:`seconds`)."""
        self._end_stage()
        self.stage_name, self.step_text = text, None
        self.count += 1
        if self._bar is not None:
            self._bar.update(1)
        self._show()

    def __call__(self, text: str) -> None:
        """Show ``text`` as the current stage's inner step (a stage if none is open)."""
        if self.stage_name is None:
            self.stage(text)
            return
        self.step_text = text
        self._show()

    def report(self, stage: str, step: str | None = None) -> None:
        """Callback of the library pipelines: ``stage`` (a new one when its name changes)
        and optionally its inner ``step``."""
        if stage != self.stage_name:
            self.stage(stage)
        if step:
            self(step)

    def _show(self) -> None:
        if not self.enabled:
            return
        if self._bar is not None:
            self._redraw()
            return
        now = self.elapsed()
        if now < self.delay:
            return
        count = f"{self.count}/{self.total} " if self.total else ""
        line = f"{self.name} [{now:6.1f} s] {count}{self.stage_name}"
        if self.step_text:
            line += f" | {self.step_text}"
        with self._lock:
            self._pending = (now, line)
        self._flush(force=not self.step_text)

    def _flush(self, force: bool) -> None:
        """Print the pending line if it is a stage start (``force``) or the last line is
        a second old."""
        with self._lock:
            if self._pending is None:
                return
            if not force and self.elapsed() - self._last_line < 1.0:
                return
            _, line = self._pending
            self._pending = None
            self._last_line = self.elapsed()
            print(line, file=self.stream, flush=True)

    def _end_stage(self) -> None:
        if self.stage_name is not None:
            now = time.monotonic()
            self.seconds[self.stage_name] = now - self._stage_start
            self._stage_start = now

    def close(self) -> None:
        """Stop the clock, record the last stage's time, remove the bar."""
        self._end_stage()
        self.stage_name = None
        self._stop.set()
        if self._thread is not None:
            self._thread.join()
        self._flush(force=True)
        if self._bar is not None:
            self._bar.close()


@contextmanager
def progress(
    name: str, total: int | None = None, *, delay: float = 0.5, enabled: bool | None = None
) -> Iterator[Progress]:
    """A :class:`Progress` closed when the block ends (also on an error)."""
    bar = Progress(name, total, delay=delay, enabled=enabled)
    try:
        yield bar
    finally:
        bar.close()
