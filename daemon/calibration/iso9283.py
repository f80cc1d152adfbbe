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

Against the truth (a simulated cell only): ``x_true_um``, per step, is the position the stage truly
attained over the step's window (no interferometer noise or wander). Real hardware has none: the list
is empty and nothing is reported against it.
"""

from __future__ import annotations

import math
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
    #: per step, the true attained position (a simulated cell only; empty on hardware)
    x_true_um: list[float] = field(default_factory=list)

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
        return len(self.x_true_um) == len(self.steps) > 0

    def true_points(self) -> list[PointStats]:
        """ISO 9283 per point against the true position (as :attr:`points` against the interferometer)."""
        if not self.has_truth:
            return []
        truths = [s for s in zip(self.steps, self.x_true_um, strict=True) if s[0].valid]
        out = []
        for target in sorted({s.step.target_um for s, _ in truths}):
            here = [(s, x) for s, x in truths if s.step.target_um == target]
            with_ = np.array([x for _, x in here])
            without = np.array([x - (s.q_um - s.step.target_um) for s, x in here])
            acc, rep = iso9283(with_, target)
            acc0, rep0 = iso9283(without, target)
            out.append(PointStats(target, len(here), acc * 1e3, rep * 1e3, acc0 * 1e3, rep0 * 1e3))
        return out

    def true_accuracy_nm(self) -> tuple[float, float]:
        """Table I against the true position: (without, with) compensation; with is NaN for an uncompensated
        test, both NaN without truth."""
        points = self.true_points()
        if not points:
            return math.nan, math.nan
        without = float(np.mean([p.accuracy_without_nm for p in points]))
        return without, float(np.mean([p.accuracy_nm for p in points])) if self.compensated else math.nan

    def coverage(self, k: float = 2.0) -> float:
        """Share of valid steps whose error (position - target) lies within ±k q_sigma_um (nan without sigmas)."""
        inside = [abs(s.x_um - s.step.target_um) <= k * sigma
                  for s, sigma in zip(self.steps, self.q_sigma_um, strict=False)
                  if s.valid and np.isfinite(sigma)]
        return float(np.mean(inside)) if inside else float("nan")

    def to_dict(self) -> dict[str, Any]:
        doc = self._measured_dict()
        if self.has_truth:
            doc["true_position"] = self._true_dict()
        return doc

    def _true_dict(self) -> dict[str, Any]:
        """The same figures against the true attained position (a simulated cell only)."""
        without, with_ = self.true_accuracy_nm()
        return {
            "without_comp_nm": _num(without),
            "with_comp_nm": _num(with_),
            "improvement_ratio": _num(without / with_) if self.compensated else None,
            "points": [
                {"x_um": p.target_um, "visits": p.visits,
                 "accuracy_nm": _num(p.accuracy_nm) if self.compensated else None,
                 "repeatability_nm": _num(p.repeatability_nm) if self.compensated else None,
                 "accuracy_without_nm": _num(p.accuracy_without_nm),
                 "repeatability_without_nm": _num(p.repeatability_without_nm)}
                for p in self.true_points()
            ],
        }

    def _measured_dict(self) -> dict[str, Any]:
        num = _num
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
            "points": [
                {"x_um": p.target_um, "visits": p.visits,
                 "accuracy_nm": num(p.accuracy_nm) if self.compensated else None,
                 "repeatability_nm": num(p.repeatability_nm) if self.compensated else None,
                 "accuracy_without_nm": num(p.accuracy_without_nm),
                 "repeatability_without_nm": num(p.repeatability_without_nm)}
                for p in self.points
            ],
        }


def _num(v: float) -> float | None:
    return None if not np.isfinite(v) else round(float(v), 3)


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


