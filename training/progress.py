"""How far a long loop (imitation's env steps, an evaluation's episodes) has come, and how long it
has left.

On a terminal it is a tqdm bar with its time estimate. A run that writes a log instead
(``progress_bar = false``: a background run) gets the same figures as a log line every
``interval`` seconds, so neither kind of run is silent for minutes.
"""

from __future__ import annotations

import logging
import math
import sys
import time
from collections.abc import Callable
from typing import TextIO

from tqdm import tqdm

log = logging.getLogger(__name__)


class Progress:
    """Counts ``total`` units of work done; use as a context manager.

    :param total: units in all (env steps, episodes)
    :param what: what is counted, for the bar's label and the log line ("dagger steps")
    :param unit: one of them, for the bar's rate ("step")
    :param bar: a tqdm bar on ``file``; False: a log line every ``interval`` seconds
    :param file: where the bar goes (default: stderr)
    :param interval: seconds between log lines (bar off)
    :param clock: the time source, seconds
    """

    def __init__(
        self,
        total: int,
        what: str,
        unit: str,
        bar: bool = True,
        file: TextIO | None = None,
        interval: float = 30.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.total = total
        self.what = what
        self.done = 0
        self._clock = clock
        self._start = self._last_log = clock()
        self._interval = interval
        self._bar = (
            tqdm(total=total, desc=what, unit=unit, file=file or sys.stderr, dynamic_ncols=True)
            if bar
            else None
        )

    def update(self, n: int = 1) -> None:
        """``n`` more units are done."""
        self.done += n
        if self._bar is not None:
            self._bar.update(n)
            return
        now = self._clock()
        if now - self._last_log >= self._interval:
            self._last_log = now
            log.info("%s", self.line())

    def line(self) -> str:
        """The log line: done of total, the time spent and the time left at the rate so far."""
        elapsed = self._clock() - self._start
        share = self.done / self.total if self.total else 1.0
        left = elapsed * (self.total - self.done) / self.done if self.done else float("nan")
        estimate = "unknown" if math.isnan(left) else tqdm.format_interval(left)
        return (
            f"{self.what}: {self.done}/{self.total} ({100 * share:.0f}%), "
            f"{tqdm.format_interval(elapsed)} spent, about {estimate} left"
        )

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
