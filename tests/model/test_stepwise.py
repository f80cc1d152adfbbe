"""Tests for nanodrift.model.stepwise.stepwisefit against a brute-force reference.

The reference below re-derives every p-value from separate least-squares fits of the full and
reduced models (partial F-test), with no QR-factor tricks, and drives its own stepwise loop.
Regressors are standardised inside the reference fits only to keep lstsq well conditioned; that
is an affine reparametrisation (the intercept is in every model), so SSEs are unchanged.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy import stats

from nanodrift.model.stepwise import StepwiseResult, stepwisefit

# ----------------------------------------------------------------------------------------------
# brute-force reference


def _fit(X: NDArray, y: NDArray, cols: list[int]) -> tuple[NDArray, NDArray, float, float]:
    """OLS of y on [1, X[:, cols]]: (coef, se) in original units, intercept, SSE."""
    n = len(y)
    Xs = X[:, cols]
    mu, sd = Xs.mean(axis=0), Xs.std(axis=0)
    A = np.column_stack([np.ones(n), (Xs - mu) / sd])
    b, *_ = np.linalg.lstsq(A, y, rcond=None)
    b += np.linalg.lstsq(A, y - A @ b, rcond=None)[0]  # one step of iterative refinement
    r = y - A @ b
    sse = float(r @ r)
    dof = n - 1 - len(cols)
    cov = np.linalg.pinv(A.T @ A) * (sse / dof if dof > 0 else np.nan)
    coef = b[1:] / sd
    se = np.sqrt(np.diag(cov)[1:]) / sd
    intercept = float(b[0] - coef @ mu)
    return coef, se, intercept, sse


def _sse(X: NDArray, y: NDArray, cols: list[int]) -> float:
    return _fit(X, y, cols)[3] if cols else float(((y - y.mean()) ** 2).sum())


def _partial_f_p(sse_red: float, sse_full: float, dof_full: int) -> float:
    F = (sse_red - sse_full) / (sse_full / dof_full)
    return float(stats.f.sf(F, 1, dof_full))


def ref_stats(X: NDArray, y: NDArray, state: NDArray) -> dict:
    """MATLAB-semantics coef/se/p for every column, given the in-model mask ``state``."""
    n, p = X.shape
    cols = [int(j) for j in np.flatnonzero(state)]
    dof = n - 1 - len(cols)
    sse = _sse(X, y, cols)
    coef, se, pval = np.full(p, np.nan), np.full(p, np.nan), np.full(p, np.nan)
    if cols:
        c, s, intercept, _ = _fit(X, y, cols)
        coef[cols], se[cols] = c, s
        for j in cols:
            pval[j] = _partial_f_p(_sse(X, y, [c for c in cols if c != j]), sse, dof)
    else:
        intercept = float(y.mean())
    for j in range(p):
        if not state[j]:
            c, s, _, sse_j = _fit(X, y, sorted([*cols, j]))
            k = sorted([*cols, j]).index(j)
            coef[j], se[j] = c[k], s[k]
            pval[j] = _partial_f_p(sse, sse_j, dof - 1)
    return {
        "coef": coef,
        "se": se,
        "pval": pval,
        "intercept": intercept,
        "sse": sse,
        "dof": dof,
        "rmse": np.sqrt(sse / dof),
    }


def ref_stepwise(
    X: NDArray,
    y: NDArray,
    penter: float = 0.05,
    premove: float = 0.10,
    inmodel: NDArray | None = None,
    keep: NDArray | None = None,
    maxiter: int | None = None,
) -> tuple[NDArray, list[tuple[str, int, float]], dict]:
    p = X.shape[1]
    state = np.zeros(p, bool) if inmodel is None else inmodel.copy()
    frozen = np.zeros(p, bool) if keep is None else keep
    history: list[tuple[str, int, float]] = []
    while True:
        st = ref_stats(X, y, state)
        if maxiter is not None and len(history) >= maxiter:
            break
        out = np.flatnonzero(~state & ~frozen)
        if out.size and st["pval"][out].min() < penter:
            j = int(out[np.argmin(st["pval"][out])])
            history.append(("add", j, float(st["pval"][j])))
            state[j] = True
            continue
        members = np.flatnonzero(state & ~frozen)
        if members.size and st["pval"][members].max() > premove:
            j = int(members[np.argmax(st["pval"][members])])
            history.append(("remove", j, float(st["pval"][j])))
            state[j] = False
            continue
        break
    return state, history, st


def _assert_p_close(actual: NDArray | float, expected: NDArray | float) -> None:
    """1e-8 relative; below 1e-20 compare log(p) instead (the tail amplifies rounding by ~t^2)."""
    a, e = np.atleast_1d(actual).astype(float), np.atleast_1d(expected).astype(float)
    assert a.shape == e.shape
    tiny = e < 1e-20
    np.testing.assert_allclose(a[~tiny], e[~tiny], rtol=1e-8, atol=0)
    np.testing.assert_allclose(np.log(a[tiny] + 1e-320), np.log(e[tiny] + 1e-320), rtol=1e-8)


def assert_matches_reference(X: NDArray, y: NDArray, **kw) -> StepwiseResult:
    res = stepwisefit(X, y, **kw)
    ref_kw = {k: (_mask(v, X.shape[1]) if k in ("inmodel", "keep") else v) for k, v in kw.items()}
    state, history, st = ref_stepwise(X, y, **ref_kw)

    assert [(a, c) for a, c, _ in res.history] == [(a, c) for a, c, _ in history]
    _assert_p_close([h[2] for h in res.history], [h[2] for h in history])
    np.testing.assert_array_equal(res.inmodel, state)
    assert res.n_steps == len(history)
    assert res.dof == st["dof"]
    assert not res.rank_deficient.any()

    # coef: relative to its own standard error, so near-zero out-of-model coefs are fair.
    np.testing.assert_allclose(res.coef, st["coef"], rtol=1e-9, atol=0)
    np.testing.assert_allclose(res.se, st["se"], rtol=1e-8, atol=0)
    _assert_p_close(res.pval, st["pval"])
    np.testing.assert_allclose(res.tstat, res.coef / res.se, rtol=1e-12)
    scale = abs(st["intercept"]) + float(np.abs(np.asarray(st["coef"]) * X.mean(axis=0))[state].sum())
    assert res.intercept == pytest.approx(st["intercept"], rel=0, abs=1e-10 * scale + 1e-12)
    assert res.rmse == pytest.approx(st["rmse"], rel=1e-9)
    assert res.sse == pytest.approx(st["sse"], rel=1e-9)
    return res


def _mask(spec, p: int) -> NDArray:
    if spec is None:
        return np.zeros(p, bool)
    arr = np.asarray(spec)
    if arr.dtype == bool:
        return arr.copy()
    m = np.zeros(p, bool)
    m[arr] = True
    return m


# ----------------------------------------------------------------------------------------------
# data sets


def random_design(seed: int = 0, n: int = 150, p: int = 8) -> tuple[NDArray, NDArray]:
    """Correlated Gaussian regressors; true model uses columns 1, 4, 6."""
    rng = np.random.default_rng(seed)
    L = rng.standard_normal((p, p)) * 0.4 + np.eye(p)
    X = rng.standard_normal((n, p)) @ L.T * rng.uniform(0.1, 50, p) + rng.uniform(-100, 100, p)
    y = 3.0 + 1.2 * X[:, 1] / X[:, 1].std() - 0.9 * X[:, 4] / X[:, 4].std() + 0.7 * X[:, 6] / X[:, 6].std()
    return X, y + rng.standard_normal(n)


def thermal_design(seed: int = 1, n: int = 408) -> tuple[NDArray, NDArray]:
    """Position polynomial (x in 0..480 um) + 4 temperatures near 20 degC sharing a slow drift."""
    rng = np.random.default_rng(seed)
    x = np.tile(np.linspace(0.0, 480.0, 51), n // 51 + 1)[:n]
    drift = 0.15 * np.sin(np.linspace(0.0, 4.0, n))
    T = 20.0 + drift[:, None] + 0.01 * rng.standard_normal((n, 4)) + np.array([0.0, 0.4, -0.3, 1.1])
    X = np.column_stack([x, x**2, x**3, T])
    y = 12.0 + 0.05 * x - 2e-5 * x**2 + 2e-8 * x**3 + 4.0 * (T[:, 0] - 20) + 0.05 * rng.standard_normal(n)
    return X, y


HALD_X = np.array(
    [
        [7, 26, 6, 60],
        [1, 29, 15, 52],
        [11, 56, 8, 20],
        [11, 31, 8, 47],
        [7, 52, 6, 33],
        [11, 55, 9, 22],
        [3, 71, 17, 6],
        [1, 31, 22, 44],
        [2, 54, 18, 22],
        [21, 47, 4, 26],
        [1, 40, 23, 34],
        [11, 66, 9, 12],
        [10, 68, 8, 12],
    ],
    dtype=float,
)
HALD_Y = np.array([78.5, 74.3, 104.3, 87.6, 95.9, 109.2, 102.7, 72.5, 93.1, 115.9, 83.8, 113.3, 109.4])


# ----------------------------------------------------------------------------------------------
# agreement with the brute-force reference


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_random_design_matches_reference_and_finds_true_model(seed: int) -> None:
    X, y = random_design(seed)
    res = assert_matches_reference(X, y)
    assert set(np.flatnonzero(res.inmodel)) >= {1, 4, 6}
    assert res.stop_reason == "converged"


def test_thermal_polynomial_design_matches_reference() -> None:
    X, y = thermal_design()
    res = assert_matches_reference(X, y)
    assert res.inmodel[0] and res.inmodel[3]
    # and with looser thresholds, which moves more columns in and out
    assert_matches_reference(X, y, penter=0.3, premove=0.4)


def test_hald_removal_after_additions_matches_reference_and_matlab() -> None:
    res = assert_matches_reference(HALD_X, HALD_Y, penter=0.08)
    assert [(a, c) for a, c, _ in res.history] == [("add", 3), ("add", 0), ("add", 1), ("remove", 3)]
    # Published MATLAB output of stepwisefit(ingredients, heat, 'PEnter', 0.08).
    np.testing.assert_allclose([h[2] for h in res.history], [0.000576232, 1.10528e-06, 0.0516873, 0.205395], rtol=1e-5)
    np.testing.assert_allclose(res.coef, [1.4683, 0.6623, 0.2500, -0.2365], atol=6e-5)
    np.testing.assert_allclose(res.se, [0.1213, 0.0459, 0.1847, 0.1733], atol=6e-5)
    np.testing.assert_allclose(res.pval, [2.6922e-07, 5.0290e-08, 0.2089, 0.2054], rtol=5e-4)
    assert res.intercept == pytest.approx(52.5773, abs=1e-4)
    assert res.rmse == pytest.approx(2.4063, abs=1e-4)
    assert res.dof == 10


def test_hald_default_thresholds() -> None:
    res = assert_matches_reference(HALD_X, HALD_Y)
    np.testing.assert_array_equal(res.inmodel, [True, False, False, True])


@pytest.mark.parametrize(
    "start", [[0, 1, 2, 3, 4, 5, 6], np.array([False, True, True, False, False, False, False]), [2, 5]]
)
def test_nonempty_initial_model(start) -> None:
    X, y = thermal_design(seed=4, n=204)
    res = assert_matches_reference(X, y, inmodel=start)
    assert res.history, "starting model is not the optimum, some step must happen"


def test_full_start_backward_elimination_random() -> None:
    X, y = random_design(seed=5, n=80)
    res = assert_matches_reference(X, y, inmodel=np.ones(X.shape[1], bool))
    assert res.history[0][0] == "remove"


def test_keep_in_and_keep_out() -> None:
    X, y = random_design(seed=6)
    free = stepwisefit(X, y)
    assert free.inmodel[4] and not free.inmodel[0]
    # keep column 0 in (initially in) and column 4 out (initially out)
    res = assert_matches_reference(X, y, inmodel=[0], keep=[0, 4])
    assert res.inmodel[0] and not res.inmodel[4]
    assert all(c not in (0, 4) for _, c, _ in res.history)
    res_mask = stepwisefit(X, y, inmodel=[0], keep=np.isin(np.arange(X.shape[1]), [0, 4]))
    assert res_mask.history == res.history


@pytest.mark.parametrize("maxiter", [0, 1, 2, 3])
def test_maxiter_truncates_history(maxiter: int) -> None:
    full = stepwisefit(HALD_X, HALD_Y, penter=0.08)
    res = assert_matches_reference(HALD_X, HALD_Y, penter=0.08, maxiter=maxiter)
    assert res.history == full.history[:maxiter]
    assert res.n_steps == maxiter
    assert res.stop_reason == "maxiter"
    assert stepwisefit(HALD_X, HALD_Y, penter=0.08, maxiter=4).stop_reason == "converged"


def test_large_sample_uses_blocked_qr_and_matches_reference() -> None:
    rng = np.random.default_rng(7)
    n = 70_000  # more than one QR row-block
    X = rng.standard_normal((n, 5)) * [1.0, 1e3, 1e-3, 5.0, 1.0] + [0.0, 1e4, 20.0, 0.0, 3.0]
    y = 0.02 * X[:, 0] + 2e-4 * X[:, 1] + rng.standard_normal(n)
    res = assert_matches_reference(X, y)
    assert res.inmodel[0] and res.inmodel[1]


# ----------------------------------------------------------------------------------------------
# invariances (would catch unit-mapping bugs)


def test_column_scaling_and_offset_only_change_units() -> None:
    X, y = thermal_design(seed=8)
    base = stepwisefit(X, y)
    scale = np.array([1e-3, 1e4, 1e-6, 10.0, 1.0, 1.0, 1e3])
    shift = np.array([500.0, 0.0, -3.0, 1e3, -20.0, 0.0, 7.0])
    res = stepwisefit(X * scale + shift, 5.0 * y - 3.0)
    assert [(a, c) for a, c, _ in res.history] == [(a, c) for a, c, _ in base.history]
    np.testing.assert_array_equal(res.inmodel, base.inmodel)
    np.testing.assert_allclose(res.pval, base.pval, rtol=1e-7)
    np.testing.assert_allclose(res.coef, 5.0 * base.coef / scale, rtol=1e-7)
    np.testing.assert_allclose(res.se, 5.0 * base.se / scale, rtol=1e-7)
    assert res.rmse == pytest.approx(5.0 * base.rmse, rel=1e-9)


def test_predictions_reproduce_fitted_values() -> None:
    X, y = thermal_design(seed=9)
    res = stepwisefit(X, y)
    yhat = res.intercept + X[:, res.inmodel] @ res.coef[res.inmodel]
    assert np.sqrt(((y - yhat) ** 2).sum() / res.dof) == pytest.approx(res.rmse, rel=1e-8)


# ----------------------------------------------------------------------------------------------
# collinear, constant, degenerate


def _check_deficient(res: StepwiseResult, j: int) -> None:
    assert res.rank_deficient[j]
    assert np.isnan(res.coef[j]) and np.isnan(res.se[j]) and np.isnan(res.tstat[j])
    assert res.pval[j] == 1.0


def test_exact_duplicate_column_never_added() -> None:
    X, y = random_design(seed=10)
    Xd = np.column_stack([X, X[:, 4]])  # column 8 duplicates the true column 4
    res = stepwisefit(Xd, y)
    base = stepwisefit(X, y)
    assert res.inmodel[4] and not res.inmodel[8]
    assert all(c != 8 for _, c, _ in res.history)
    _check_deficient(res, 8)
    assert res.rank_deficient.sum() == 1
    np.testing.assert_array_equal(res.inmodel[:8], base.inmodel)
    np.testing.assert_allclose(res.coef[:8], base.coef, rtol=1e-9)
    np.testing.assert_allclose(res.pval[:8], base.pval, rtol=1e-8)


@pytest.mark.parametrize(("original", "copy"), [(3, 1), (1, 3)])
def test_duplicate_tie_goes_to_lowest_index(original: int, copy: int) -> None:
    rng = np.random.default_rng(11)
    X = rng.standard_normal((100, 5)) * 7.0 + 20.0
    y = 2.0 * X[:, original] + 0.5 * X[:, 4] + rng.standard_normal(100)
    X[:, copy] = X[:, original]
    res = stepwisefit(X, y)
    low, high = sorted((original, copy))
    assert res.history[0][:2] == ("add", low)
    assert res.inmodel[low] and not res.inmodel[high]
    _check_deficient(res, high)
    assert res.coef[low] == pytest.approx(2.0, abs=0.1)


def test_linear_combination_column_never_added() -> None:
    X, y = random_design(seed=12)
    combo = 2.0 * X[:, 1] - 0.5 * X[:, 4] + 7.0  # in span of intercept + true columns 1, 4
    Xc = np.column_stack([X, combo])
    res = stepwisefit(Xc, y)
    base = stepwisefit(X, y)
    assert base.inmodel[1] and base.inmodel[4]
    # Whichever two of {1, 4, 8} enter first, the third is then in their span: flagged, never added.
    dependent = [1, 4, 8]
    assert res.inmodel[dependent].sum() == 2
    (left_out,) = [j for j in dependent if not res.inmodel[j]]
    _check_deficient(res, left_out)
    assert res.rank_deficient.sum() == 1
    added = [c for a, c, _ in res.history if a == "add"]
    assert added.count(left_out) == 0
    # same column space as the model without the extra column => same fit
    np.testing.assert_array_equal(np.delete(res.inmodel, dependent), np.delete(base.inmodel, [1, 4]))
    assert res.rmse == pytest.approx(base.rmse, rel=1e-9)
    assert res.sse == pytest.approx(base.sse, rel=1e-9)


def test_linear_combination_out_of_model_with_its_parents_in() -> None:
    X, y = random_design(seed=12)
    Xc = np.column_stack([X, 2.0 * X[:, 1] - 0.5 * X[:, 4] + 7.0])
    res = stepwisefit(Xc, y, inmodel=[1, 4], penter=0.99, premove=0.999)  # adds anything testable
    assert not res.inmodel[8] and res.inmodel[:8].all()
    _check_deficient(res, 8)


def test_linear_combination_in_initial_model_is_removed() -> None:
    X, y = random_design(seed=12)
    Xc = np.column_stack([X, 2.0 * X[:, 1] - 0.5 * X[:, 4] + 7.0])
    res = stepwisefit(Xc, y, inmodel=[1, 4, 8], maxiter=0)
    _check_deficient(res, 8)  # the later index of the dependent set is the one dropped
    assert res.dof == len(y) - 1 - 2
    ref = ref_stats(X, y, np.isin(np.arange(8), [1, 4]))
    np.testing.assert_allclose(res.coef[[1, 4]], ref["coef"][[1, 4]], rtol=1e-9)
    np.testing.assert_allclose(res.pval[[1, 4]], ref["pval"][[1, 4]], rtol=1e-8)
    # additions take priority (MATLAB); once nothing can enter, the untestable column goes first
    res = stepwisefit(Xc, y, inmodel=[1, 4, 8])
    first_remove = next(h for h in res.history if h[0] == "remove")
    assert first_remove == ("remove", 8, 1.0)
    assert not res.inmodel[8] and ("add", 8) not in [(a, c) for a, c, _ in res.history]


def test_constant_columns_flagged_and_never_added() -> None:
    X, y = thermal_design(seed=13)
    const = np.full((len(y), 2), [20.0, 0.0])
    Xc = np.column_stack([X, const])
    res = stepwisefit(Xc, y, penter=0.99, premove=0.999)  # would add anything testable
    for j in (7, 8):
        _check_deficient(res, j)
        assert not res.inmodel[j]
    assert res.inmodel[:7].all()


def test_constant_column_kept_in_model() -> None:
    X, y = random_design(seed=14)
    Xc = np.column_stack([np.full(len(y), 3.3), X])
    res = stepwisefit(Xc, y, inmodel=[0], keep=[0])
    assert res.inmodel[0]
    _check_deficient(res, 0)
    base = stepwisefit(X, y)
    np.testing.assert_array_equal(res.inmodel[1:], base.inmodel)
    np.testing.assert_allclose(res.coef[1:], base.coef, rtol=1e-9)
    assert res.intercept == pytest.approx(base.intercept, rel=1e-9)


def test_constant_y() -> None:
    X, _ = random_design(seed=15)
    res = stepwisefit(X, np.full(len(X), 4.0))
    assert not res.inmodel.any() and res.history == []
    assert res.intercept == pytest.approx(4.0)
    assert np.all(res.pval == 1.0)


def test_exact_fit_stops_cleanly() -> None:
    X, _ = random_design(seed=16)
    y = 1.0 + 2.0 * X[:, 2] - 3.0 * X[:, 5]
    res = stepwisefit(X, y)
    np.testing.assert_array_equal(np.flatnonzero(res.inmodel), [2, 5])
    np.testing.assert_allclose(res.coef[[2, 5]], [2.0, -3.0], rtol=1e-10)
    assert res.intercept == pytest.approx(1.0, abs=1e-8)
    assert res.rmse == 0.0
    assert np.all(res.pval[~res.inmodel] == 1.0)
    assert np.all(res.pval[res.inmodel] == 0.0)


def test_too_few_rows_does_not_crash() -> None:
    rng = np.random.default_rng(17)
    X = rng.standard_normal((4, 6))
    y = X[:, 0] + 0.01 * rng.standard_normal(4)
    res = stepwisefit(X, y, penter=0.5, premove=0.6)
    assert res.dof >= 1  # a column that would leave dof 0 cannot enter
    assert res.inmodel.sum() <= 2
    # saturated start: excess columns rank deficient, untestable columns get p = 1 and leave
    res = stepwisefit(X, y, inmodel=np.ones(6, bool), maxiter=0)
    assert res.rank_deficient.sum() == 3 and res.dof == 0 and np.isnan(res.rmse)
    assert np.all(res.pval == 1.0)
    res = stepwisefit(X, y, inmodel=np.ones(6, bool))
    assert res.dof >= 1 and res.history[0][0] == "remove"
    one = stepwisefit(X[:1], y[:1])
    assert one.history == [] and one.dof == 0


# ----------------------------------------------------------------------------------------------
# validation and contract


def test_penter_greater_than_premove_raises() -> None:
    X, y = random_design()
    with pytest.raises(ValueError, match="penter"):
        stepwisefit(X, y, penter=0.2, premove=0.1)
    stepwisefit(X, y, penter=0.1, premove=0.1)  # equal is allowed


@pytest.mark.parametrize(
    ("X", "y", "match"),
    [
        (np.ones(10), np.ones(10), "2-D"),
        (np.ones((10, 2, 1)), np.ones(10), "2-D"),
        (np.ones((10, 2)), np.ones(9), "rows"),
        (np.ones((10, 2)), np.ones((10, 2)), "1-D"),
        (np.ones((0, 2)), np.ones(0), "no rows"),
    ],
)
def test_bad_shapes_raise(X, y, match: str) -> None:
    with pytest.raises(ValueError, match=match):
        stepwisefit(X, y)


def test_non_finite_values_raise_and_name_the_culprit() -> None:
    X, y = random_design()
    Xb = X.copy()
    Xb[5, 2] = np.nan
    Xb[9, 6] = np.inf
    with pytest.raises(ValueError, match=r"X contains NaN or inf in column\(s\) \[2, 6\]"):
        stepwisefit(Xb, y)
    yb = y.copy()
    yb[3] = -np.inf
    with pytest.raises(ValueError, match=r"y contains NaN or inf .*row 3"):
        stepwisefit(X, yb)


def test_bad_masks_and_maxiter_raise() -> None:
    X, y = random_design()
    with pytest.raises(ValueError, match="inmodel"):
        stepwisefit(X, y, inmodel=[8])
    with pytest.raises(ValueError, match="keep"):
        stepwisefit(X, y, keep=np.ones(3, bool))
    with pytest.raises(ValueError, match="inmodel"):
        stepwisefit(X, y, inmodel=[0.5])
    with pytest.raises(ValueError, match="maxiter"):
        stepwisefit(X, y, maxiter=-1)


def test_result_is_frozen_and_column_y_accepted() -> None:
    X, y = random_design()
    res = stepwisefit(X, y[:, None])
    assert res.history == stepwisefit(X, y).history
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.rmse = 0.0  # type: ignore[misc]
    with pytest.raises(ValueError):
        res.coef[0] = 1.0
    assert res.inmodel.dtype == bool and res.rank_deficient.dtype == bool
    assert res.coef.shape == res.se.shape == res.pval.shape == (X.shape[1],)
    assert isinstance(res.intercept, float) and isinstance(res.rmse, float)
    assert all(isinstance(c, int) and isinstance(pv, float) for _, c, pv in res.history)

