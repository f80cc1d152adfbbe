"""Stepwise linear regression with MATLAB ``stepwisefit`` semantics.

Why a QR factor and not the Gram matrix: the candidate terms (x, x^2, x^3 with x up to 480 um,
temperatures near 20 degC that barely move) are badly scaled and strongly correlated. Forming
X'X squares the condition number, and then an exact duplicate column leaves a residual of about
1e-8 instead of 1e-16, so collinearity cannot be told apart from a real (small) effect.
Instead, the centred data [X - mean, y - mean] is reduced ONCE to its small (p+1)x(p+1)
triangular factor R (Householder QR, in row chunks so no n x p copy is made). Because the data
equals Q R with orthonormal Q, every regression of y on any subset of columns gives exactly the
same coefficients and residual norms when run on R's columns, so each step costs a QR of a
matrix of at most 11 x 10, with no pass over the n rows. Columns of R are scaled to unit norm,
which is the same as standardising the data (QR commutes with column scaling), and results are
mapped back to original units at the end.

One module of ~450 lines on purpose: it is one algorithm (MATLAB's), read and checked against
MATLAB's documentation as a whole; split, its steps would be harder to compare line by line.

``hac_lag``: the same loop with every entry and removal test a Wald t-test under the Newey-West (HAC)
covariance (:mod:`nanodrift.model.hac`) instead of the iid partial F-test. On autocorrelated residuals
(a calibration's) the iid test calls channels significant that the data cannot separate. The
coefficients are the same least-squares ones; only standard errors and p-values change. These tests
need the rows (the QR factor has lost their order), so this mode keeps a centred, scaled n x p copy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal, TypeVar

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy import linalg

from nanodrift.model.hac import andrews_lag, hac_covariance, hac_meat, t_p_values

__all__ = ["RANK_TOL", "StepwiseResult", "stepwisefit"]

RANK_TOL: float = 1e-10
"""Relative tolerance for rank decisions. A column is *constant* when
||x - mean|| <= RANK_TOL * ||x||, and *collinear* with a model when the norm of its residual after
projection on the intercept and the model's columns is <= RANK_TOL * ||x - mean||. The residual of
y is taken as exactly zero (perfect fit) when its norm is <= RANK_TOL * ||y - mean||."""

_TIE_RTOL: float = 1e-10
"""|t| values this close (relative) count as a tie, resolved by the lowest column index; exact
duplicates of a column differ in the last bits after QR, and must still tie deterministically."""

_CHUNK_ROWS: int = 32768
"""Rows per block of the tall-skinny QR; keeps the temporary centred copy small for 1e6 rows."""

StopReason = Literal["converged", "maxiter", "cycle"]


@dataclass(frozen=True, eq=False)
class StepwiseResult:
    """Outcome of :func:`stepwisefit`; arrays have one entry per column of X and are read-only.

    For an in-model column, ``coef``/``se``/``tstat``/``pval`` come from the final model. For an
    out-of-model column they are what it would get if it alone were added to the final model
    (MATLAB semantics). Conventions for columns that cannot be tested:

    * rank deficient (constant, or in the span of the intercept and the other estimable model
      columns): ``coef = se = tstat = NaN``, ``pval = 1.0`` and ``rank_deficient`` is True. Such a
      column is never added; if it is in the model (via ``inmodel``), it is the first one removed
      (unless kept), and it does not count in ``dof``.
    * no residual degree of freedom left (too few rows): ``coef`` is still given if estimable,
      ``se = tstat = NaN`` and ``pval = 1.0``, so the column cannot enter.
    * exact fit of y (residual norm <= RANK_TOL * ||y - mean||): residual taken as zero, in-model
      columns get ``se = 0, pval = 0``; out-of-model columns ``coef = se = tstat = 0, pval = 1``.
    """

    inmodel: NDArray[np.bool_]
    coef: NDArray[np.float64]
    se: NDArray[np.float64]
    tstat: NDArray[np.float64]
    pval: NDArray[np.float64]
    rank_deficient: NDArray[np.bool_]
    intercept: float
    rmse: float
    """sqrt(sse / dof); NaN when dof == 0."""
    sse: float
    dof: int
    """n - 1 - (number of estimable in-model columns)."""
    n_steps: int
    history: list[tuple[str, int, float]]
    """(``"add"`` | ``"remove"``, 0-based column, p-value that triggered the action), in order."""
    stop_reason: StopReason
    """``"converged"`` (no eligible action), ``"maxiter"``, or ``"cycle"`` (the next action would
    have revisited an earlier model, so it was not taken)."""


@dataclass(frozen=True)
class _Fit:
    """Per-step statistics in standardised units (unit-norm centred columns and y)."""

    coef: NDArray[np.float64]
    se: NDArray[np.float64]
    tstat: NDArray[np.float64]
    pval: NDArray[np.float64]
    deficient: NDArray[np.bool_]
    testable: NDArray[np.bool_]
    sse: float
    dof: int


def stepwisefit(
    X: ArrayLike,
    y: ArrayLike,
    *,
    penter: float = 0.05,
    premove: float = 0.10,
    inmodel: ArrayLike | Sequence[int] | None = None,
    keep: ArrayLike | Sequence[int] | None = None,
    maxiter: int | None = None,
    hac_lag: int | Literal["andrews"] | None = None,
    run_id: ArrayLike | None = None,
) -> StepwiseResult:
    """Forward/backward stepwise regression of y on the columns of X (intercept always included).

    Each step takes ONE action: add the out-of-model column with the smallest entrance p-value
    (partial F-test, i.e. two-sided t-test in model + {j}) if it is < ``penter``; otherwise remove
    the in-model column with the largest t-test p-value if it is > ``premove``; otherwise stop.
    Ties go to the lowest column index. Since all candidates of a step share the same degrees of
    freedom, they are ranked by |t| (p-values underflow to 0 for strong effects on 1e6 rows).

    Args:
        X: n x p design, without a constant column.
        y: n responses.
        penter: entrance threshold; must be <= ``premove`` (MATLAB's rule), otherwise a column
            could be added and then removed again at the same p-value.
        premove: removal threshold.
        inmodel: initial model, as a bool mask of length p or a list of 0-based indices.
        keep: columns frozen in their initial state (never added nor removed); mask or indices.
        maxiter: maximum number of actions (default: unlimited). A repeated model also stops.
        hac_lag: None (default): MATLAB's iid partial F-tests, exactly. An integer L >= 0: every test,
            and the returned ``se``/``tstat``/``pval``, use the Newey-West covariance with lag L;
            ``"andrews"``: L chosen at each step from the current model's residual
            (:func:`nanodrift.model.hac.andrews_lag`).
        run_id: with ``hac_lag``, a run number per row; rows of different runs are taken as independent.

    See :class:`StepwiseResult` for the outputs and the conventions on untestable columns.
    """
    Xa, ya = _validate_data(X, y)
    n, p = Xa.shape
    penter_f, premove_f = _validate_thresholds(penter, premove)
    max_steps = _validate_maxiter(maxiter)
    state = _as_mask(inmodel, p, "inmodel")
    frozen = _as_mask(keep, p, "keep")

    R, x_mean, x_scale, constant, y_mean, y_scale = _reduce(Xa, ya)
    rows = None if hac_lag is None else _hac_rows(Xa, ya, x_mean, x_scale, y_mean, y_scale, hac_lag, run_id)

    history: list[tuple[str, int, float]] = []
    seen = {state.tobytes()}
    stop_reason: StopReason = "converged"
    while True:
        fit = _evaluate(R, state, constant, n)
        if rows is not None:
            fit = _with_hac(fit, state, rows)
        action = _next_action(fit, state, frozen, penter_f, premove_f)
        if action is None:  # stop_reason stays "converged"
            break
        if len(history) >= max_steps:
            stop_reason = "maxiter"
            break
        kind, col, pv = action
        new_state = state.copy()
        new_state[col] = kind == "add"
        if new_state.tobytes() in seen:
            stop_reason = "cycle"
            break
        seen.add(new_state.tobytes())
        state = new_state
        history.append((kind, col, pv))

    # Back to original units: x_z = (x - mean)/x_scale, y_z = (y - mean)/y_scale.
    unit = y_scale / x_scale
    coef = fit.coef * unit
    se = fit.se * unit
    est_in = state & ~fit.deficient
    intercept = float(y_mean - np.dot(coef[est_in], x_mean[est_in]))
    sse = float(fit.sse * y_scale**2)
    rmse = math.sqrt(sse / fit.dof) if fit.dof > 0 else math.nan

    return StepwiseResult(
        inmodel=_readonly(state),
        coef=_readonly(coef),
        se=_readonly(se),
        tstat=_readonly(fit.tstat.copy()),
        pval=_readonly(fit.pval.copy()),
        rank_deficient=_readonly(fit.deficient.copy()),
        intercept=intercept,
        rmse=rmse,
        sse=sse,
        dof=fit.dof,
        n_steps=len(history),
        history=history,
        stop_reason=stop_reason,
    )


# ----------------------------------------------------------------------------------------------
# validation


def _validate_data(X: ArrayLike, y: ArrayLike) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Return float64 copies-or-views of X (n x p) and y (n,), rejecting anything non-finite."""
    if np.iscomplexobj(X) or np.iscomplexobj(y):
        raise ValueError("stepwisefit: X and y must be real, got complex values")
    try:
        Xa = np.asarray(X, dtype=np.float64)
        ya = np.asarray(y, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"stepwisefit: X and y must be numeric arrays ({exc})") from exc
    if Xa.ndim != 2:
        raise ValueError(f"stepwisefit: X must be 2-D (n rows x p columns), got shape {Xa.shape}")
    n, _ = Xa.shape
    if ya.ndim == 2 and ya.shape[1] == 1:
        ya = ya[:, 0]
    if ya.ndim != 1:
        raise ValueError(f"stepwisefit: y must be 1-D (or n x 1), got shape {ya.shape}")
    if ya.shape[0] != n:
        raise ValueError(f"stepwisefit: y has {ya.shape[0]} values but X has {n} rows")
    if n == 0:
        raise ValueError("stepwisefit: X and y have no rows")
    bad_cols = np.flatnonzero(~np.isfinite(Xa).all(axis=0))
    if bad_cols.size:
        raise ValueError(f"stepwisefit: X contains NaN or inf in column(s) {bad_cols.tolist()}")
    bad_rows = np.flatnonzero(~np.isfinite(ya))
    if bad_rows.size:
        raise ValueError(f"stepwisefit: y contains NaN or inf ({bad_rows.size} value(s), first at row {bad_rows[0]})")
    return Xa, ya


def _validate_thresholds(penter: float, premove: float) -> tuple[float, float]:
    pe, pr = float(penter), float(premove)
    if not (math.isfinite(pe) and math.isfinite(pr)):
        raise ValueError(f"stepwisefit: penter ({penter}) and premove ({premove}) must be finite")
    if pe > pr:
        raise ValueError(
            f"stepwisefit: penter ({pe}) must be <= premove ({pr}); otherwise a column could be "
            "added and then immediately removed (same rule as MATLAB stepwisefit)"
        )
    return pe, pr


def _validate_maxiter(maxiter: int | None) -> float:
    if maxiter is None or (isinstance(maxiter, float) and math.isinf(maxiter) and maxiter > 0):
        return math.inf
    if isinstance(maxiter, bool) or not isinstance(maxiter, int | np.integer) or maxiter < 0:
        raise ValueError(f"stepwisefit: maxiter must be a non-negative integer or None, got {maxiter!r}")
    return float(maxiter)


def _as_mask(spec: ArrayLike | Sequence[int] | None, p: int, name: str) -> NDArray[np.bool_]:
    """Accept a bool mask of length p or 0-based column indices (a bool dtype means mask)."""
    mask = np.zeros(p, dtype=bool)
    if spec is None:
        return mask
    arr = np.atleast_1d(np.asarray(spec))
    if arr.dtype == np.bool_:
        if arr.shape != (p,):
            raise ValueError(f"stepwisefit: {name} mask must have length {p}, got shape {arr.shape}")
        return arr.copy()
    if arr.size == 0:
        return mask
    if arr.ndim != 1 or not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"stepwisefit: {name} must be a bool mask or a 1-D list of column indices")
    if (arr < 0).any() or (arr >= p).any():
        raise ValueError(f"stepwisefit: {name} has column indices outside 0..{p - 1}: {arr.tolist()}")
    mask[arr] = True
    return mask


_S = TypeVar("_S", bound=np.generic)


def _readonly(a: NDArray[_S]) -> NDArray[_S]:
    a.setflags(write=False)
    return a


# ----------------------------------------------------------------------------------------------
# numerics


def _reduce(
    X: NDArray[np.float64], y: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], NDArray[np.bool_], float, float]:
    """Centre [X, y], reduce it to its triangular QR factor, scale its columns to unit norm.

    The QR is blocked by rows (TSQR: stack the blocks' R factors, factor again), which gives the
    same R up to signs without materialising an n x (p+1) centred copy.
    """
    n, p = X.shape
    x_mean = X.mean(axis=0)
    y_mean = float(y.mean())
    blocks: list[NDArray[np.float64]] = []
    for start in range(0, n, _CHUNK_ROWS):
        stop = min(start + _CHUNK_ROWS, n)
        B = np.empty((stop - start, p + 1), order="F")
        np.subtract(X[start:stop], x_mean, out=B[:, :p])
        np.subtract(y[start:stop], y_mean, out=B[:, p])
        blocks.append(_r_factor(B))
    R = blocks[0] if len(blocks) == 1 else _r_factor(np.vstack(blocks))

    # ||A e_j|| = ||R e_j|| since A = QR; ||x||^2 = ||x - mean||^2 + n mean^2.
    centred_norm = np.linalg.norm(R, axis=0)
    raw_norm = np.sqrt(centred_norm**2 + n * np.append(x_mean, y_mean) ** 2)
    flat = centred_norm <= RANK_TOL * raw_norm
    scale = np.where(flat, 1.0, centred_norm)
    R = R / scale
    R[:, flat] = 0.0  # constant columns (and constant y) carry rounding noise only
    return R, x_mean, scale[:p], flat[:p], y_mean, float(scale[p])


def _r_factor(B: NDArray[np.float64]) -> NDArray[np.float64]:
    # mode "raw": the same factorisation, but scipy's mode "r" would also zero a full rows x columns copy of it
    r = linalg.qr(B, mode="raw", overwrite_a=True, check_finite=False)[1]
    return np.asarray(r[: min(B.shape)], dtype=np.float64)


def _evaluate(R: NDArray[np.float64], state: NDArray[np.bool_], constant: NDArray[np.bool_], n: int) -> _Fit:
    """Statistics of the model ``state`` (plus intercept) and of each single-column addition."""
    m, p1 = R.shape
    p = p1 - 1
    deficient = constant.copy()

    # Estimable in-model columns, greedily in index order: a column whose residual on the
    # previously accepted ones is below tolerance is dropped and the factorisation redone.
    cols = [j for j in np.flatnonzero(state) if not constant[j]]
    while True:
        k = len(cols)
        if k == 0:
            Q = np.eye(m)
            Rk = np.zeros((0, 0))
            break
        Q, Rs = np.linalg.qr(R[:, cols], mode="complete")
        diag = np.abs(np.diag(Rs))
        bad = np.flatnonzero(diag <= RANK_TOL)
        if bad.size:
            drop = int(bad[0])
        elif k > m:
            drop = m
        else:
            Rk = Rs[:k, :k]
            break
        deficient[cols[drop]] = True
        del cols[drop]

    T = Q.T @ R  # rotated data: rows [:k] span the model, rows [k:] its orthogonal complement
    dof = n - 1 - k
    r = T[k:, p].copy()  # residual of y (coordinates in the complement)
    if np.linalg.norm(r) <= RANK_TOL * np.linalg.norm(R[:, p]):
        r[:] = 0.0
    sse = float(r @ r)

    coef = np.full(p, np.nan)
    se = np.full(p, np.nan)
    col_dof = np.zeros(p, dtype=np.int64)

    if k:
        idx = np.asarray(cols)
        inv = linalg.solve_triangular(Rk, np.eye(k), check_finite=False)
        coef[idx] = inv @ T[:k, p]
        col_dof[idx] = dof
        if dof > 0:
            se[idx] = math.sqrt(sse / dof) * np.sqrt(np.einsum("ij,ij->i", inv, inv))

    out = np.flatnonzero(~state & ~constant)
    if out.size:
        # Frisch-Waugh-Lovell: adding x_j to the model = regressing the residual of y on the
        # residual of x_j; both live in the complement rows of T.
        xr = T[k:, out]
        xnorm = np.linalg.norm(xr, axis=0)
        ok = xnorm > RANK_TOL
        deficient[out[~ok]] = True
        out, xr, xnorm = out[ok], xr[:, ok], xnorm[ok]
        b = (r @ xr) / xnorm**2
        coef[out] = b
        col_dof[out] = dof - 1
        if dof - 1 > 0:
            resid = r[:, None] - xr * b
            se[out] = np.sqrt(np.einsum("ij,ij->j", resid, resid) / (dof - 1)) / xnorm

    testable = ~deficient & (col_dof > 0)
    tstat = np.full(p, np.nan)
    pval = np.ones(p)
    if testable.any():
        tstat[testable], pval[testable] = t_p_values(coef[testable], se[testable], col_dof[testable])
    return _Fit(coef, se, tstat, pval, deficient, testable, sse, dof)


@dataclass(frozen=True)
class _HacRows:
    """The standardised rows the HAC tests need (same units as R's columns)."""

    Z: NDArray[np.float64]
    yz: NDArray[np.float64]
    lag: int | None
    """None: Andrews' plug-in from each step's residual."""
    run_id: NDArray[np.int64] | None


def _hac_rows(X: NDArray[np.float64], y: NDArray[np.float64], x_mean: NDArray[np.float64],
              x_scale: NDArray[np.float64], y_mean: float, y_scale: float, lag: int | str,
              run_id: ArrayLike | None) -> _HacRows:
    if lag != "andrews" and (isinstance(lag, bool) or not isinstance(lag, int | np.integer) or lag < 0):
        raise ValueError(f"stepwisefit: hac_lag must be a non-negative integer, 'andrews' or None, got {lag!r}")
    ids = None
    if run_id is not None:
        ids = np.asarray(run_id, dtype=np.int64)
        if ids.shape != y.shape:
            raise ValueError(f"stepwisefit: run_id has shape {ids.shape}, expected one per row {y.shape}")
    return _HacRows((X - x_mean) / x_scale, (y - y_mean) / y_scale, None if lag == "andrews" else int(lag), ids)


def _with_hac(fit: _Fit, state: NDArray[np.bool_], rows: _HacRows) -> _Fit:
    """``fit`` with the testable columns' se/t/p replaced by HAC Wald tests (same coefficients).

    In-model columns: the model's HAC covariance. An out-of-model column j: by Frisch-Waugh-Lovell its
    row of (AᵀA)⁻¹Aᵀ in model + {j} is x̃ⱼᵀ/‖x̃ⱼ‖² (x̃ⱼ: x_j's residual on the model), so its HAC
    variance needs only that vector and the residual of model + {j}: one pass over the rows each.
    """
    n = rows.yz.shape[0]
    se = fit.se.copy()
    members = np.flatnonzero(state & ~fit.deficient)
    k = members.size
    A = rows.Z[:, members]
    Q = np.linalg.qr(A)[0] if k else np.zeros((n, 0))
    resid = rows.yz - A @ fit.coef[members] if k else rows.yz.copy()
    if fit.sse == 0.0:
        resid[:] = 0.0
    lag = andrews_lag(resid, rows.run_id) if rows.lag is None else rows.lag
    if k:
        cov = hac_covariance(A, resid, lag, n_params=k + 1, run_id=rows.run_id)
        se[members] = np.sqrt(np.maximum(np.diag(cov), 0.0))
    for j in np.flatnonzero(~state & fit.testable):
        x = rows.Z[:, j] - Q @ (Q.T @ rows.Z[:, j])
        norm2 = float(x @ x)
        a = x / norm2
        e = resid - x * (float(a @ resid))
        meat = hac_meat(a * e, lag, rows.run_id)[0, 0]
        se[j] = math.sqrt(max(meat, 0.0) * (n / (n - k - 2) if n > k + 2 else 1.0))
    testable = fit.testable
    tstat, pval = fit.tstat.copy(), fit.pval.copy()
    col_dof = np.where(state, fit.dof, fit.dof - 1)
    tstat[testable], pval[testable] = t_p_values(fit.coef[testable], se[testable], col_dof[testable])
    return _Fit(fit.coef, se, tstat, pval, fit.deficient, testable, fit.sse, fit.dof)


def _next_action(
    fit: _Fit, state: NDArray[np.bool_], frozen: NDArray[np.bool_], penter: float, premove: float
) -> tuple[str, int, float] | None:
    """MATLAB's rule: best entry if p < penter, else worst in-model column if p > premove."""
    # Untestable columns rank as p = 1: never the best entrant, always the worst member.
    score = np.where(fit.testable, np.abs(fit.tstat), -np.inf)

    candidates = np.flatnonzero(~state & ~frozen)
    if candidates.size:
        j = _pick(candidates, score[candidates], best="max")
        if fit.pval[j] < penter:
            return ("add", j, float(fit.pval[j]))

    members = np.flatnonzero(state & ~frozen)
    if members.size:
        j = _pick(members, score[members], best="min")
        if fit.pval[j] > premove:
            return ("remove", j, float(fit.pval[j]))
    return None


def _pick(cols: NDArray[np.intp], score: NDArray[np.float64], best: Literal["max", "min"]) -> int:
    """Column with the extreme score; near-ties (relative _TIE_RTOL) go to the lowest index."""
    target = score.max() if best == "max" else score.min()
    if math.isfinite(target):
        tied = np.abs(score - target) <= _TIE_RTOL * abs(target)
    else:
        tied = score == target
    return int(cols[np.flatnonzero(tied)[0]])
