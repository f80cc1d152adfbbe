"""ISO 9283 statistics adapted to one axis (paper III.B-C, Table I, Fig. 9, 11).

Test points 0, 80, ..., 480 µm, visited in forward sweeps, each point always approached from the same
side (ISO 9283 repeatability is unidirectional; from both sides RP would mix in the stage's
hysteresis); ``cycles`` sweeps (30 in the paper: 210 steps of 29 s, ~1.7 h). Each visit is a step of the
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

Any number of axes, one code path (:func:`score_points`): per point, ISO 9283's pose accuracy AP =
|barycentre of the attained points - target| and repeatability RP = l̄ + 3 S_l (l_i = |attained_i -
barycentre|) in the cell's dimension (one axis: the figures above), and the same per axis (Table I per
axis). A test's "without compensation" is data: the positions computed from the same run (one axis,
:func:`summarize`) or those of a second, uncompensated run (a multi-axis cell, :func:`summarize_runs`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nanodrift.calibration.plans import StepResult


@dataclass
class PointStats:
    """One ISO 9283 point: AP and RP in the cell's dimension and per axis (nm)."""

    target_um: dict[str, float]
    visits: int
    accuracy_nm: float
    repeatability_nm: float
    axis_accuracy_nm: dict[str, float]
    axis_repeatability_nm: dict[str, float]


@dataclass
class TestResult:
    """One ISO 9283 test of a cell of any number of axes: per point with the model (``points``; empty when the
    test ran without it) and without it (``points_without``: computed from the same run, or a second run)."""

    name: str
    compensated: bool
    steps: list[StepResult]
    points: list[PointStats] = field(default_factory=list)
    points_without: list[PointStats] = field(default_factory=list)
    axes: tuple[str, ...] = ("x",)
    extrapolating_steps: int = 0
    invalid_steps: int = 0
    #: per step, with the model: the bias correction its command carried (``validate --adapt``) ...
    corrections_um: list[float] = field(default_factory=list)
    #: ... and the model's standard uncertainty for its command
    q_sigma_um: list[float] = field(default_factory=list)
    adapted: bool = False
    #: with ``--adapt``: the standard uncertainty of the corrected command (what the tracker leaves)
    q_sigma_adapted_um: list[float] = field(default_factory=list)
    #: the model's ``wander_um``: what the position sensor adds to a measured error beside q_sigma
    measurement_sigma_um: float = 0.0

    @property
    def axis(self) -> str:
        """The axis of a one-axis test (its steps' positions and commands on it)."""
        (axis,) = self.axes
        return axis

    @property
    def accuracy_nm(self) -> float:
        """Table I "with comp.": AP, mean over the points (NaN when the test ran without the model)."""
        return _mean_of(self.points, "accuracy_nm") if self.compensated else float("nan")

    @property
    def accuracy_without_nm(self) -> float:
        return _mean_of(self.points_without, "accuracy_nm")

    @property
    def repeatability_nm(self) -> float:
        return _mean_of(self.points, "repeatability_nm") if self.compensated else float("nan")

    @property
    def repeatability_without_nm(self) -> float:
        return _mean_of(self.points_without, "repeatability_nm")

    def axis_accuracy_nm(self, axis: str, *, with_model: bool = True) -> float:
        """Table I for one axis: mean over the points of |mean attained - target| along ``axis``."""
        points = self.points if with_model else self.points_without
        return float(np.mean([p.axis_accuracy_nm[axis] for p in points])) if points else float("nan")

    @property
    def improvement(self) -> float:
        return self.accuracy_without_nm / self.accuracy_nm if self.compensated else float("nan")

    @property
    def x_true_um(self) -> list[float]:
        """Per step of a one-axis test, the true attained position (a simulated cell only; empty on hardware)."""
        truths = [s.true_um.get(self.axis, math.nan) for s in self.steps]
        return truths if truths and all(map(math.isfinite, truths)) else []

    @property
    def has_truth(self) -> bool:
        """Whether every step knows the true attained position (a simulated cell; never on hardware)."""
        return bool(self.x_true_um)

    def against_truth(self) -> TestResult | None:
        """The same test scored against the true position (as this one against the interferometer); None
        without truth."""
        if not self.has_truth:
            return None
        return summarize(self.name, self.steps, self.compensated, axis=self.axis, truth=True)

    def true_accuracy_nm(self) -> tuple[float, float]:
        """Table I against the true position: (without, with) compensation; with is NaN for an uncompensated
        test, both NaN without truth."""
        truth = self.against_truth()
        return (truth.accuracy_without_nm, truth.accuracy_nm) if truth else (math.nan, math.nan)

    @property
    def accuracy_true_nm(self) -> float:
        """Table I's "with comp." against the true position (nan on hardware or without the model)."""
        return self.true_accuracy_nm()[1]

    @property
    def command_sigma_um(self) -> list[float]:
        """The σ of what each step commanded: the tracker's with ``--adapt``, else the model's q_sigma."""
        return self.q_sigma_adapted_um if self.adapted and self.q_sigma_adapted_um else self.q_sigma_um

    def coverage(self, k: float = 2.0, *, truth: bool = False) -> float:
        """Share of valid steps whose measured error (position - target; with ``truth`` the TRUE position, nan
        without it) lies within ±k σ (nan without sigmas). σ: :attr:`command_sigma_um`, for a measured error
        sqrt(q_sigma² + measurement_sigma²): it carries the sensor's wander besides the true error q_sigma is for."""
        if truth and not self.has_truth:
            return float("nan")
        m2 = self.measurement_sigma_um ** 2
        a = self.axis
        inside = [abs((s.true_um if truth else s.positions_um)[a] - s.step.target(a))
                  <= k * (sigma if truth else float(np.sqrt(sigma * sigma + m2)))
                  for s, sigma in zip(self.steps, self.command_sigma_um, strict=False)
                  if s.valid and np.isfinite(sigma)]
        return float(np.mean(inside)) if inside else float("nan")

    def coverage_true(self, k: float = 2.0) -> float:
        """:meth:`coverage` of the TRUE errors (true position - target)."""
        return self.coverage(k, truth=True)

    def to_dict(self) -> dict[str, Any]:
        """Table I's document of a one-axis test (the ``validate --json`` contract)."""
        num = _num
        doc: dict[str, Any] = {
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
            "points": self._points_list(),
        }
        truth = self.against_truth()
        if truth is not None:
            doc["true_position"] = {"without_comp_nm": num(truth.accuracy_without_nm),
                                    "with_comp_nm": num(truth.accuracy_nm),
                                    "improvement_ratio": num(truth.improvement) if truth.compensated else None,
                                    "points": truth._points_list()}
        return doc

    def _points_list(self) -> list[dict[str, Any]]:
        a, num = self.axis, _num
        return [{"x_um": p0.target_um[a], "visits": p0.visits,
                 "accuracy_nm": num(p.accuracy_nm) if self.compensated else None,
                 "repeatability_nm": num(p.repeatability_nm) if self.compensated else None,
                 "accuracy_without_nm": num(p0.accuracy_nm),
                 "repeatability_without_nm": num(p0.repeatability_nm)}
                for p, p0 in zip(self.points, self.points_without, strict=True)]

    def scores_dict(self, *, with_model: bool) -> dict[str, Any] | None:
        """AP/RP in the cell's dimension and per axis, per point, with or without the model (a multi-axis
        test's document; None: the test ran without the model)."""
        if with_model and not self.compensated:
            return None
        points = self.points if with_model else self.points_without
        return {
            "test": self.name, "axes": list(self.axes),
            "accuracy_nm": round(_mean_of(points, "accuracy_nm"), 3),
            "repeatability_nm": round(_mean_of(points, "repeatability_nm"), 3),
            "axis_accuracy_nm": {a: round(self.axis_accuracy_nm(a, with_model=with_model), 3) for a in self.axes},
            "points": [{"target_um": p.target_um, "visits": p.visits, "accuracy_nm": round(p.accuracy_nm, 3),
                        "repeatability_nm": round(p.repeatability_nm, 3),
                        "axis_accuracy_nm": {a: round(v, 3) for a, v in p.axis_accuracy_nm.items()},
                        "axis_repeatability_nm": {a: round(v, 3) for a, v in p.axis_repeatability_nm.items()}}
                       for p in points],
        }


def _mean_of(points: Sequence[PointStats], figure: str) -> float:
    return float(np.mean([getattr(p, figure) for p in points])) if points else float("nan")


def _num(v: float) -> float | None:
    return None if not np.isfinite(v) else round(float(v), 3)


def summarize(name: str, steps: Sequence[StepResult], compensated: bool, extrapolating: int = 0,
              axis: str = "x", truth: bool = False) -> TestResult:
    """One test of ``axis`` from its valid steps: with the model as run, and without it computed from the same
    run (x - (q' - x')); against the position sensor, or with ``truth`` the true position (simulated)."""
    valid = [s for s in steps if s.valid]
    targets = {axis: np.array([s.step.target(axis) for s in valid])}
    as_run = np.array([(s.true_um if truth else s.positions_um)[axis] for s in valid])
    without = as_run - np.array([s.q_um[axis] - s.step.target(axis) for s in valid])
    result = summarize_runs(name, targets, {axis: without}, {axis: as_run})
    result.compensated, result.steps = compensated, list(steps)
    result.extrapolating_steps, result.invalid_steps = extrapolating, len(steps) - len(valid)
    return result


def summarize_runs(name: str, targets_um: Mapping[str, np.ndarray], without_um: Mapping[str, np.ndarray],
                   with_um: Mapping[str, np.ndarray] | None) -> TestResult:
    """One test of any number of axes from per-step targets and attained positions (µm, one array per axis):
    without the model and with it (None: not run)."""
    return TestResult(name, with_um is not None, [], score_points(targets_um, with_um) if with_um is not None else [],
                      score_points(targets_um, without_um), axes=tuple(targets_um))


# ----- ISO 9283 pose accuracy and repeatability in the cell's dimension ---------------------------------

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


def score_points(targets_um: Mapping[str, np.ndarray], attained_um: Mapping[str, np.ndarray]) -> list[PointStats]:
    """ISO 9283 per point (steps with the same target on every axis) from per-step targets and attained
    positions (µm, one array per axis): AP/RP in the cell's dimension and per axis, in nm. The one code path
    of every test, one axis or several (one axis: AP = |mean - target|, RP = l̄ + 3 S_l with l_i = |x_i - mean|)."""
    axes = tuple(targets_um)
    target = np.column_stack([np.asarray(targets_um[a], dtype=np.float64) for a in axes])
    attained = np.column_stack([np.asarray(attained_um[a], dtype=np.float64) for a in axes])
    points = []
    rows, first = np.unique(target, axis=0, return_index=True)
    for row in (rows if len(axes) == 1 else rows[np.argsort(first)]):  # one axis: by position; else as visited (P1..P5)
        here = attained[np.all(target == row, axis=1)]
        per_axis = {a: (pose_accuracy(here[:, [j]], row[j:j + 1]), pose_repeatability(here[:, [j]]))
                    for j, a in enumerate(axes)}
        points.append(PointStats(
            target_um={a: float(row[j]) for j, a in enumerate(axes)}, visits=int(here.shape[0]),
            accuracy_nm=pose_accuracy(here, row) * 1e3, repeatability_nm=pose_repeatability(here) * 1e3,
            axis_accuracy_nm={a: v[0] * 1e3 for a, v in per_axis.items()},
            axis_repeatability_nm={a: v[1] * 1e3 for a, v in per_axis.items()}))
    return points
