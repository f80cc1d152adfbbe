"""Identification: known models are recovered; the order is chosen on held-out cycles; exclusions hold."""

import numpy as np
import pytest
from helpers.synthetic import TRUE_TERMS, paper_run

from nanodrift.calibration.dataset import concat
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.model.identify import (
    CURVATURE_MIN_SPAN_C,
    FitError,
    candidate_terms,
    curvature_candidates,
    fit,
    holdout_blocks,
)
from nanodrift.model.terms import ChannelSquare


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_fit_recovers_true_coefficients_within_their_standard_errors(seed):
    result = fit(paper_run(seed=seed), order=3)
    coefs = {ft.term.name: ft for ft in result.model.terms}
    for name in ("x^3", "x^2", "x", "T1", "T2", "1"):
        ft = coefs[name]
        assert abs(ft.coef - TRUE_TERMS[name]) < 3.5 * ft.se, (name, ft.coef, ft.se)
    # the paper's stage: first-order thermal terms of the right sign and size
    assert -0.7 < coefs["T1"].coef < -0.5


def test_predict_on_fresh_rows_lands_within_the_noise():
    model = fit(paper_run(seed=10)).model
    fresh = paper_run(seed=11, cycles=8)
    residual = fresh.q - model.predict(fresh)
    assert np.sqrt(np.mean(residual**2)) < 0.02 * 1.2  # noise is 20 nm rms


def test_auto_order_prefers_the_true_order_and_reports_each_tried():
    result = fit(paper_run(seed=5))
    assert result.orders["x"].order == 3
    assert set(result.orders["x"].scores) == {1, 2, 3, 4, 5}
    assert result.orders["x"].scores[1] > 1.5 * result.orders["x"].scores[3]  # too low an order is much worse
    assert result.model.selection["order_holdout_rms_um"]["3"] == result.orders["x"].scores[3]


def test_auto_order_is_not_fooled_by_training_error_on_a_linear_stage():
    linear = {"x": 1.0005, "T1": -0.6, "1": 20.0}
    result = fit(paper_run(seed=6, terms=linear))
    assert result.orders["x"].order <= 2  # x^2.. would only fit the noise
    assert "x^3" not in result.model.term_names()


def test_excluded_channel_never_enters():
    result = fit(paper_run(seed=2), order=3, exclude=["T1"])
    assert "T1" not in result.model.term_names()
    assert "T1" not in result.model.channels
    assert result.model.selection["excluded"] == ["T1"]


def test_holdout_blocks_are_whole_cycles_in_time_order():
    data = paper_run(cycles=12)
    folds = holdout_blocks(data)
    cycles = data.cycles()
    for c in np.unique(cycles):
        assert np.unique(folds[cycles == c]).size == 1  # a cycle is never split
    assert np.all(np.diff(folds) >= 0)  # contiguous in time


def test_bad_requests_are_clear_errors():
    data = paper_run(cycles=2)
    with pytest.raises(FitError, match="penter"):
        fit(data, penter=0.2, premove=0.1)
    with pytest.raises(FitError, match="not in the data"):
        candidate_terms(["T1"], 3, exclude=["T9"])
    data.q = None
    with pytest.raises(FitError, match="no q_um column"):
        fit(data)


def test_rows_marked_invalid_are_ignored():
    data = paper_run(seed=7)
    data.q = data.q.copy()
    data.q[5] += 50.0  # a step averaged over a sensor fault
    valid = np.ones(len(data.q))
    valid[5] = 0
    data.extra["valid"] = valid
    model = fit(data, order=3).model
    assert model.fit["residual_rms_nm"] < 25.0


def test_a_calibration_narrower_than_a_degree_is_offered_no_square():
    """The paper's 0.45 °C calibration: a square fitted there would be the interferometer's wander."""
    data = simulate_dataset("train", cycles=24, seed=3)
    assert max(float(np.ptp(v)) for v in data.channels.values()) < CURVATURE_MIN_SPAN_C
    assert curvature_candidates(data) == []
    model = fit(data).model
    assert not [n for n in model.selection["candidates"] if n.endswith(")^2")]


def test_records_over_degrees_let_the_fit_find_the_bracket_bending():
    """Calibration plus a run 1.5 °C warmer (test 5's room): the squares enter, and fresh runs are predicted
    better than by the same fit with no square on offer (in range: at least down to the noise floor)."""
    calibration = simulate_dataset("train", cycles=24, seed=3)
    warm = simulate_dataset("test5", cycles=30, seed=305)
    both = concat([calibration, warm])
    squares = curvature_candidates(both)
    assert [t.name for t in squares] == ["(T1 - 22.53)^2", "(T2 - 22.41)^2", "(T3 - 22.58)^2", "(T4 - 22.49)^2"]
    curved = fit(both).model
    assert any(isinstance(ft.term, ChannelSquare) for ft in curved.terms), curved.term_names()
    assert curved.covariance is not None and curved.covariance.curvature is None  # the model fits its curvature
    straight = fit(both, squares=False).model  # eq. 3 as the paper wrote it
    assert not any(isinstance(ft.term, ChannelSquare) for ft in straight.terms)
    for scenario, seed in (("test5", 353), ("train", 350), ("test2", 351)):
        fresh = simulate_dataset(scenario, cycles=30, seed=seed)
        rms_curved, rms_straight = (float(np.sqrt(np.mean((fresh.q - m.predict(fresh)) ** 2)))
                                    for m in (curved, straight))
        # measured (coherent selection): 0.42 warm, 0.42 in the calibration's room; in range (test 2) either fit
        # reaches the floor the simulated noise sets (curved 19.8, straight 17.3 nm): there the square may not
        # cost more than that floor
        assert rms_curved < max(0.85 * rms_straight, 0.025), (scenario, rms_curved, rms_straight)


def test_excluded_channel_gets_no_square_either():
    both = concat([simulate_dataset("train", cycles=24, seed=3), simulate_dataset("test5", cycles=30, seed=305)])
    assert "T2" not in {t.channels[0] for t in curvature_candidates(both, exclude=["T2"])}
    model = fit(both, exclude=["T2"]).model
    assert not [n for n in model.selection["candidates"] if "T2" in n]
