"""σ is calibrated over calibrations: a small, loose version of ``benchmarks/coverage.py`` (which pools 16 seeds).

Six independent calibrations of the realistic simulated cell (simulated clock), each validated in range (test2)
and ~1.5 °C above it (test5) through the vectorised simulator; every step's TRUE error against the σ of its
command, pooled over the calibrations (one run's steps share one calibration's offset: only the pool says
whether σ is calibrated). The bounds are loose (six seeds), but a σ twice or half what it should be fails in
range; out of range σ must err wide, never narrow.
"""

from __future__ import annotations

import numpy as np
import pytest

from nanodrift.calibration.plans import validation_plan
from nanodrift.commands._cell import scenario_seed
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CellPhysics
from nanodrift.drivers.simulated.runs import simulate_steps
from nanodrift.model.identify import fit
from nanodrift.model.model import Model

SEEDS = range(2000, 2006)  # neither the benchmark's scored seeds (0..15) nor its tuning seeds (1000..1015)


def _calibration(seed: int) -> Model:
    return fit(simulate_dataset("train", seed=scenario_seed(seed, "train"), cell="realistic")).model


def _errors_and_sigmas(model: Model, test: str, seed: int) -> tuple[np.ndarray, np.ndarray]:
    plan = validation_plan(30)
    targets = np.array([s.target_um for s in plan])
    evaluator = model.evaluator()
    sigmas: list[float] = []

    def command(target: dict[str, float], t: float, temps: dict[str, float]) -> dict[str, float]:
        evaluator.observe(t, temps)
        sigmas.append(evaluator.sigma(target["x"], t))
        return {"x": float(evaluator.command(target["x"], t))}

    physics = CellPhysics.create(test, seed=scenario_seed(seed, test), cell="realistic")
    run = simulate_steps(physics, {"x": targets}, [s.cycle for s in plan], command_for=command)
    return run["x_true_um"] - targets, np.array(sigmas)


@pytest.fixture(scope="module")
def pooled() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    runs: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {"test2": [], "test5": []}
    for seed in SEEDS:
        model = _calibration(seed)
        for test in runs:
            runs[test].append(_errors_and_sigmas(model, test, seed))
    return {test: (np.concatenate([e for e, _ in r]), np.concatenate([s for _, s in r])) for test, r in runs.items()}


def _coverage_and_rms_z(error: np.ndarray, sigma: np.ndarray) -> tuple[float, float]:
    assert np.all(np.isfinite(sigma)) and np.all(sigma > 0)
    z = error / sigma
    return float(np.mean(np.abs(z) <= 2.0)), float(np.sqrt(np.mean(z * z)))


def test_in_range_two_sigma_holds_most_true_errors_but_not_all_pooled_over_calibrations(pooled):
    coverage, rms_z = _coverage_and_rms_z(*pooled["test2"])
    # "not all": at least one true error beyond 2σ (seen: 0.9952, 209 of 210, after σ gained the wander; the
    # 16-calibration benchmark, benchmarks/coverage.py, is where the 90-98 % goal is judged)
    assert 0.80 <= coverage < 1.0, (coverage, rms_z)
    assert 0.6 <= rms_z <= 1.6, (coverage, rms_z)


def test_out_of_range_sigma_errs_wide_never_narrow(pooled):
    """Test 5: the curvature allowance is what one calibration cannot rule out (README), wide on this cell."""
    coverage, rms_z = _coverage_and_rms_z(*pooled["test5"])
    assert coverage >= 0.90 and rms_z <= 1.0, (coverage, rms_z)
