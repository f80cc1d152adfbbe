"""ISO 9283 statistics adapted to one axis (paper III.B-C, Table I, Fig. 9, 11).

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
from typing import Any

import numpy as np

from daemon.calibration.plans import StepResult


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
    #: per step, with the model: the bias correction its command carried (``validate --adapt``) ...
    corrections_um: list[float] = field(default_factory=list)
    #: ... and the model's standard uncertainty for its command
    q_sigma_um: list[float] = field(default_factory=list)
    adapted: bool = False
    #: the model's ``wander_um``: what the position sensor adds to a measured error beside q_sigma
    measurement_sigma_um: float = 0.0

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

    @property
    def has_truth(self) -> bool:
        """Whether every valid step knows the true attained position (a simulated cell)."""
        valid = [s for s in self.steps if s.valid]
        return bool(valid) and all(np.isfinite(s.x_true_um) for s in valid)

    @property
    def accuracy_true_nm(self) -> float:
        """Table I's "with comp." against the true position (nan on hardware or without the model)."""
        if not (self.compensated and self.has_truth):
            return float("nan")
        valid = [s for s in self.steps if s.valid]
        targets = sorted({s.step.target_um for s in valid})
        return float(np.mean([iso9283(np.array([s.x_true_um for s in valid if s.step.target_um == x]), x)[0]
                              for x in targets])) * 1e3

    def coverage(self, k: float = 2.0) -> float:
        """Share of valid steps whose measured error (position - target) lies within ±k σ (nan without sigmas).

        σ = sqrt(q_sigma² + measurement_sigma²): the measured error carries the sensor's wander besides
        the true error q_sigma is for."""
        m2 = self.measurement_sigma_um ** 2
        inside = [abs(s.x_um - s.step.target_um) <= k * float(np.sqrt(sigma * sigma + m2))
                  for s, sigma in zip(self.steps, self.q_sigma_um, strict=False)
                  if s.valid and np.isfinite(sigma)]
        return float(np.mean(inside)) if inside else float("nan")

    def coverage_true(self, k: float = 2.0) -> float:
        """Share of valid steps whose TRUE error (true position - target) lies within ±k q_sigma (nan: no truth)."""
        inside = [abs(s.x_true_um - s.step.target_um) <= k * sigma
                  for s, sigma in zip(self.steps, self.q_sigma_um, strict=False)
                  if s.valid and np.isfinite(sigma) and np.isfinite(s.x_true_um)]
        return float(np.mean(inside)) if inside else float("nan")

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
            "adapted": self.adapted,
            "final_correction_um": num(self.corrections_um[-1]) if self.adapted and self.corrections_um else None,
            "q_sigma_median_nm": num(float(np.median(self.q_sigma_um)) * 1e3) if self.q_sigma_um else None,
            "within_2_sigma": num(self.coverage()),
            **({"with_comp_true_nm": num(self.accuracy_true_nm), "within_2_sigma_true": num(self.coverage_true())}
               if self.has_truth and self.compensated else {}),
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


