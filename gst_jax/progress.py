"""Progress of long work on a stream: a live line on a terminal, plain lines in a log."""

from __future__ import annotations

import sys
import time
from typing import TextIO


def hms(seconds: float) -> str:
    seconds = int(max(seconds, 0))
    return f"{seconds // 3600:d}:{seconds // 60 % 60:02d}:{seconds % 60:02d}"


class StepClock:
    """An ETA for the steps left from the seconds a step takes once compiled: the time since
    the first step, less the compiling since, per step. The first step (tracing, compiling,
    warm-up: minutes on a GPU) is left out; projected onto every step it made the first
    ETAs hundreds of hours long."""

    def __init__(self):
        self._first: tuple[float, float, int] | None = None  # time, compile seconds, steps

    def eta(self, steps_done: int, steps_left: int, compile_seconds: float) -> str:
        """`H:MM:SS`, or `--` at the first step. compile_seconds: all the run's so far."""
        now = time.perf_counter()
        if self._first is None:
            self._first = (now, compile_seconds, steps_done)
            return "--"
        started, compiled, steps = self._first
        per_step = max(now - started - (compile_seconds - compiled), 0.0) / (steps_done - steps)
        return hms(per_step * steps_left)


class Progress:
    """`live` lines overwrite each other on a terminal; in a log one of them, indented, every
    `log_every_s` seconds (so a log shows where a long epoch is, or where it stalled); `line`
    always writes; `count` reports k of n items with their rate and an ETA."""

    def __init__(self, stream: TextIO | None = None, log_every_s: float = 60.0):
        self.stream = stream or sys.stderr
        self.is_terminal = self.stream.isatty()
        self.log_every_s = log_every_s
        self._last_logged = time.perf_counter()
        self._reported_tenth = -1

    def live(self, text: str) -> None:
        if self.is_terminal:
            self.stream.write("\r" + text + "  ")
            self.stream.flush()
        elif (now := time.perf_counter()) - self._last_logged >= self.log_every_s:
            self._last_logged = now
            self.line("  " + text)

    def line(self, text: str) -> None:
        self.stream.write(("\r" if self.is_terminal else "") + text + "\n")
        self.stream.flush()

    def count(self, what: str, done: int, total: int, started: float) -> None:
        """`what done/total, rate/s, ETA`: live on a terminal, else a line every tenth."""
        elapsed = max(time.perf_counter() - started, 1e-9)
        text = (f"{what} {done}/{total}, {done / elapsed:.1f}/s, "
                f"ETA {hms(elapsed / max(done, 1) * (total - done))}")
        if self.is_terminal:
            self.live(text)
            if done == total:
                self.line(text)
        elif (tenth := 10 * done // max(total, 1)) > self._reported_tenth:
            self._reported_tenth = tenth
            self.line(text)
