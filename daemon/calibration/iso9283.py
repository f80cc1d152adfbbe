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

A multi-axis cell (:func:`summarize_cell`): per point, ISO 9283's pose accuracy AP = |barycentre of the
attained points - target| and repeatability RP = l̄ + 3 S_l (l_i = |attained_i - barycentre|) in 2-D/3-D,
and the one-axis figures per axis (Table I per axis).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nanodrift.calibration.plans import StepResult


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
    #: with ``--adapt``: the standard uncertainty of the corrected command (what the tracker leaves)
    q_sigma_adapted_um: list[float] = field(default_factory=list)
    #: per step, the true attained position (a simulated cell only; empty on hardware)
    x_true_um: list[float] = field(default_factory=list)
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
        """Whether every step knows the true attained position (a simulated cell; never on hardware)."""
        return len(self.x_true_um) == len(self.steps) > 0 and all(map(math.isfinite, self.x_true_um))

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

    @property
    def accuracy_true_nm(self) -> float:
        """Table I's "with comp." against the true position (nan on hardware or without the model)."""
        return self.true_accuracy_nm()[1]

    @property
    def command_sigma_um(self) -> list[float]:
        """The σ of what each step commanded: the tracker's with ``--adapt``, else the model's q_sigma."""
        return self.q_sigma_adapted_um if self.adapted and self.q_sigma_adapted_um else self.q_sigma_um

    def coverage(self, k: float = 2.0) -> float:
        """Share of valid steps whose measured error (position - target) lies within ±k σ (nan without sigmas).

        σ = sqrt(q_sigma² + measurement_sigma²): the measured error carries the sensor's wander besides
        the true error q_sigma is for."""
        m2 = self.measurement_sigma_um ** 2
        inside = [abs(s.x_um - s.step.target_um) <= k * float(np.sqrt(sigma * sigma + m2))
                  for s, sigma in zip(self.steps, self.command_sigma_um, strict=False)
                  if s.valid and np.isfinite(sigma)]
        return float(np.mean(inside)) if inside else float("nan")

    def coverage_true(self, k: float = 2.0) -> float:
        """Share of valid steps whose TRUE error (true position - target) lies within ±k σ (nan: no truth);
        σ: :attr:`command_sigma_um`."""
        if not self.has_truth:
            return float("nan")
        inside = [abs(x_true - s.step.target_um) <= k * sigma
                  for s, sigma, x_true in zip(self.steps, self.command_sigma_um, self.x_true_um, strict=False)
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
            **({"q_sigma_adapted_median_nm": num(float(np.median(self.q_sigma_adapted_um)) * 1e3)}
               if self.adapted and self.q_sigma_adapted_um else {}),
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




# ----- multi-axis cells: ISO 9283 pose accuracy and repeatability in 2-D / 3-D -------------------------

def pose_accuracy(attained: np.ndarray, target: Sequence[float]) -> float:
    """ISO 9283 pose accuracy AP: distance from the barycentre of the attained points (rows) to the target."""
    points = np.atleast_2d(np.asarray(attained, dtype=np.float64))
    return float(np.linalg.norm(points.mean(axis=0) - np.asarray(target, dtype=np.float64)))


def pose_repeatability(attained: np.ndarray) -> float:
    """ISO 9283 pose repeatability RP = l̄ + 3 S_l, l_i the distance of attained point i to the barycentre
    (S_l with N - 1; 0 for a single visit)."""
    points = np.atleast_2d(np.asarray(attained, dtype=np.float64))
    dist = np.linalg.norm(points - points.mean(axis=0), axis=1)
    spread = float(np.std(dist, ddof=1)) if dist.size > 1 else 0.0
    return float(dist.mean()) + 3.0 * spread


@dataclass
class CellPointStats:
    """One ISO 9283 point of a multi-axis test: AP and RP in 2-D/3-D and per axis (nm)."""

    target_um: dict[str, float]
    visits: int
    accuracy_nm: float
    repeatability_nm: float
    axis_accuracy_nm: dict[str, float]
    axis_repeatability_nm: dict[str, float]


@dataclass
class CellTestResult:
    """The ISO 9283 figures of one multi-axis test run (with or without the model), against one reference."""

    name: str
    axes: tuple[str, ...]
    points: list[CellPointStats]

    @property
    def accuracy_nm(self) -> float:
        """The test's figure: AP in 2-D/3-D, mean over the points."""
        return float(np.mean([p.accuracy_nm for p in self.points]))

    @property
    def repeatability_nm(self) -> float:
        return float(np.mean([p.repeatability_nm for p in self.points]))

    def axis_accuracy_nm(self, axis: str) -> float:
        """Table I for one axis: mean over the points of |mean attained - target| along ``axis``."""
        return float(np.mean([p.axis_accuracy_nm[axis] for p in self.points]))

    def to_dict(self) -> dict[str, Any]:
        return {
            "test": self.name, "axes": list(self.axes),
            "accuracy_nm": round(self.accuracy_nm, 3), "repeatability_nm": round(self.repeatability_nm, 3),
            "axis_accuracy_nm": {a: round(self.axis_accuracy_nm(a), 3) for a in self.axes},
            "points": [{"target_um": p.target_um, "visits": p.visits, "accuracy_nm": round(p.accuracy_nm, 3),
                        "repeatability_nm": round(p.repeatability_nm, 3),
                        "axis_accuracy_nm": {a: round(v, 3) for a, v in p.axis_accuracy_nm.items()},
                        "axis_repeatability_nm": {a: round(v, 3) for a, v in p.axis_repeatability_nm.items()}}
                       for p in self.points],
        }


def summarize_cell(name: str, targets_um: dict[str, np.ndarray], attained_um: dict[str, np.ndarray]
                   ) -> CellTestResult:
    """ISO 9283 per point (rows with the same target on every axis, in first-visit order) from per-step
    targets and attained positions (µm, one array per axis): AP/RP in the cell's dimension and per axis, in nm."""
    axes = tuple(targets_um)
    target = np.column_stack([np.asarray(targets_um[a], dtype=np.float64) for a in axes])
    attained = np.column_stack([np.asarray(attained_um[a], dtype=np.float64) for a in axes])
    points = []
    rows, first = np.unique(target, axis=0, return_index=True)
    for row in rows[np.argsort(first)]:  # in the order the plan first visits them (P1..P5)
        here = attained[np.all(target == row, axis=1)]
        per_axis = {a: iso9283(here[:, j], float(row[j])) for j, a in enumerate(axes)}
        points.append(CellPointStats(
            target_um={a: float(row[j]) for j, a in enumerate(axes)}, visits=int(here.shape[0]),
            accuracy_nm=pose_accuracy(here, row) * 1e3, repeatability_nm=pose_repeatability(here) * 1e3,
            axis_accuracy_nm={a: v[0] * 1e3 for a, v in per_axis.items()},
            axis_repeatability_nm={a: v[1] * 1e3 for a, v in per_axis.items()}))
    return CellTestResult(name, axes, points)
