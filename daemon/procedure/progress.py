"""A progress line on stderr: steps done and the wall-clock time left.

The time left starts from the plan: each step's rise and hold on the cell's clock
(:meth:`Progress.begin`, from the run's ``[procedure]`` timing), which is wall time on real
hardware. Once steps are done it is scaled by the measured pace, the wall seconds this run took per
planned second so far: a simulated cell on its virtual clock runs a 29 s step in milliseconds, and
a real one takes a little longer than planned (retries, slow devices). Before anything is measured
the line says ``(planned)``. The first line comes at the start; off a terminal, one more after each
cycle.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from typing import IO

from nanodrift.calibration.plans import PlannedStep


class Progress:
    """A bar on stderr with the wall-clock time left (a line at the start and per cycle when not a TTY)."""

    def __init__(self, plan: Sequence[PlannedStep], label: str, stream: IO[str] | None = None, done: int = 0,
                 wall: Callable[[], float] = time.monotonic) -> None:
        self.cycles = [s.cycle for s in plan]
        self.total, self.label = len(plan), label
        self.done = done
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.invalid = 0
        self._wall = wall
        self._started_wall, self._started_done = wall(), done  # a resumed run's earlier steps took no time here
        self._planned_s: list[float] | None = None  # the remaining steps' planned seconds (begin)
        self._bar_shown = False

    @staticmethod
    def _hms(seconds: float) -> str:
        if not math.isfinite(seconds):
            return "?:??:??"
        s = max(0, round(seconds))
        return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"

    def begin(self, planned_s: Sequence[float]) -> None:
        """The run starts: ``planned_s`` is each remaining step's rise and hold on the cell's clock.
        Prints the first line."""
        self._planned_s = list(planned_s)
        self._started_wall, self._started_done = self._wall(), self.done
        self._show()

    def seconds_left(self) -> float:
        """The remaining steps' planned seconds times the measured pace (wall per planned second; 1
        before a step is measured). Without a plan (:meth:`begin` not called): the steps left times
        the wall seconds per step measured so far (NaN before one is)."""
        measured = self.done - self._started_done
        elapsed = self._wall() - self._started_wall
        if self._planned_s is None:
            return (self.total - self.done) * elapsed / measured if measured > 0 else float("nan")
        planned_done = sum(self._planned_s[:measured])
        pace = elapsed / planned_done if measured > 0 and planned_done > 0 else 1.0
        return sum(self._planned_s[measured:]) * pace

    def _left(self) -> str:
        left = self._hms(self.seconds_left())
        return f"{left} left" + (" (planned)" if self.done == self._started_done else "")

    def _show(self) -> None:
        if self.tty:
            width = 30
            filled = int(width * self.done / max(1, self.total))
            bar = "#" * filled + "-" * (width - filled)
            self.stream.write(f"\r{self.label} [{bar}] {self.done}/{self.total} steps, {self._left()} ")
            self._bar_shown = True
        else:
            self.stream.write(f"{self.label}: {self.done}/{self.total} steps, {self._left()}, {self.invalid} invalid\n")
        self.stream.flush()

    def note(self, text: str) -> None:
        """A line about the run (on a terminal, below the bar)."""
        self.stream.write(("\n" if self._bar_shown else "") + f"{self.label}: {text}\n")
        self._bar_shown = False
        self.stream.flush()

    def advance(self, valid: bool) -> None:
        """One more step done (``valid``: its window was clean)."""
        self.done += 1
        self.invalid += 0 if valid else 1
        if self.tty or self.done >= self.total or self.cycles[self.done] != self.cycles[self.done - 1]:  # a cycle ended
            self._show()

    def finish(self) -> None:
        if self.tty and self._bar_shown:
            self.stream.write("\n")
            self.stream.flush()
