"""What lets a season of records (a million rows) be fitted on a lab PC, checked against the plain forms.

The row loops these replace are written out here as the reference: the vectorised recurrence, Σ·M of the
noise model and the held-out refits must give what they gave, and the noise model fitted on windows of a
long run must still find the noise the run was made with.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.synthetic import paper_run
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import lfilter

from nanodrift.model.identify import candidate_terms, fit_terms, holdout_blocks, holdout_rms
from nanodrift.model.recurrence import decayed_cumsum
from nanodrift.model.uncertainty import (
    REML_MAX_ROWS,
    REML_WINDOW_ROWS,
    Noise,
    fit_noise,
    noise_gram,
    reml_rows,
)


def looped_cumsum(values: np.ndarray, decay: np.ndarray) -> np.ndarray:
    out = np.empty_like(values)
    acc = np.zeros(values.shape[1:])
    for i in range(values.shape[0]):
        acc = decay[i] * acc + values[i]
        out[i] = acc
    return out


def looped_noise_times(M: np.ndarray, t: np.ndarray, runs: list[slice], noise: Noise) -> np.ndarray:
    """Σ·M as uncertainty.py computed it before: the covariance matrix of white + wander, written out."""
    cov = np.zeros((t.size, t.size))
    for part in runs:
        tt = t[part]
        cov[part, part] = noise.wander_um**2 * np.exp(-np.abs(tt[:, None] - tt[None, :]) / noise.tau_s)
    return cov @ M + noise.white_um**2 * M


@given(st.lists(st.tuples(st.floats(-1e3, 1e3), st.floats(0.0, 1.0)), min_size=1, max_size=60),
       st.booleans())
@settings(max_examples=200, deadline=None)
def test_the_recurrence_equals_its_loop_for_any_factors(rows: list[tuple[float, float]], two_columns: bool) -> None:
    values = np.array([v for v, _ in rows])
    decay = np.array([d for _, d in rows])
    if two_columns:
        values = np.column_stack([values, -2.0 * values + 1.0])
    expected = looped_cumsum(values, decay)
    assert decayed_cumsum(values, decay) == pytest.approx(expected, rel=1e-9, abs=1e-9 * (1 + np.abs(expected).max()))


def test_equal_factors_and_tiny_ones_take_their_own_paths_and_agree_with_the_loop() -> None:
    rng = np.random.default_rng(1)
    values = rng.normal(size=(5000, 3)) * np.array([1.0, 1e8, 1e-3])
    uniform = np.full(5000, math.exp(-0.01))
    uniform[[0, 1200, 3000]] = 0.0  # three runs, each of equal factors: scipy's lfilter
    assert decayed_cumsum(values, uniform) == pytest.approx(looped_cumsum(values, uniform), rel=1e-10)
    uneven = np.exp(-rng.uniform(0.0, 3.0, 5000))  # Π falls below e^-500 within a few hundred rows: chunks
    got, expected = decayed_cumsum(values, uneven), looped_cumsum(values, uneven)
    for column in range(3):  # rounding relative to the column's size (a sum that cancels keeps its absolute error)
        size = float(np.abs(values[:, column]).max())
        assert got[:, column] == pytest.approx(expected[:, column], rel=1e-10, abs=1e-12 * size)


def test_a_decay_of_the_wrong_length_is_refused() -> None:
    with pytest.raises(ValueError, match="one factor per row"):
        decayed_cumsum(np.ones((4, 2)), np.ones(3))


def test_sigma_times_m_equals_the_written_out_covariance_on_irregular_times_and_several_runs() -> None:
    rng = np.random.default_rng(2)
    t = np.cumsum(rng.uniform(1.0, 60.0, 700))
    runs = [slice(0, 250), slice(250, 251), slice(251, 700)]
    M = np.column_stack([np.ones(700), rng.normal(size=700), t / 1e3])
    noise = Noise(white_um=0.02, wander_um=0.03, tau_s=600.0)
    expected = looped_noise_times(M, t, runs, noise)
    assert noise_gram(M, t, runs, noise) == pytest.approx(M.T @ expected, rel=1e-9)


def test_up_to_the_limit_every_row_is_scored_beyond_it_windows_inside_the_runs() -> None:
    runs = [slice(0, 10_000)]
    assert reml_rows(10_000, runs) == (None, runs)
    runs = [slice(0, 50_000), slice(50_000, 51_000), slice(51_000, 300_000)]
    rows, pieces = reml_rows(300_000, runs)
    assert rows is not None and rows.size <= REML_MAX_ROWS
    assert np.all(np.diff(rows) > 0)
    assert sum(p.stop - p.start for p in pieces) == rows.size
    for piece in pieces:  # each piece: consecutive rows of one run
        picked = rows[piece]
        assert np.all(np.diff(picked) == 1) and picked.size <= REML_WINDOW_ROWS
        assert sum(r.start <= picked[0] and picked[-1] < r.stop for r in runs) == 1
    assert rows[0] == 0 and rows[-1] == 299_999  # the windows span the whole season


def test_the_noise_of_a_long_run_is_found_on_its_windows() -> None:
    """60k rows of white noise (20 nm) plus a wander (30 nm, 40 rows): the windowed REML finds both."""
    rng = np.random.default_rng(3)
    n = 60_000
    t = np.arange(n) * 29.0
    a = math.exp(-1.0 / 40.0)
    wander = lfilter([0.03 * math.sqrt(1 - a * a)], [1.0, -a], rng.normal(size=n))
    x = np.resize(np.arange(0.0, 481.0, 30.0), n)
    A = np.column_stack([x, np.ones(n)])
    y = 1.001 * x + 0.02 * rng.normal(size=n) + wander
    models = fit_noise(A, y, t, [slice(0, n)])
    white = math.sqrt(sum(w * m.white_um**2 for w, m in models))
    wandering = math.sqrt(sum(w * m.wander_um**2 for w, m in models))
    tau_rows = sum(w * m.tau_s for w, m in models) / 29.0
    assert white == pytest.approx(0.02, rel=0.1)
    assert wandering == pytest.approx(0.03, rel=0.2)
    assert 20 <= tau_rows <= 80


def test_held_out_scores_are_those_of_full_refits() -> None:
    """The held-out refits keep stepwise's own coefficients: the scores equal a full fit_terms per block."""
    data = paper_run(cycles=18, seed=4)
    pool = candidate_terms(list(data.channels), 3)
    score, folds = holdout_rms(data, pool, 0.05, 0.10)
    blocks = holdout_blocks(data)
    q = np.asarray(data.q)
    errors = []
    for k in np.unique(blocks):
        model = fit_terms(data.select(blocks != k), pool, uncertainty=False)
        errors.append(q[blocks == k] - model.predict(data.select(blocks == k)))
    assert folds == np.unique(blocks).size
    assert score == pytest.approx(float(np.sqrt(np.mean(np.concatenate(errors) ** 2))), rel=1e-9)

