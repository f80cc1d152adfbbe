"""The paper's trajectories and step timing (section III.B, Fig. 6, 7; ISO 9283 points): pure data.

One step: the command ramps from the previous target in ``ramp_s`` (4 s), holds ``hold_s`` (25 s),
and the step's measurement is the average of the last ``window_s`` (5 s). The procedure that drives
hardware (``nanodrift.procedure``), the vectorised simulated run (``nanodrift.drivers.simulated.runs``) and the
demo all take their timing from :class:`StepTiming`, and a move's sub-commands from :func:`ramp_commands`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

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
    (``nanodrift.procedure.steps``); the simulated run (``nanodrift.drivers.simulated.runs``) computes the same
    track in one pass, so a simulated calibration is commanded exactly as a driven one.
    """
    n = max(1, round(duration_s / interval_s))
    fraction = np.arange(1, n + 1) / n
    return fraction * duration_s, q_from_um + (q_to_um - q_from_um) * fraction


@dataclass(frozen=True)
class PlannedStep:
    """One step of a plan: every axis' target (µm), in the cell's axis order (a one-axis cell's: ``x``)."""

    index: int
    cycle: int
    targets_um: tuple[tuple[str, float], ...]

    @classmethod
    def on_x(cls, index: int, cycle: int, target_um: float) -> PlannedStep:
        """A step of a one-axis plan."""
        return cls(index, cycle, (("x", target_um),))

    def target(self, axis: str) -> float:
        return dict(self.targets_um)[axis]

    @property
    def target_um(self) -> float:
        """A one-axis step's target (its axis ``x``)."""
        return self.target("x")


def calibration_plan(cycles: int, points: Sequence[float] = CALIBRATION_POINTS_UM) -> list[PlannedStep]:
    """Forward sweeps, as the paper measures (Fig. 7)."""
    return [PlannedStep.on_x(i, c, x) for i, (c, x) in enumerate((c, x) for c in range(cycles) for x in points)]


def bidirectional_plan(cycles: int, points: Sequence[float] = CALIBRATION_POINTS_UM) -> list[PlannedStep]:
    """Alternate up and down sweeps: direction-dependent effects become visible."""
    order = [list(points) if c % 2 == 0 else list(points)[::-1] for c in range(cycles)]
    return [PlannedStep.on_x(i, c, x) for i, (c, x) in enumerate((c, x) for c in range(cycles) for x in order[c])]


def validation_plan(cycles: int, points: Sequence[float] = VALIDATION_POINTS_UM) -> list[PlannedStep]:
    """ISO 9283: every cycle the same forward sweep 0 -> 480 µm, so each point is always approached from the same
    side (ISO 9283 pose repeatability is unidirectional: approaches from both sides would add a stage's
    hysteresis to RP). The paper's calibration sweeps forward too (III.B)."""
    return [PlannedStep.on_x(i, c, float(x)) for i, (c, x) in enumerate((c, x) for c in range(cycles) for x in points)]


# ----- multi-axis cells (an XY or XYZ stage) ---------------------------------------------------------

#: per extra axis of a calibration design: (slope, shift per cycle) of its level index (:func:`cell_calibration_plan`)
_DESIGN_LINES: dict[int, tuple[int, int]] = {1: (1, 5), 2: (13, 6)}


@dataclass
class StepResult:
    """What one step measured, per axis: the means of its averaging window (a fallback when ``valid`` is False)."""

    step: PlannedStep
    t_s: float
    q_um: dict[str, float]
    positions_um: dict[str, float]
    temperatures: dict[str, float]
    valid: bool
    retries: int = 0
    problem: str = ""
    #: each axis' true attained position over the window, when the cell knows it (simulated); nan on hardware
    true_um: dict[str, float] = field(default_factory=dict)

    def x_without_um(self, axis: str) -> float:
        """Where ``axis`` would have been with the command = target: position - (command - target) (the stage's
        closed loop follows its command with unit gain, so this is the same period without the model)."""
        return self.positions_um[axis] - (self.q_um[axis] - self.step.target(axis))


#: a multi-axis plan's first cycle is its diagonal (every axis at level i): a model fitted on it cannot tell
#: the axes apart, so a calibration that fits one needs a second cycle
MIN_CELL_CYCLES = 2


def cell_calibration_plan(axes: Sequence[str], cycles: int = 24,
                          levels: Sequence[float] = CALIBRATION_POINTS_UM) -> list[PlannedStep]:
    """A space-filling calibration of 2 or 3 axes: a Latin hypercube per cycle on the paper's 17 levels.

    Why this design: each cycle is the paper's forward sweep of the first axis (0, 30, ..., 480 µm,
    Fig. 7) while every other axis visits each of the same 17 levels exactly once, at level index
    ``(slope * i + shift * cycle) mod 17`` for the first axis' level ``i`` (17 is prime, so every cycle
    is a permutation). For y the slope is 1 and the shift 5 per cycle: over 17 cycles every (x, y) pair
    of the 17 x 17 grid is visited exactly once, so the plan is a full factorial spread over time, with
    the room's history across every part of the workspace (not one corner while it is cold). For z
    the slope is 13 and the shift 6, chosen so that over 24 cycles no two of the centred candidate
    terms (x, y, z, x^2, y^2, z^2, x*y, x*z, y*z) correlate by more than 0.03: each cross term is
    identified on its own. A full grid per cycle would take 289 steps (2.3 h) per cycle; this takes
    the paper's 17 steps per cycle, so the paper's 24 cycles are its 408 steps of 4 s + 25 s: 3.3 h,
    for 2 axes and for 3. The validation points (:data:`CELL_VALIDATION_FRACTIONS`) lie between levels.
    """
    axes = tuple(axes)
    if not 2 <= len(axes) <= 1 + len(_DESIGN_LINES):
        raise ValueError(f"a multi-axis calibration has 2 or 3 axes, got {', '.join(axes)}")
    n = len(levels)
    steps: list[PlannedStep] = []
    for c in range(cycles):
        for i in range(n):
            targets = [(axes[0], float(levels[i]))]
            for k, axis in enumerate(axes[1:], start=1):
                slope, shift = _DESIGN_LINES[k]
                targets.append((axis, float(levels[(slope * i + shift * c) % n])))
            steps.append(PlannedStep(len(steps), c, tuple(targets)))
    return steps


#: ISO 9283 test points as fractions of each axis' range: P1 near the centre, P2..P5 near the corners of
#: the test plane (2 axes: the XY square; 3 axes: the cube's diagonal plane through two opposite edges);
#: ISO puts P2..P5 10 % in from the corners (48 and 432 µm of 480) and P1 at the centre: here each
#: coordinate is moved to the nearest midpoint between two calibration levels (45, 255, 435 µm), so no
#: validation coordinate is a training level.
CELL_VALIDATION_FRACTIONS: dict[int, tuple[tuple[float, ...], ...]] = {
    2: ((255 / 480, 255 / 480), (45 / 480, 45 / 480), (435 / 480, 45 / 480), (435 / 480, 435 / 480),
        (45 / 480, 435 / 480)),
    3: ((255 / 480, 255 / 480, 255 / 480), (45 / 480, 45 / 480, 45 / 480), (435 / 480, 45 / 480, 45 / 480),
        (435 / 480, 435 / 480, 435 / 480), (45 / 480, 435 / 480, 435 / 480)),
}


def cell_validation_points(axes: Sequence[str], ranges_um: dict[str, tuple[float, float]] | None = None
                           ) -> list[tuple[tuple[str, float], ...]]:
    """The ISO 9283 points P1..P5 of a 2- or 3-axis cell over ``ranges_um`` (default 0..480 µm per axis)."""
    axes = tuple(axes)
    if len(axes) not in CELL_VALIDATION_FRACTIONS:
        raise ValueError(f"ISO 9283 points are defined for 2 or 3 axes, got {', '.join(axes)}")
    ranges = {axis: (ranges_um or {}).get(axis, (0.0, 480.0)) for axis in axes}
    return [tuple((axis, round(ranges[axis][0] + f * (ranges[axis][1] - ranges[axis][0]), 3))
                  for axis, f in zip(axes, fractions, strict=True))
            for fractions in CELL_VALIDATION_FRACTIONS[len(axes)]]


def cell_validation_plan(axes: Sequence[str], cycles: int = 30,
                         ranges_um: dict[str, tuple[float, float]] | None = None) -> list[PlannedStep]:
    """ISO 9283 cycles P1 -> P2 -> ... -> P5, the same order every cycle: each point is always approached from the
    same pose (unidirectional pose repeatability, as the one-axis plan's forward sweeps)."""
    points = cell_validation_points(axes, ranges_um)
    return [PlannedStep(i, c, p) for i, (c, p) in enumerate((c, p) for c in range(cycles) for p in points)]
