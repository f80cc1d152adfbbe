"""Identification (paper section II.C): stepwise selection of eq. 3's terms from recorded data.

Candidates are ``x^1..x^n1`` and every temperature channel not excluded, plus a channel's square
``(T2 - 22.05)^2`` where the data spans at least 1 °C of it (days of recorded operation: the curvature a
0.5 °C calibration cannot see); the bias is always in.
The geometric order n1 cannot be chosen by training error (it always falls with order), so
``order="auto"`` picks it by the error on held-out blocks of the run: whole calibration cycles.
Several runs fitted together (calibration plus recorded operation) keep their own time: features
restart at each run's first row and no held-out block spans two runs (:mod:`nanodrift.model.segments`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Collection, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Generic, TypedDict, TypeVar, Unpack

import numpy as np

from nanodrift.model import hac
from nanodrift.model.axis_terms import AxisProduct
from nanodrift.model.cell_model import CellModel, one_axis
from nanodrift.model.model import FittedTerm, Model, Training, json_float
from nanodrift.model.provenance import created_now, software
from nanodrift.model.segments import design_matrix, runs
from nanodrift.model.series import CellSeries, Series
from nanodrift.model.stepwise import StepwiseResult, stepwisefit
from nanodrift.model.terms import Bias, Channel, ChannelSquare, Power, Term
from nanodrift.model.uncertainty import Covariance, estimate

MAX_AUTO_ORDER = 5
#: a channel's square is a candidate only where the data spans at least this much of it (°C). The
#: curvature's sagitta over a span s is k2·s²/4: over the paper's 0.5 °C calibration the bracket's
#: -0.4 µm/°C² bends 25 nm, no more than the interferometer's wander, so a square fitted there is that
#: wander, extrapolated quadratically; over 1 °C it is 100 nm, over a week's 2.7 °C 0.7 µm.
CURVATURE_MIN_SPAN_C = 1.0


class FitError(ValueError):
    """The data cannot support the requested fit; the message says why."""


@dataclass(frozen=True)
class OrderChoice:
    """An axis' geometric order n1: the one chosen, the held-out RMS (um) of every order tried (empty when the
    order was fixed) and how many held-out blocks scored them."""

    order: int
    scores: dict[int, float] = field(default_factory=dict)
    folds: int = 0


#: the model an identification gives: one axis' :class:`Model`, or a cell's :class:`CellModel`
FittedModel = TypeVar("FittedModel", Model, CellModel)


@dataclass
class FitResult(Generic[FittedModel]):
    """An identification: the model and each axis' order choice (a one-axis run's axis is ``x``)."""

    model: FittedModel
    orders: dict[str, OrderChoice]


class FitOptions(TypedDict, total=False):
    """The options :func:`fit` and :func:`fit_cell` share (see :func:`fit`)."""

    order: int | str
    max_order: int
    exclude: Sequence[str]
    penter: float
    premove: float
    source: str | None
    squares: bool
    selection: str


#: stepwise selection modes: ``paper`` (MATLAB stepwisefit exactly: iid partial F-tests, as the paper selected),
#: ``hac`` (entry/removal by Wald tests under the Newey-West covariance) and ``coherent``: ``paper``'s tests, then,
#: while the channels pass more independent sensor noise than one thermocouple carrying their summed sensitivity
#: would (noise gain sqrt(Σc²)/|Σc| > 1), channels whose coefficient opposes the sum are dropped (weakest first) and
#: the selection rerun without them: channels the data cannot separate are not traded against each other with
#: large opposite-sign coefficients, which pass each thermocouple's noise into every command. The default is
#: ``coherent`` by measurement on fresh runs of the realistic cell (README, *What the data identifies*:
#: benchmarks/repeatability.py and benchmarks/selection_modes.py --cell realistic, 16 seeds, scored against the
#: simulated truth).
SELECTIONS = ("hac", "paper", "coherent")
DEFAULT_SELECTION = "coherent"
SELECTION_TESTS = {
    "hac": "Wald t-test of each added/kept term under the Newey-West HAC covariance",
    "paper": "partial F-test, rows taken as independent (MATLAB stepwisefit, as the paper)",
    "coherent": "partial F-test (MATLAB stepwisefit), then, while the channels' noise gain sqrt(sum c^2)/|sum c| "
                "exceeds 1, channels opposing the summed thermal sensitivity dropped, weakest first, and the "
                "selection rerun",
}


@dataclass(frozen=True)
class OLS:
    """A least-squares fit; ``se``/``p``/``cov`` are Newey-West HAC (lag ``hac_lag``), ``*_iid`` the textbook ones."""

    coef: np.ndarray  # per column
    se: np.ndarray
    p: np.ndarray
    intercept: float
    intercept_se: float
    intercept_p: float
    rmse: float
    dof: int
    r2: float
    #: covariance of the coefficients in original units, ordered as the columns then the intercept
    #: (a model's term order: bias last)
    cov: np.ndarray
    #: the textbook (iid) covariance, standard errors and p-values, per column then the intercept (comparison only)
    cov_iid: np.ndarray
    se_iid: np.ndarray
    p_iid: np.ndarray
    hac_lag: int

    @property
    def se_method(self) -> str:
        return hac.describe(self.hac_lag)


def ols(X: np.ndarray, y: np.ndarray, run_id: np.ndarray | None = None) -> OLS:
    """Least squares with an intercept; Newey-West HAC standard errors and t-test p-values (and the iid ones).

    Columns are standardised for the solve. ``run_id``: a run number per row (rows of different runs are
    independent); the lag follows :func:`nanodrift.model.hac.andrews_lag` of the fit's residual.
    """
    n, k = X.shape
    dof = n - k - 1
    if dof <= 0:
        raise FitError(f"{n} rows cannot support {k} terms plus a bias")
    mean, scale = X.mean(axis=0), X.std(axis=0)
    scale[scale == 0] = 1.0
    Z = np.column_stack([np.ones(n), (X - mean) / scale])
    coef_z, *_ = np.linalg.lstsq(Z, y, rcond=None)
    resid = y - Z @ coef_z
    sse = float(resid @ resid)
    sigma2 = sse / dof
    cov_iid_z = sigma2 * np.linalg.pinv(Z.T @ Z)
    lag = hac.andrews_lag(resid, run_id)
    cov_z = hac.hac_covariance(Z, resid, lag, run_id=run_id)
    # back to original units: b = bz/scale; intercept = b0z - Σ bz·mean/scale
    J = np.zeros((k + 1, k + 1))
    J[0, 0] = 1.0
    J[0, 1:] = -mean / scale
    J[1:, 1:] = np.diag(1.0 / scale)
    coef = J @ coef_z
    cov = J @ cov_z @ J.T
    se = np.sqrt(np.maximum(np.diag(cov), 0.0))
    cov_iid = J @ cov_iid_z @ J.T
    se_iid = np.sqrt(np.maximum(np.diag(cov_iid), 0.0))
    _, p = hac.t_p_values(coef, se, dof)
    _, p_iid = hac.t_p_values(coef, se_iid, dof)
    sst = float(((y - y.mean()) ** 2).sum())
    order = [*range(1, k + 1), 0]
    return OLS(
        coef=coef[1:], se=se[1:], p=p[1:], intercept=float(coef[0]), intercept_se=float(se[0]),
        intercept_p=float(p[0]), rmse=math.sqrt(sigma2), dof=dof, r2=1.0 - sse / sst if sst > 0 else 1.0,
        cov=0.5 * (cov + cov.T)[np.ix_(order, order)], cov_iid=0.5 * (cov_iid + cov_iid.T)[np.ix_(order, order)],
        se_iid=se_iid[order], p_iid=p_iid[order], hac_lag=lag,
    )


def _commands(data: Series) -> np.ndarray:
    if data.q is None:
        raise FitError(f"{data.source}: no q_um column (the command sent to the stage) to fit")
    return np.asarray(data.q, dtype=np.float64)


def fit_terms(
    data: Series,
    candidates: Sequence[Term],
    *,
    always: Sequence[Term] = (),
    penter: float = 0.05,
    premove: float = 0.10,
    source: str | None = None,
    extra_selection: Mapping[str, Any] | None = None,
    uncertainty: bool = True,
    selection: str = DEFAULT_SELECTION,
    scored_only: bool = False,
) -> Model:
    """Select among ``candidates`` by stepwise regression (bias always in; ``always`` forced in).

    ``selection``: one of :data:`SELECTIONS`; either way the reported standard errors and p-values are HAC ones.

    ``uncertainty=False`` skips the covariance block (held-out refits): for models only scored, never saved.
    ``scored_only=True`` (a held-out refit) also skips the final fit's standard errors and statistics: the
    model has its terms and coefficients only (:func:`_scored_model`).
    """
    data = data.valid_rows()
    y = _commands(data)
    pool = [t for t in candidates if not isinstance(t, Bias)]
    forced = [t for t in always if not isinstance(t, Bias)]
    for t in forced:
        if t not in pool:
            pool.append(t)
    if len(data) <= len(pool) + 1:
        raise FitError(f"{len(data)} rows are too few for {len(pool)} candidate terms plus a bias")
    X = design_matrix(pool, data)
    keep = np.array([t in forced for t in pool])
    _check_selection(selection)
    run_id = hac.run_ids(len(y), runs(data))
    result = stepwisefit(X, y, penter=penter, premove=premove, inmodel=keep.copy(), keep=keep,
                         hac_lag="andrews" if selection == "hac" else None, run_id=run_id)
    dropped: list[str] = []
    frozen_out = np.zeros(len(pool), dtype=bool)  # every channel dropped so far stays out: the loop ends
    while selection == "coherent" and (weakest := _opposing_channel(pool, result, keep)) is not None:
        dropped.append(pool[weakest].name)
        frozen_out[weakest] = True
        result = stepwisefit(X, y, penter=penter, premove=premove, inmodel=keep & ~frozen_out,
                             keep=keep | frozen_out, run_id=run_id)
    chosen = [i for i in range(len(pool)) if result.inmodel[i]]
    chosen_terms = [pool[i] for i in chosen]
    if scored_only and np.isfinite(result.coef[result.inmodel]).all():
        # stepwise's least-squares coefficients suffice (a kept column it found collinear has none: ols'
        # minimum-norm solution below serves it)
        return _scored_model(data, chosen_terms, result)
    # what each left-out term would get if added alone, under the same HAC covariance as the printed ones
    # (held-out refits, never saved, skip it); before the chosen columns are copied out, which it does not need
    if_added = result if selection == "hac" or not uncertainty else stepwisefit(
        X, y, penter=0.0, premove=1.0, inmodel=result.inmodel.copy(), keep=np.ones(len(pool), dtype=bool),
        hac_lag="andrews", run_id=run_id)
    X_chosen = X[:, chosen]
    final = ols(X_chosen, y, run_id) if chosen else None
    if final is None:
        mean = float(y.mean())
        resid = y - mean
        rmse = float(math.sqrt(resid @ resid / max(len(y) - 1, 1)))
        lag = hac.andrews_lag(resid, run_id)
        mean_se = math.sqrt(hac.hac_covariance(np.ones((len(y), 1)), resid, lag, run_id=run_id)[0, 0])
        terms = [FittedTerm(Bias(), mean, mean_se, math.nan)]
        fit_stats = {"rmse_um": rmse, "r2": 0.0, "dof": len(y) - 1, "se_method": hac.describe(lag), "hac_lag": lag}
        covariance = None
        if uncertainty:
            cov, s, _, noise = estimate(np.empty((len(y), 0)), y, np.asarray(data.t, dtype=np.float64), runs(data), {})
            covariance = Covariance(cov, s, wander_um=noise.wander_um)
    else:
        terms = [FittedTerm(t, float(final.coef[j]), float(final.se[j]), float(final.p[j]))
                 for j, t in enumerate(chosen_terms)]
        terms.append(FittedTerm(Bias(), final.intercept, final.intercept_se, final.intercept_p))
        fit_stats = {"rmse_um": final.rmse, "r2": final.r2, "dof": final.dof, "se_method": final.se_method,
                     "hac_lag": final.hac_lag, "iid": _iid_stats(chosen_terms, final)}
        covariance = model_covariance(X_chosen, y, final, data, chosen_terms) if uncertainty else None
    channels = [c for c in data.channels if any(c in ft.term.channels for ft in terms)]
    resid = y - X_chosen @ np.array([ft.coef for ft in terms[:-1]]) - terms[-1].coef  # bias last
    fit_stats.update(rows=len(data), residual_rms_nm=float(np.sqrt(np.mean(resid**2)) * 1000.0))
    selection_record = {
        "method": "stepwise",
        "mode": selection,
        "test": SELECTION_TESTS[selection],
        "penter": penter,
        "premove": premove,
        "candidates": [t.name for t in pool],
        "forced": [t.name for t in forced],
        "history": [
            {"action": action, "term": pool[col].name, "p": float(p)} for action, col, p in result.history
        ],
        "not_selected": {
            pool[i].name: {"coef_if_added": json_float(if_added.coef[i]), "p_if_added": json_float(if_added.pval[i])}
            for i in range(len(pool))
            if not result.inmodel[i]
        },
    }
    if selection == "coherent":
        selection_record["opposing_dropped"] = dropped
    selection_record.update(extra_selection or {})
    if final is not None and covariance is not None:
        fit_stats["thermal_sensitivity"] = thermal_sensitivity(chosen_terms, final, covariance)
    return Model(
        terms=terms,
        training=Training.of(data, channels),
        fit=fit_stats,
        selection=selection_record,
        provenance={"created": created_now(), "data_file": source, "software": software()},
        covariance=covariance,
    )


def _scored_model(data: Series, terms: Sequence[Term], result: StepwiseResult) -> Model:
    """The model a held-out refit scores: the stepwise's own least-squares coefficients of ``terms``
    (equal to :func:`ols`' to rounding), no standard errors, statistics or covariance. It is never saved,
    and a season of rows spares :func:`ols`' passes over them 30 times per fit."""
    fitted = [FittedTerm(t, float(c), math.nan, math.nan) for t, c in zip(terms, result.coef[result.inmodel],
                                                                          strict=True)]
    fitted.append(FittedTerm(Bias(), result.intercept, math.nan, math.nan))
    channels = [c for c in data.channels if any(c in t.channels for t in terms)]
    return Model(terms=fitted, training=Training.of(data, channels), fit={"rows": len(data)},
                 selection={"method": "stepwise (held-out refit)"}, provenance={})


def _opposing_channel(pool: Sequence[Term], result: StepwiseResult, forced: np.ndarray) -> int | None:
    """The selected, not forced, channel of the weakest |t| whose coefficient opposes the channels' sum, while the
    channels amplify sensor noise; None once they do not.

    The channels' noise gain is sqrt(Σ c²) / |Σ c|: what independent thermocouple noise passes into the command,
    against one thermocouple carrying the whole sensitivity. Above 1, opposite-sign coefficients trade each
    channel's noise for a fit the data cannot separate (benchmarks/repeatability.py); at or below 1 an opposing
    channel is a small correction (a part of the stage that grows the other way) and stays."""
    channels = [i for i, t in enumerate(pool) if isinstance(t, Channel) and result.inmodel[i]]
    coefs = np.array([result.coef[i] for i in channels], dtype=np.float64)
    total = float(coefs.sum())
    if not channels or math.sqrt(float(coefs @ coefs)) <= abs(total):
        return None
    opposing = [i for i in channels if result.coef[i] * total < 0 and not forced[i]]
    return min(opposing, key=lambda i: abs(float(result.tstat[i]))) if opposing else None


def thermal_sensitivity(terms: Sequence[Term], final: OLS, covariance: Covariance) -> dict[str, Any]:
    """The command's response to a common change of every selected channel (µm/°C) and its standard error.

    What the data identifies even where it cannot separate the channels (they move together): the sum of
    the channels' coefficients. Its standard error is the covariance block's (the REML noise model: white
    plus wander, covariances between the channels included), not HAC: one run holds about one slow
    excursion of that direction, and no Bartlett lag sees it (HAC said 4x too little over 8 calibrations
    of the realistic cell, the block 0.5-2x: tests/model/test_thermal_sensitivity.py).
    """
    mask = np.array([isinstance(t, Channel) for t in terms] + [False])
    return {"channels": [t.name for t in terms if isinstance(t, Channel)],
            "um_per_c": float(final.coef[mask[:-1]].sum()) if mask.any() else 0.0,
            "se_um_per_c": float(np.sqrt(max(float(mask @ covariance.matrix @ mask), 0.0))),
            "se_method": "the covariance block's (REML: white noise plus wander)"}


def _check_selection(selection: str) -> None:
    if selection not in SELECTIONS:
        raise FitError(f"selection must be one of {', '.join(SELECTIONS)}, got {selection!r}")


def _iid_stats(terms: Sequence[Term], final: OLS) -> dict[str, dict[str, float | None]]:
    """The textbook (iid) standard error and p-value of each term, bias last: kept for comparison only."""
    names = [t.name for t in terms] + [Bias().name]
    return {name: {"se": json_float(final.se_iid[i]), "p": json_float(final.p_iid[i])} for i, name in enumerate(names)}


def model_covariance(X: np.ndarray, y: np.ndarray, final: OLS, data: Series, terms: Sequence[Term],
                     nuisance: np.ndarray | None = None) -> Covariance:
    """The model file's covariance block for ``final``, the least-squares fit of y on X.

    See :mod:`nanodrift.model.uncertainty` for what it holds and why.

    ``nuisance`` (n, m): the last m columns of X are fitted but not kept (discovery's drift in run
    time); the bias then absorbs their value at the start of the run, and C follows.
    """
    channels = [c for c in data.channels if any(c in t.channels for t in terms)]
    if any(isinstance(t, ChannelSquare) for t in terms):
        channels = []  # the model fits its curvature: C carries it, no allowance for an unseen one
    cov, s, curvature, noise = estimate(X, y, np.asarray(data.t, dtype=np.float64), runs(data),
                                        {c: data.channels[c] for c in channels})
    k = len(terms)
    m = 0 if nuisance is None else nuisance.shape[1]
    J = np.zeros((k + 1, k + m + 1))  # the model's coefficients from the fit's: bias = intercept + Σ coef·start
    J[:k, :k] = np.eye(k)
    if nuisance is not None:
        J[k, k:k + m] = nuisance[0]
    J[k, k + m] = 1.0
    return Covariance(J @ cov @ J.T, s, curvature, noise.wander_um)


def candidate_terms(channels: Sequence[str], order: int, exclude: Sequence[str] = ()) -> list[Term]:
    unknown = [c for c in exclude if c not in channels]
    if unknown:
        raise FitError(f"--exclude names channel(s) {', '.join(unknown)} not in the data ({', '.join(channels)})")
    return [Power(k) for k in range(order, 0, -1)] + [Channel(c) for c in channels if c not in exclude]


def curvature_candidates(data: Series, exclude: Collection[str] = ()) -> list[ChannelSquare]:
    """``(T - centre)^2`` for each channel not excluded that the (valid) rows span by at least
    :data:`CURVATURE_MIN_SPAN_C`; the centre is the middle of its range, to 0.01 °C."""
    squares: list[ChannelSquare] = []
    for name, values in data.channels.items():
        v = np.asarray(values, dtype=np.float64)
        v = v[np.isfinite(v)]
        if name in exclude or v.size == 0:
            continue
        lo, hi = float(v.min()), float(v.max())
        if hi - lo >= CURVATURE_MIN_SPAN_C:
            squares.append(ChannelSquare(name, round(0.5 * (lo + hi), 2)))
    return squares


def cell_candidate_terms(axis: str, axes: Sequence[str], channels: Sequence[str], order: int,
                         exclude: Sequence[str] = ()) -> list[Term]:
    """Candidates for one axis of a multi-axis cell: its own powers up to ``order``, every other axis'
    position and square (crosstalk, non-orthogonality, sag), every product of two axes (coupled
    bending), and the channels. The same stepwise selection keeps what the data supports."""
    own: list[Term] = [Power(k, axis) for k in range(order, 0, -1)]
    others: list[Term] = [Power(k, b) for b in axes if b != axis for k in (1, 2)]
    products: list[Term] = [AxisProduct(a, b) for i, a in enumerate(axes) for b in axes[i + 1:]]
    return own + others + products + candidate_terms(channels, 1, exclude)[1:]


def holdout_blocks(data: Series, max_folds: int = 6) -> np.ndarray:
    """Fold index per row: whole cycles grouped into contiguous blocks (time blocks if one cycle).

    Several runs: each run gets its own blocks (at least one, about ``max_folds`` in all, shared by
    rows), so no block spans two runs and a short run of recorded operation is held out whole.
    """
    parts = runs(data)
    if len(parts) > 1:
        folds = np.zeros(len(data), dtype=np.int64)
        n, first = max(len(data), 1), 0
        for part in parts:
            share = max(1, round(max_folds * (part.stop - part.start) / n))
            own = _run_blocks(data.select(part), share)
            folds[part] = own + first
            first += int(own.max()) + 1
        return folds
    return _run_blocks(data, max_folds)


def _run_blocks(data: Series, max_folds: int) -> np.ndarray:
    cycles = data.cycles()
    unique = np.unique(cycles)
    if unique.size >= 3:
        folds = min(max_folds, unique.size)
        rank = np.searchsorted(unique, cycles)
        return (rank * folds) // unique.size
    folds = min(max_folds, 5)
    return (np.arange(len(data)) * folds) // max(len(data), 1)


def holdout_rms(data: Series, candidates: Sequence[Term], penter: float, premove: float,
                always: Sequence[Term] = (), selection: str = DEFAULT_SELECTION,
                folds: np.ndarray | None = None) -> tuple[float, int]:
    """RMS (um) of the command predicted for each held-out block by a model fitted on the others.

    ``folds``: :func:`holdout_blocks` of ``data``, when the caller scores several candidate sets on them.
    """
    folds = holdout_blocks(data) if folds is None else folds
    y = _commands(data)
    errors = []
    for k in np.unique(folds):
        train, test = data.select(folds != k), data.select(folds == k)
        model = fit_terms(train, candidates, always=always, penter=penter, premove=premove, uncertainty=False,
                          selection=selection, scored_only=True)
        errors.append(y[folds == k] - model.predict(test))
    err = np.concatenate(errors)
    return float(np.sqrt(np.mean(err**2))), int(np.unique(folds).size)


def fit(data: Series, *, candidates: Callable[[int], list[Term]] | None = None, keep: Sequence[Term] = (),
        **options: Unpack[FitOptions]) -> FitResult[Model]:
    """The paper's identification of a one-axis run: stepwise over x^1..x^n1 and the channels; n1 fixed or
    chosen (see :func:`_fit_axis` for every option)."""
    model, choice = _fit_axis(data, candidates=candidates, keep=keep, **options)
    return FitResult(model, {"x": choice})


def _fit_axis(
    data: Series,
    *,
    order: int | str = "auto",
    max_order: int = MAX_AUTO_ORDER,
    exclude: Sequence[str] = (),
    penter: float = 0.05,
    premove: float = 0.10,
    source: str | None = None,
    candidates: Callable[[int], list[Term]] | None = None,
    keep: Sequence[Term] = (),
    squares: bool = True,
    selection: str = DEFAULT_SELECTION,
) -> tuple[Model, OrderChoice]:
    """One axis' identification: stepwise over x^1..x^n1 and the channels; n1 fixed or chosen.

    ``keep``: terms in the model whatever the stepwise says (``fit --keep``: e.g. a refit with days of
    recorded operation keeping the calibration's x^2, x^3, which the records' thermal spread would hide).

    ``candidates(n1)``: the candidate terms for geometric order n1 (default: x^1..x^n1 and the channels
    not excluded; a multi-axis cell's axis passes :func:`cell_candidate_terms`). The squares of the
    channels the data spans widely enough (:func:`curvature_candidates`) are added to either, unless
    ``squares`` is False (eq. 3 as the paper wrote it, linear in temperature over any range).
    """
    _check_selection(selection)
    if penter > premove:
        raise FitError(f"penter ({penter}) must not exceed premove ({premove})")
    where = source or data.source
    given = len(data)
    data = data.valid_rows()
    _commands(data)
    channels = list(data.channels)
    scores: dict[int, float] = {}
    folds = 0
    curved = curvature_candidates(data, exclude) if squares else []

    def pool(n1: int) -> list[Term]:
        base = candidates(n1) if candidates is not None else candidate_terms(channels, n1, exclude)
        return base + curved

    def too_few(order_n1: int, purpose: str, advice: str) -> FitError:
        n, terms = len(data), len(pool(order_n1))
        left_out = f" ({given - n} more marked valid = 0 left out)" if given > n else ""
        powers = "x" if order_n1 == 1 else "x, x^2" if order_n1 == 2 else f"x..x^{order_n1}"
        used = [c for c in channels if c not in exclude]
        kinds = f"{powers} and channel{'s' if len(used) > 1 else ''} {', '.join(used)}" if used else powers
        if curved:
            kinds += f", squares of {', '.join(t.channel for t in curved)}"
        return FitError(
            f"{where}: {'1 row' if n == 1 else f'{n} rows'}{left_out} {'is' if n == 1 else 'are'} too few {purpose} "
            f"{terms} candidate term{'s' if terms != 1 else ''} ({kinds}) plus a bias: {advice}"
        )

    first = 1 if order == "auto" else int(order)
    if first < 1:
        raise FitError(f"order must be >= 1 or 'auto', got {order}")
    needed = len(pool(first)) + 2
    if len(data) < needed:
        raise too_few(first, "to fit", f"record at least {needed} rows")
    if order == "auto":
        blocks = holdout_blocks(data)
        for n1 in range(1, max_order + 1):
            try:
                scores[n1], folds = holdout_rms(data, pool(n1), penter, premove, keep, selection, blocks)
            except FitError:  # the blocks left after holding one out are too short for this order
                if n1 == 1:
                    raise too_few(1, "to choose the geometric order on held-out blocks (each fitted from the "
                                     "others) with", "record more rows, or give --order N") from None
                break  # higher orders need even more rows
        best = min(scores.values())
        # the lowest order within 1 % of the best: extra powers must earn their place
        chosen = min(n for n, s in scores.items() if s <= best * 1.01)
    else:
        chosen = first
    extra = {
        "order": chosen,
        "order_choice": "auto (held-out cycles)" if order == "auto" else "fixed",
        "order_holdout_rms_um": {str(k): v for k, v in scores.items()},
        "excluded": list(exclude),
    }
    model = fit_terms(
        data, pool(chosen), always=keep, penter=penter, premove=premove, source=source, extra_selection=extra,
        selection=selection,
    )
    if scores:
        model.fit["holdout_rms_um"] = scores[chosen]
    return model, OrderChoice(chosen, scores, folds)


def fit_cell(data: CellSeries, *, keep: Sequence[Term] = (), **options: Unpack[FitOptions]) -> FitResult[CellModel]:
    """Identification of every axis of a cell's run (one axis or several): :func:`fit` per axis over
    :func:`cell_candidate_terms` (for one axis, x: :func:`fit`'s own candidates), the geometric order chosen per
    axis on held-out cycles. ``keep``: terms every axis' model keeps whatever the stepwise says."""
    axes = data.axes
    channels = list(data.channels)
    exclude = options.get("exclude", ())
    candidate_terms(channels, 1, exclude)  # refuses an --exclude naming a channel the data lacks
    missing = [] if one_axis(axes) else [a for a in axes if a not in data.commands]  # one axis: its q_um, as fit
    if missing:
        raise FitError(f"{options.get('source') or data.source}: no q_{missing[0]}_um column (the command sent to "
                       f"axis {missing[0]}) to fit")
    models: dict[str, Model] = {}
    orders: dict[str, OrderChoice] = {}
    for axis in axes:
        def candidates(n1: int, axis: str = axis) -> list[Term]:
            return cell_candidate_terms(axis, axes, channels, n1, exclude)

        models[axis], orders[axis] = _fit_axis(data.axis_view(axis), candidates=candidates, keep=keep, **options)
    return FitResult(CellModel(axes, models, provenance=dict(models[axes[0]].provenance)), orders)
