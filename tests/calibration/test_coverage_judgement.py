"""benchmarks/coverage.py's judgement: in range over steps, out of range over runs (one sample per calibration).

The out-of-range rule must pass a calibrated σ at the benchmark's run count and fail one too wide or too narrow,
so that the benchmark can fail either way; in range the issue's step rule (90-98 %, RMS(e/σ) 0.8-1.25) holds.
"""

from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest
from helpers.benchmark_module import load_benchmark


@pytest.fixture(scope="module")
def coverage() -> ModuleType:
    return load_benchmark("coverage")


def runs_of(run_z: np.ndarray, within_sd: float = 0.1, steps: int = 210) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Per run: ``steps`` errors whose e/σ is the run's value plus a small within-run spread (σ = 1)."""
    rng = np.random.default_rng(7)
    errors = [z + within_sd * rng.standard_normal(steps) for z in run_z]
    return errors, [np.ones(steps) for _ in run_z]


def calibrated(runs: int) -> np.ndarray:
    """``runs`` values spread as N(0, 1) is (its quantiles), signs alternating: a σ exactly calibrated over runs."""
    from scipy import stats  # here, not at collection: every worker collects every file
    z = stats.norm.ppf((np.arange(runs) + 0.5) / runs)
    return z * np.where(np.arange(runs) % 2 == 0, 1.0, -1.0)


@pytest.mark.parametrize("runs", [16, 48])
def test_out_of_range_a_calibrated_sigma_passes_and_one_too_wide_or_too_narrow_fails(coverage: ModuleType,
                                                                                        runs: int) -> None:
    for scale, want in ((1.0, True), (0.5, False), (2.0, False)):
        s = coverage.score(*runs_of(scale * calibrated(runs)))
        good, rule = coverage.judge("test5", s, runs)
        assert good is want, (scale, s, rule)
        assert "runs" in rule


def test_out_of_range_the_step_rule_would_have_failed_the_calibrated_sigma(coverage: ModuleType) -> None:
    """Why test 5 is judged over runs: a calibrated σ over 16 runs leaves ~1 run (~6 % of the steps) or none beyond
    2σ, so the steps' coverage is 93.8 % or 100 %, and the step rule fails the second for no fault of σ."""
    z = calibrated(16)
    assert np.sum(np.abs(z) > 2) == 0  # the quantiles of 16 runs stop at ±1.86
    s = coverage.score(*runs_of(z))
    assert s["coverage"] > coverage.GOAL_COVERAGE[1]
    assert coverage.judge("test2", s, 16)[0] is False  # judged by steps it would miss
    assert coverage.judge("test5", s, 16)[0] is True


def test_in_range_the_steps_are_judged_as_the_issue_says(coverage: ModuleType) -> None:
    rng = np.random.default_rng(3)
    steps = [rng.standard_normal(210) for _ in range(16)]  # independent steps, σ = 1: ~95.4 % within 2σ
    ones = [np.ones(210) for _ in steps]
    assert coverage.judge("test2", coverage.score(steps, ones), 16) == (True, "steps")
    assert coverage.judge("test2", coverage.score([0.3 * e for e in steps], ones), 16)[0] is False  # σ 3x wide
    assert coverage.judge("test2", coverage.score([1.6 * e for e in steps], ones), 16)[0] is False  # too narrow
