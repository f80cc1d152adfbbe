"""A progress line on stderr: steps done and the wall-clock time left.

The time left is measured, not planned: a step lasts 29 s of the cell's clock, which is 29 s on real
hardware but a few milliseconds on the simulated cell's virtual clock, so the rate is the steps this
run has completed per wall-clock second so far.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Sequence
from typing import IO

from daemon.calibration.plans import PlannedStep, StepResult


class Progress:
    """A bar on stderr with the wall-clock time left (a line per cycle when not a TTY)."""

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

    @staticmethod
    def _hms(seconds: float) -> str:
        if not math.isfinite(seconds):
            return "?:??:??"
        s = max(0, round(seconds))
        return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"

    def seconds_left(self) -> float:
        """Steps still to run times the wall seconds per step measured so far in this run."""
        measured = self.done - self._started_done
        if measured <= 0:
            return float("nan")
        return (self.total - self.done) * (self._wall() - self._started_wall) / measured

    def advance(self, result: StepResult) -> None:
        self.done += 1
        self.invalid += 0 if result.valid else 1
        left = self._hms(self.seconds_left())
        if self.tty:
            width = 30
            filled = int(width * self.done / max(1, self.total))
            bar = "#" * filled + "-" * (width - filled)
            self.stream.write(f"\r{self.label} [{bar}] {self.done}/{self.total} steps, {left} left ")
            self.stream.flush()
        elif self.done >= self.total or self.cycles[self.done] != self.cycles[self.done - 1]:  # a cycle ended
            self.stream.write(f"{self.label}: {self.done}/{self.total} steps, {left} left, {self.invalid} invalid\n")
            self.stream.flush()

    def finish(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()
