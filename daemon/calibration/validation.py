"""ISO 9283 validation adapted to one axis (paper III.B-C, Table I, Fig. 9, 11).

Test points 0, 80, ..., 480 µm, visited in alternating up and down sweeps so the inner points are
approached from both sides (the end points are measured twice at each turn, the second time
without a move); ``cycles`` sweeps (30 in the paper: 210 steps of 29 s, ~1.7 h). Each visit is a step of the
calibration procedure (4 s ramp, 25 s hold, mean of the last 5 s), commanded through the model
(``q' = model(x', temperatures now)``) or, uncompensated, with ``q' = x'``.

Per point j with attained positions x_ji (i = 1..N visits):
- accuracy AP_j = |mean_i x_ji - x'_j| (ISO 9283 positioning accuracy, 1-D);
- repeatability RP_j = mean(l) + 3 * std(l), l_i = |x_ji - mean_i x_ji| (ISO 9283 RP, 1-D).
The test's figure in Table I is the mean of AP_j over the points.

"Without compensation" while the model runs (tests 2-5, marked * as in the paper): the position the
stage would have reached with the uncompensated command, x_without = x_measured - (q' - x'). The
stage's closed loop makes the attained position follow the command with unit gain (its nonlinearity
over the sub-µm difference q' - x' is below a nm), so this is the same period's drift without the
model, computed from the same measurements.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import IO, Any

import numpy as np

from daemon.calibration.procedure import (
    Backend,
    PlannedStep,
    Progress,
    StepResult,
    StepTiming,
    run_steps,
)

VALIDATION_POINTS_UM: tuple[float, ...] = tuple(float(x) for x in range(0, 481, 80))


def validation_plan(cycles: int, points: Sequence[float] = VALIDATION_POINTS_UM) -> list[PlannedStep]:
    steps: list[PlannedStep] = []
    for c in range(cycles):
        for x in (points if c % 2 == 0 else list(points)[::-1]):
            steps.append(PlannedStep(len(steps), c, float(x)))
    return steps


@dataclass
class PointStats:
    target_um: float
    visits: int
    accuracy_nm: float
    repeatability_nm: float
    accuracy_without_nm: float
    repeatability_without_nm: float


@dataclass
class TestResult:
    name: str
    compensated: bool
    steps: list[StepResult]
    points: list[PointStats] = field(default_factory=list)
    extrapolating_steps: int = 0
    invalid_steps: int = 0

    @property
    def accuracy_nm(self) -> float:
        """Table I "with comp." (NaN when the test ran without the model)."""
        return float(np.mean([p.accuracy_nm for p in self.points])) if self.compensated else float("nan")

    @property
    def accuracy_without_nm(self) -> float:
        return float(np.mean([p.accuracy_without_nm for p in self.points]))

    @property
    def improvement(self) -> float:
        return self.accuracy_without_nm / self.accuracy_nm if self.compensated else float("nan")

    def to_dict(self) -> dict[str, Any]:
        def num(v: float) -> float | None:
            return None if not np.isfinite(v) else round(float(v), 3)

        return {
            "test": self.name,
            "compensated": self.compensated,
            "without_comp_nm": num(self.accuracy_without_nm),
            "without_is_computed": self.compensated,
            "with_comp_nm": num(self.accuracy_nm),
            "improvement_ratio": num(self.improvement),
            "improvement_percent": num((self.improvement - 1.0) * 100.0),
            "extrapolating_steps": self.extrapolating_steps,
            "invalid_steps": self.invalid_steps,
            "points": [
                {"x_um": p.target_um, "visits": p.visits,
                 "accuracy_nm": num(p.accuracy_nm) if self.compensated else None,
                 "repeatability_nm": num(p.repeatability_nm) if self.compensated else None,
                 "accuracy_without_nm": num(p.accuracy_without_nm),
                 "repeatability_without_nm": num(p.repeatability_without_nm)}
                for p in self.points
            ],
        }


def iso9283(positions: np.ndarray, target: float) -> tuple[float, float]:
    """(accuracy, repeatability) in the units of ``positions`` for one point (1-D ISO 9283)."""
    mean = float(np.mean(positions))
    dist = np.abs(positions - mean)
    spread = float(np.std(dist, ddof=1)) if positions.size > 1 else 0.0
    return abs(mean - target), float(np.mean(dist)) + 3.0 * spread


def x_without(step: StepResult) -> float:
    return step.x_um - (step.q_um - step.step.target_um)


def summarize(name: str, steps: Sequence[StepResult], compensated: bool, extrapolating: int = 0) -> TestResult:
    valid = [s for s in steps if s.valid]
    result = TestResult(name, compensated, list(steps), extrapolating_steps=extrapolating,
                        invalid_steps=len(steps) - len(valid))
    for target in sorted({s.step.target_um for s in valid}):
        here = [s for s in valid if s.step.target_um == target]
        with_ = np.array([s.x_um for s in here])
        without = np.array([x_without(s) for s in here])
        acc, rep = iso9283(with_, target)
        acc0, rep0 = iso9283(without, target)
        result.points.append(PointStats(target, len(here), acc * 1e3, rep * 1e3, acc0 * 1e3, rep0 * 1e3))
    return result


async def run_validation(
    backend: Backend,
    model: Any | None,
    *,
    name: str = "validation",
    cycles: int = 30,
    timing: StepTiming | None = None,
    progress_stream: IO[str] | None = None,
) -> TestResult:
    """One test: drive the validation plan with the model (or without when ``model`` is None)."""
    timing = timing or StepTiming()
    plan = validation_plan(cycles)
    evaluator = model.evaluator() if model is not None else None
    latest: dict[str, float] = {}
    extrapolating = 0
    if model is not None:
        missing = [c for c in model.channels if c not in backend.temperature_channels]
        if missing:
            raise ValueError(f"the model needs channel(s) {', '.join(missing)} that this cell does not measure")

    def observe(t: float, temps: dict[str, float]) -> None:
        latest.update(temps)
        if evaluator is not None:
            evaluator.observe(t, temps)

    def command_for(step: PlannedStep, t: float) -> float:
        nonlocal extrapolating
        if evaluator is None:
            return step.target_um
        if not evaluator.ready:
            raise RuntimeError("no clean temperature sample yet for every channel the model needs")
        if model.out_of_range(step.target_um, latest):
            extrapolating += 1
        return float(evaluator.command(step.target_um, t))

    progress = Progress(plan, timing.step_s, name, progress_stream)
    steps = await run_steps(backend, plan, timing=timing, command_for=command_for, on_temperatures=observe,
                            progress=progress)
    return summarize(name, steps, model is not None, extrapolating)
