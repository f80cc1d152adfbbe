"""HAC (Newey-West) standard errors: equal to statsmodels' and honest about a calibration's spread.

statsmodels is an independent oracle here (the test extra installs it): ``OLS(...).fit(cov_type="HAC",
cov_kwds={"maxlags": L, "kernel": "bartlett", "use_correction": True}, use_t=True)`` with the same L.
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.model import hac
from nanodrift.model.describe import describe_model
from nanodrift.model.identify import fit, fit_terms, ols
from nanodrift.model.model import Model, load_model, save_model
from nanodrift.model.segments import features
from nanodrift.model.stepwise import stepwisefit
from nanodrift.model.terms import Channel, Power


def _statsmodels() -> ModuleType:
    """``statsmodels.api``, imported where a test compares with it: at the top of this file every pytest-xdist
    worker paid its 1.5 s of CPU (pandas, scipy.stats) only to collect the file, to run it on one of them."""
    import statsmodels.api

    return statsmodels.api


def _oracle(X: np.ndarray, y: np.ndarray, lag: int):
    sm = _statsmodels()
    return sm.OLS(y, sm.add_constant(X)).fit(
        cov_type="HAC", cov_kwds={"maxlags": lag, "kernel": "bartlett", "use_correction": True}, use_t=True)


def _autocorrelated_data(seed: int, n: int = 300, p: int = 4) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    X = np.cumsum(rng.normal(size=(n, p)), axis=0) + rng.normal(size=(n, p))
    noise = np.zeros(n)
    for i in range(1, n):  # AR(1) residual, as a wandering interferometer leaves
        noise[i] = 0.9 * noise[i - 1] + rng.normal()
    return X, X @ np.linspace(0.5, -1.0, p) + 3.0 + noise


@given(seed=st.integers(0, 2**32 - 1), lag=st.integers(0, 60))
@settings(max_examples=examples(25), deadline=None)
def test_ols_hac_standard_errors_and_p_values_equal_statsmodels(seed, lag):
    X, y = _autocorrelated_data(seed)
    ref = _oracle(X, y, lag)
    Z = _statsmodels().add_constant(X)
    cov = hac.hac_covariance(Z, y - Z @ ref.params, lag)
    np.testing.assert_allclose(np.sqrt(np.diag(cov)), ref.bse, rtol=1e-8)


@pytest.mark.parametrize("seed", range(4))
def test_fit_printed_standard_errors_are_statsmodels_hac_with_the_stated_lag(seed):
    X, y = _autocorrelated_data(seed)
    fitted = ols(X, y)
    ref = _oracle(X, y, fitted.hac_lag)
    np.testing.assert_allclose([*fitted.se, fitted.intercept_se], [*ref.bse[1:], ref.bse[0]], rtol=1e-8)
    np.testing.assert_allclose([*fitted.p, fitted.intercept_p], [*ref.pvalues[1:], ref.pvalues[0]], rtol=1e-6)
    assert fitted.hac_lag == hac.andrews_lag(ref.resid)
    assert fitted.hac_lag > 5  # strongly autocorrelated: far beyond a fixed small lag


def test_stepwise_hac_tests_equal_statsmodels_for_kept_and_left_out_terms():
    X, y = _autocorrelated_data(7, p=5)
    lag = 12
    res = stepwisefit(X, y, inmodel=[0, 1, 2], keep=[0, 1, 2, 3, 4], hac_lag=lag)
    full = _oracle(X[:, [0, 1, 2]], y, lag)
    np.testing.assert_allclose(res.se[:3], full.bse[1:], rtol=1e-8)
    np.testing.assert_allclose(res.pval[:3], full.pvalues[1:], rtol=1e-6)
    for j in (3, 4):  # out of the model: what it would get if added alone
        added = _oracle(X[:, [0, 1, 2, j]], y, lag)
        assert res.coef[j] == pytest.approx(added.params[4], rel=1e-9)
        assert res.se[j] == pytest.approx(added.bse[4], rel=1e-8)
        assert res.pval[j] == pytest.approx(added.pvalues[4], rel=1e-6)


def test_hac_ignores_products_across_runs():
    X, y = _autocorrelated_data(3, n=200, p=2)
    Z = _statsmodels().add_constant(X)
    resid = y - Z @ np.linalg.lstsq(Z, y, rcond=None)[0]
    ids = np.repeat([0, 1], 100)
    together = hac.hac_meat(Z * resid[:, None], 10, ids)
    apart = hac.hac_meat(Z[:100] * resid[:100, None], 10) + hac.hac_meat(Z[100:] * resid[100:, None], 10)
    np.testing.assert_allclose(together, apart, rtol=1e-12)


def test_paper_selection_is_matlab_and_hac_selection_uses_its_own_tests():
    data = simulate_dataset("train", seed=3)
    paper = fit(data, order=3, selection="paper", squares=False).model
    hac_model = fit(data, order=3, selection="hac", squares=False).model
    assert paper.selection["mode"] == "paper" and "partial F" in paper.selection["test"]
    assert hac_model.selection["mode"] == "hac" and "HAC" in hac_model.selection["test"]
    pool = [Power(3), Power(2), Power(1), *(Channel(c) for c in data.channels)]
    X = np.column_stack([features(t, data) for t in pool])
    matlab = stepwisefit(X, np.asarray(data.q))
    names = ["x^3", "x^2", "x", *data.channels]
    assert sorted(paper.term_names()) == sorted([*(n for n, kept in zip(names, matlab.inmodel, strict=True) if kept),
                                                 "1"])
    assert [h["p"] for h in paper.selection["history"]] == pytest.approx([p for _, _, p in matlab.history])


def _one_channel_fit(seed: int) -> Model:
    terms = [Power(3), Power(2), Power(1), Channel("T1")]
    return fit_terms(simulate_dataset("train", seed=seed), terms, always=terms, uncertainty=False)


def test_seed_to_seed_spread_of_a_coefficient_matches_the_standard_error_printed():
    """Ten independent calibrations of the simulated cell (simulated clock, seeds 0..9), one model form:
    the spread of T1's coefficient over them is what its printed SE claims (0.5-2x). The iid SE was 7x too small."""
    fits = [_one_channel_fit(seed) for seed in range(10)]
    coef = [next(ft.coef for ft in m.terms if ft.term.name == "T1") for m in fits]
    se = [next(ft.se for ft in m.terms if ft.term.name == "T1") for m in fits]
    ratio = statistics.stdev(coef) / statistics.median(se)
    assert 0.5 <= ratio <= 2.0, (ratio, coef, se)
    assert all("Newey-West HAC" in m.fit["se_method"] for m in fits)


def test_a_model_file_from_before_hac_loads_keeps_its_id_and_says_its_ses_are_iid():
    """The model file is extended, not renamed: an old file (no ``se_method``) loads with its id, and the
    printout does not pass its textbook SEs off as HAC ones."""
    path = Path(__file__).parent / "data" / "default_model_before_hac.json"  # the model shipped until the default
    # selection became coherent, fitted before HAC standard errors
    assert "se_method" not in json.loads(path.read_text())["fit"]
    model = load_model(path)  # checks its id against its content
    assert model.id == json.loads(path.read_text())["id"]
    text = describe_model(model)
    assert "SE and p: iid (a model file from before HAC standard errors)" in text
    assert "Newey-West" not in text


def test_the_model_file_records_the_se_method_and_the_iid_figures_beside_it(tmp_path):
    model = _one_channel_fit(0)
    save_model(model, tmp_path / "m.json")
    doc = json.loads((tmp_path / "m.json").read_text())
    assert doc["fit"]["se_method"] == hac.describe(doc["fit"]["hac_lag"])
    t1 = next(t for t in doc["terms"] if t["term"] == "T1")
    assert t1["se"] > 3 * doc["fit"]["iid"]["T1"]["se"]  # the autocorrelated residual: HAC far above iid
    assert load_model(tmp_path / "m.json").fit["se_method"] == doc["fit"]["se_method"]
