"""Progress of long work: a live bar on a terminal, a few plain lines in a log.

On a terminal `progress_bar` is tqdm's bar. Where stderr is a file or a pipe (a batch job's
log, `2> run.log`), a `\\r` update per chunk would write hundreds of updates into one line of
the log, so `LogProgress` writes a line at every tenth of the work and otherwise at most one
a minute, and one at the end.
"""

from __future__ import annotations

import sys
import time
from collections.abc import Iterable

# a log line at every tenth of the work, and at least this often while a tenth takes longer
LOG_FRACTION_STEP = 0.1
LOG_HEARTBEAT_S = 60.0
LOG_INTERVAL_WITHOUT_TOTAL_S = 10.0


class LogProgress:
    """tqdm's interface as the package uses it (update, iteration, a context manager),
    writing plain lines: `desc: 40% (32768/81920 px), 3.1 s elapsed, ~4.7 s left`."""

    def __init__(
        self,
        iterable: Iterable | None = None,
        total: float | None = None,
        desc: str = "",
        unit: str = "it",
        initial: float = 0,
        disable: bool = False,
        file=None,
        **_ignored,
    ):
        self.iterable = iterable
        if total is None and iterable is not None and hasattr(iterable, "__len__"):
            total = len(iterable)
        self.total, self.desc, self.unit, self.n = total, desc, unit, initial
        self.disable = disable
        self.file = file
        self.start = self.last_line = time.monotonic()
        self.next_fraction = self._next_fraction(initial)
        self.closed = False

    def _next_fraction(self, n: float) -> float:
        if not self.total:
            return float("inf")
        done = n / self.total
        return (int(done / LOG_FRACTION_STEP + 1e-9) + 1) * LOG_FRACTION_STEP

    def _line(self, now: float) -> str:
        elapsed = now - self.start
        if not self.total:
            return f"{self.desc}: {self.n:g} {self.unit}, {elapsed:.1f} s elapsed"
        done = self.n / self.total
        left = f", ~{elapsed * (1 - done) / done:.1f} s left" if 0 < done < 1 else ""
        return f"{self.desc}: {100 * done:.0f}% ({self.n:g}/{self.total:g} {self.unit}), {elapsed:.1f} s elapsed{left}"

    def _write(self, now: float):
        print(self._line(now), file=self.file or sys.stderr, flush=True)
        self.last_line = now

    def update(self, n: float = 1):
        self.n += n
        if self.disable:
            return
        now = time.monotonic()
        interval = LOG_HEARTBEAT_S if self.total else LOG_INTERVAL_WITHOUT_TOTAL_S
        if self.total and self.n / self.total >= self.next_fraction - 1e-9:
            self.next_fraction = self._next_fraction(self.n)
            self._write(now)
        elif now - self.last_line >= interval:
            self._write(now)

    def close(self):
        if self.closed:
            return
        self.closed = True
        # the end, unless the last tenth's line said it already
        if not self.disable and not (self.total and self.n >= self.total and self.last_line > self.start):
            self._write(time.monotonic())

    def __iter__(self):
        try:
            for item in self.iterable:
                yield item
                self.update(1)
        finally:
            self.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
        return False


def progress_bar(iterable: Iterable | None = None, **kwargs):
    """A tqdm bar where stderr is a terminal, `LogProgress` lines where it is not. Takes
    tqdm's keywords (total, desc, unit, initial, disable, unit_scale, …)."""
    if sys.stderr.isatty():
        from tqdm.auto import tqdm

        return tqdm(iterable, **kwargs)
    return LogProgress(iterable, **kwargs)
