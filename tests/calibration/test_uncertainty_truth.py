"""Issue 19: q_sigma judged against the truth, and adaptation's claims too.

The simulated cell knows where the stage truly is behind every interferometer reading; a validation
step there carries the true attained position over its averaging window (``x_true_um``), so the
errors are scored against the truth as well as against the instrument the bias tracker follows.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path

import numpy as np
import pytest
from helpers.discovery_helpers import cell_run, paper_model
from helpers.sim_helpers import Capture, trained_model

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration import iso9283
from nanodrift.calibration.discovery import discover
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.cli import main
from nanodrift.model.model import Model, save_model
from nanodrift.procedure.validation import run_validation


def validate(model: Model, test: str, seed: int, cycles: int, effects: str | None = None,
             adapt: BiasTracker | None = None) -> iso9283.TestResult:
    drivers = simulated_drivers(test, effects, seed=seed)
    return asyncio.run(run_validation(drivers, model, name=test, cycles=cycles, progress_stream=Capture(),
                                      adapt=adapt))


def true_inside(result: iso9283.TestResult) -> tuple[int, int, float, float]:
    """(steps whose true error lies within ±2 q_sigma, valid steps, RMS true error, median q_sigma)."""
    pairs = [(s.true_um["x"] - s.step.target_um, sigma)
             for s, sigma in zip(result.steps, result.command_sigma_um, strict=True) if s.valid]
    errors = np.array([e for e, _ in pairs])
    sigmas = np.array([sg for _, sg in pairs])
    return (int(np.sum(np.abs(errors) <= 2.0 * sigmas)), len(pairs), float(np.sqrt(np.mean(errors**2))),
            float(np.median(sigmas)))


def test_every_validation_step_on_the_simulated_cell_knows_the_true_position() -> None:
    result = validate(trained_model(0), "test2", seed=3, cycles=1)
    for step in result.steps:
        measured_minus_true = step.positions_um["x"] - step.true_um["x"]
        assert np.isfinite(step.true_um["x"])
        assert abs(measured_minus_true) < 0.15  # the interferometer's wander and noise, nothing more
    assert result.has_truth and np.isfinite(result.accuracy_true_nm)


def test_two_sigma_holds_the_true_error_in_range_without_claiming_far_more_than_it() -> None:
    """Pooled over calibrations (seeds 0-3, test 2): ±2 q_sigma holds >= 90 % of the true errors, and
    q_sigma is the size of those errors, not several times it (main: 88 nm for a 41 nm error)."""
    inside = steps = 0
    square_errors, sigmas = [], []
    for seed in range(4):
        i, n, rms_um, sigma_um = true_inside(validate(trained_model(seed), "test2", seed=100 * seed + 2, cycles=6))
        inside, steps = inside + i, steps + n
        square_errors.append(rms_um**2)
        sigmas.append(sigma_um)
    assert inside / steps >= 0.90, (inside, steps)
    ratio = float(np.median(sigmas)) / float(np.sqrt(np.mean(square_errors)))  # a run's errors share one offset:
    # judged over the calibrations, not per run. Not 2.0: q_sigma books the calibration's wander as the stage's
    # (one instrument cannot tell them apart, issue 27), and this ideal cell's wander is all the
    # interferometer's, which the true error never carries (seen 2.09 with the wander cut to what varies within
    # the calibration's runs; 3.05 with it whole)
    assert 0.7 < ratio < 2.5, (sigmas, square_errors)


def test_two_sigma_holds_the_true_error_out_of_range_and_on_a_discovery_extended_model() -> None:
    i, n, _, _ = true_inside(validate(trained_model(1), "test5", seed=105, cycles=6))
    assert i / n >= 0.90, (i, n)  # out of range: the curvature allowance covers the bracket's bending
    effect = "creep:c=0.01,tau_s=15"
    data = cell_run(effect, seed=5)
    given = paper_model(data)
    extended = discover(data, given).model
    assert extended.covariance is not None and extended.covariance.wander_um is not None
    i, n, rms_um, sigma_um = true_inside(validate(extended, "test2", seed=11, cycles=6, effects=effect))
    assert i / n >= 0.90 and sigma_um < 2.0 * max(rms_um, 0.010), (i, n, rms_um, sigma_um)
    # the given model (no creep term) on the same run: its error is the creep it lacks. Its q_sigma books
    # the misfit its calibration saw (issue 27: the wander is the stage's as far as one instrument can
    # tell), but the forward sweeps hid most of the creep: fewer steps than a calibrated σ holds, so
    # validate's coverage warning (< 90 %) says so
    i, n, _, _ = true_inside(validate(given, "test2", seed=11, cycles=6, effects=effect))
    assert i / n < 0.9


def test_adaptation_is_scored_against_the_truth_not_only_the_interferometer_it_follows() -> None:
    """The tracker follows the interferometer's wander, so through the interferometer adaptation looks
    better than it is: against the truth it cannot beat the interferometer's own wander."""
    model = trained_model(0)
    adaptive = validate(model, "test2", seed=21, cycles=8, adapt=BiasTracker(600.0, 1.0))
    doc = adaptive.to_dict()
    assert doc["with_comp_true_nm"] == pytest.approx(adaptive.accuracy_true_nm, abs=1e-3)
    assert adaptive.accuracy_true_nm > adaptive.accuracy_nm  # the flattering view is the instrument's
    wander_nm = model.covariance.wander_um * 1e3 if model.covariance and model.covariance.wander_um else 0.0
    assert adaptive.accuracy_true_nm > 0.25 * wander_nm


def test_an_adaptive_runs_sigma_is_what_the_tracker_leaves_and_still_holds_the_truth() -> None:
    """Out of range the static σ allows for the curvature the calibration could not rule out (about
    1 µm on test 5); the tracker takes that error out as it learns, and the σ of its commands says so:
    far narrower than the static one and still holding the true errors (main: the static σ, 1 µm,
    for a 60 nm error)."""
    model = trained_model(1)
    static = validate(model, "test5", seed=105, cycles=20)
    adaptive = validate(model, "test5", seed=105, cycles=20, adapt=BiasTracker(600.0, 1.0))
    inside, n, rms_um, sigma_um = true_inside(adaptive)
    _, _, static_rms_um, static_sigma_um = true_inside(static)
    assert inside / n >= 0.90, (inside, n)
    assert sigma_um < 0.25 * static_sigma_um, (sigma_um, static_sigma_um)
    assert rms_um < 0.5 * static_rms_um  # the tracker did take the error out
    assert adaptive.q_sigma_adapted_um[0] == static.q_sigma_um[0]  # before its first residual: the model's own σ
    assert adaptive.q_sigma_um == static.q_sigma_um  # the model's own σ is still there, unchanged


def test_validate_reports_the_truth_and_warns_when_q_sigma_is_miscalibrated(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "m.json"
    model = trained_model(0)
    save_model(model, path)
    assert main(["validate", "--model", str(path), "--cycles", "2", "--json"]) == 0
    (doc,) = json.loads(capsys.readouterr().out)["tests"]
    assert doc["with_comp_true_nm"] > 0 and 0.0 <= doc["within_2_sigma_true"] <= 1.0
    assert "coverage_warning" in doc
    # a model claiming 100x too little: the warning names it, on stderr and in the JSON
    assert model.covariance is not None
    tiny = type(model.covariance)(model.covariance.matrix * 1e-4, model.covariance.residual_rms_um * 1e-2,
                                  None, 0.0)
    save_model(Model(terms=model.terms, training=model.training, fit=model.fit, covariance=tiny), path)
    assert main(["validate", "--model", str(path), "--cycles", "2", "--json"]) == 0
    out, err = capsys.readouterr()
    (doc,) = json.loads(out)["tests"]
    assert doc["coverage_warning"] and "understates" in doc["coverage_warning"]
    assert "warning: q_sigma is not calibrated" in err
    assert main(["validate", "--model", str(path), "--cycles", "2"]) == 0
    out, _ = capsys.readouterr()
    assert "against the true position (simulated cell): accuracy" in out
