"""The paper's trajectories and step timing (section III.B, Fig. 6, 7; ISO 9283 points): pure data.

One step: the command ramps from the previous target in ``ramp_s`` (4 s), holds ``hold_s`` (25 s),
and the step's measurement is the average of the last ``window_s`` (5 s). The procedure that drives
hardware (``daemon.procedure``), the vectorised simulated run (``drivers.simulated.runs``) and the
demo all take their timing from :class:`StepTiming`, and a move's sub-commands from :func:`ramp_commands`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

CALIBRATION_POINTS_UM: tuple[float, ...] = tuple(float(x) for x in range(0, 481, 30))
VALIDATION_POINTS_UM: tuple[float, ...] = tuple(float(x) for x in range(0, 481, 80))


@dataclass(frozen=True)
class StepTiming:
    ramp_s: float = 4.0
    hold_s: float = 25.0
    window_s: float = 5.0
    ramp_interval_s: float = 0.25
    max_retries: int = 2

    @property
    def step_s(self) -> float:
        return self.ramp_s + self.hold_s


#: the paper's step: 4 s ramp, 25 s hold, the last 5 s averaged
PAPER_TIMING = StepTiming()


def ramp_commands(q_from_um: float, q_to_um: float, duration_s: float,
                  interval_s: float) -> tuple[np.ndarray, np.ndarray]:
    """One move as sub-commands: (seconds after the move starts, command in um) of each.

    ``n = round(duration_s / interval_s)`` (at least 1) equal steps, one every ``duration_s / n``,
    the last one at the target. The procedure sends them on the cell's clock
    (``daemon.procedure.steps``); the simulated run (``drivers.simulated.runs``) computes the same
    track in one pass, so a simulated calibration is commanded exactly as a driven one.
    """
    n = max(1, round(duration_s / interval_s))
    fraction = np.arange(1, n + 1) / n
    return fraction * duration_s, q_from_um + (q_to_um - q_from_um) * fraction


@dataclass(frozen=True)
class PlannedStep:
    index: int
    cycle: int
    target_um: float


def calibration_plan(cycles: int, points: Sequence[float] = CALIBRATION_POINTS_UM) -> list[PlannedStep]:
    """Forward sweeps, as the paper measures (Fig. 7)."""
    return [PlannedStep(i, c, x) for i, (c, x) in enumerate((c, x) for c in range(cycles) for x in points)]


def bidirectional_plan(cycles: int, points: Sequence[float] = CALIBRATION_POINTS_UM) -> list[PlannedStep]:
    """Alternate up and down sweeps: direction-dependent effects become visible."""
    order = [list(points) if c % 2 == 0 else list(points)[::-1] for c in range(cycles)]
    return [PlannedStep(i, c, x) for i, (c, x) in enumerate((c, x) for c in range(cycles) for x in order[c])]


@dataclass
class StepResult:
    """What one step measured: the means of its averaging window (or a fallback when ``valid`` is False)."""

    step: PlannedStep
    t_s: float
    q_um: float
    x_um: float
    temperatures: dict[str, float]
    valid: bool
    retries: int = 0
    problem: str = ""
    t_command_s: float = math.nan
    #: the true attained position over the same window, when the cell knows it (simulated); nan on hardware
    x_true_um: float = math.nan


def validation_plan(cycles: int, points: Sequence[float] = VALIDATION_POINTS_UM) -> list[PlannedStep]:
    """ISO 9283: alternating up and down sweeps, so inner points are approached from both sides."""
    steps: list[PlannedStep] = []
    for c in range(cycles):
        for x in (points if c % 2 == 0 else list(points)[::-1]):
            steps.append(PlannedStep(len(steps), c, float(x)))
    return steps
