"""Discovery: where a model and measured data disagree, which physical effect is missing, and its terms.

Pure computation (numpy/scipy, no I/O). The algorithm (documented for operators in the report):

1. Residuals of the model as given: ``r = q_measured - q_pred`` (um). Their structure against time,
   position, each channel, each channel's rate of change, the direction of motion and the last step
   is quantified by binned means and a one-way ANOVA F-test whose F is deflated for the residuals'
   lag-1 autocorrelation ρ (effective sample size n(1-ρ)/(1+ρ)), plus Durbin-Watson; a variable
   is flagged when that p, Bonferroni-corrected over the variables, is below ``p_max`` and the bins
   explain at least 5 % of the residual variance.
2. The working model is the given model's terms refitted on the data. Every effect of the catalogue
   proposes its term(s); a nonlinear parameter (a lag's or a creep's time constant) is found by a
   log-spaced grid then a bounded scalar minimisation of the training SSE (on log τ).
3. Each candidate is judged two ways: a partial F-test on all rows, honest about the search (one
   extra numerator degree of freedom per searched parameter, F and denominator degrees of freedom
   deflated by the residuals' lag-1 autocorrelation ρ: n(1-ρ)/(1+ρ) effective rows, ρ the lower of
   the residual's before and after the candidate; Bonferroni over the channels tried),
   and the RMS on held-out time blocks (whole cycles, never random rows; each block predicted by a
   fit on the others).
4. An effect is named when p < ``p_max`` AND it cuts the held-out RMS by at least
   ``min_holdout_gain`` AND improves at least half of the held-out blocks; the best is the lowest
   held-out RMS, each searched parameter charged ``search_penalty`` of it (parsimony: ``dir`` beats
   an equivalent creep). Its terms are added, the whole model refitted (the given terms plus the
   new ones), and the search repeats until nothing clears the bar.

Special rules, each for a reason the tests exercise:

- A lag and a rate of the same channel span the same model once the channel is in it, so one τ
  search serves both: τ ≤ ``rate_tau_max_s`` names ``temperature_rate``, longer ``thermal_lag``.
  Among near-equal channels the fastest (the air's) is preferred, and the lag is also reported
  relative to it (``tau_behind_fastest_s``): a lag behind a slow channel adds the two delays.
- A trend in time (``unmonitored_drift``) or a lag as long as the run is "trend-like": the
  interferometer's own slow wander can look like one, so it must cut the held-out RMS by
  ``trend_gain``. It is named but never applied online: fitted as a nuisance (so the other
  coefficients are clean), left out of the written model; the operator is told to add a sensor.
- ``sensor_exclusion`` (the paper's hot plate) is a removal: the channel must be one the stepwise
  keeps with conviction (iid F-test p < ``exclusion_p_iid``), yet leaving it out must predict
  at least ``exclusion_blocks`` of the held-out blocks better and cut their RMS by ``exclusion_gain``.
- ``missing_channel``: a monitored channel the given model left out (an effect can mask it).
- Re-admission: a large hidden effect can make the paper's stepwise leave out a channel or power
  the cell needs. After each step the given model's own selection (its candidates and ``penter``)
  is rerun with the working terms kept; what it re-admits joins that step (``params.readmitted``)
  when it also lowers the held-out RMS. Without this the next round "found" the masked channel
  again, dressed as a long lag or a missing channel (a spurious second step).
- A thermal_lag whose column, beyond the working terms, correlates with a line in time by at least
  ``twin_correlation`` is flagged ``alike: unmonitored_drift``: in a run where the room falls and
  rises once (24 cycles) the two look the same and τ is not pinned; a longer run tells them apart.

All regressions go through per-block Gram matrices of standardised columns against the working
model's residual (so no large numbers cancel): one pass over the rows per candidate column, which
keeps 1e6 rows within seconds.
"""

from __future__ import annotations

import datetime as dt
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import optimize, stats

from daemon.calibration.dataset import Dataset
from daemon.model.effect_terms import CREEP_DEADBAND_UM, Creep, PositionCoupling, Rate
from daemon.model.identify import holdout_blocks, ols
from daemon.model.model import FittedTerm, Model, Training
from daemon.model.stepwise import stepwisefit
from daemon.model.terms import Bias, Channel, Direction, Lag, Power, Term, UnknownTermError, lag_filter, parse_term

EFFECTS = (
    "geometric_order",
    "thermal_lag",
    "temperature_rate",
    "hysteresis",
    "position_thermal_coupling",
    "creep",
    "unmonitored_drift",
    "sensor_exclusion",
    "missing_channel",
)

#: effects whose terms the daemon cannot apply online: named, fitted as nuisance, not written out
NOT_APPLIED_ONLINE = frozenset({"unmonitored_drift"})


class DiscoveryError(ValueError):
    """The data cannot support discovery (too few rows, no q column); the message says why."""


@dataclass(frozen=True)
class Settings:
    """Thresholds and search ranges (the defaults are the documented bar)."""

    p_max: float = 0.01
    min_holdout_gain: float = 0.10  # held-out RMS must fall by at least 10 %
    exclusion_gain: float = 0.05  # leaving a channel out must cut the held-out RMS by 5 % ...
    exclusion_blocks: float = 0.8  # ... improving at least 80 % of the held-out blocks ...
    exclusion_p_iid: float = 1e-4  # ... though the stepwise keeps it with conviction (a barely kept one is not it)
    #: a trend in time (or a lag as long as the run) must cut the held-out RMS by half: over a few
    #: hours the interferometer's own slow wander (tens of nm) can look like a trend
    trend_gain: float = 0.50
    search_penalty: float = 0.02
    prefer_fastest_within: float = 0.05
    min_direction_share: float = 0.10  # ranking: held-out RMS x (1 + 2 % per searched parameter)
    max_steps: int = 4
    max_power: int = 6
    lag_tau_s: tuple[float, float] = (60.0, 8 * 3600.0)
    #: a lag shorter than this acts through the rate of change: named temperature_rate
    rate_tau_max_s: float = 900.0
    #: piezo creep settles in seconds to minutes; longer would only mimic slow thermal drift
    creep_tau_s: tuple[float, float] = (0.5, 600.0)
    grid_points: int = 10
    refine_evals: int = 10
    bins: int = 8
    rate_probe_tau_s: float = 600.0
    #: a named thermal_lag is flagged as alike an unmonitored drift when, beyond the working model's
    #: terms, the lag's column and a line in time correlate at least this much
    twin_correlation: float = 0.9


# --- residual structure ---------------------------------------------------------------------


def lag1_autocorr(r: np.ndarray) -> float:
    r = np.asarray(r, dtype=np.float64) - float(np.mean(r))
    denom = float(r @ r)
    return float(r[1:] @ r[:-1]) / denom if denom > 0 and r.size > 2 else 0.0


def durbin_watson(r: np.ndarray) -> float:
    r = np.asarray(r, dtype=np.float64)
    denom = float(r @ r)
    return float(np.sum(np.diff(r) ** 2) / denom) if denom > 0 else 2.0


def ar1_deflation(r: np.ndarray) -> float:
    """(1-ρ)/(1+ρ) for positively autocorrelated residuals, else 1: effective rows per row."""
    rho = lag1_autocorr(r)
    return (1.0 - rho) / (1.0 + rho) if rho > 0 else 1.0


@dataclass
class Disagreement:
    variable: str
    description: str
    f_stat: float
    p_value: float  # AR(1)-deflated
    p_value_iid: float
    eta2: float  # share of the residual variance the bins explain
    spread_um: float  # largest minus smallest bin mean
    bins: list[dict[str, float]]
    significant: bool
    values: np.ndarray = field(repr=False, default_factory=lambda: np.empty(0))

    def to_dict(self) -> dict[str, Any]:
        return {
            "variable": self.variable, "description": self.description, "f_stat": _f(self.f_stat),
            "p_value": _f(self.p_value), "p_value_iid": _f(self.p_value_iid), "eta2": _f(self.eta2),
            "spread_um": _f(self.spread_um), "significant": self.significant, "bins": self.bins,
        }


def _f(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(v) else None


def structure_variables(data: Dataset, settings: Settings = Settings()) -> dict[str, tuple[str, np.ndarray]]:
    """The variables residuals are checked against: name -> (description, value per row)."""
    t, x = np.asarray(data.t, dtype=np.float64), np.asarray(data.x, dtype=np.float64)
    out: dict[str, tuple[str, np.ndarray]] = {
        "t": ("time since the start of the run (s)", t - t[0]),
        "x": ("position x (um)", x),
    }
    for c, v in data.channels.items():
        out[c] = (f"temperature {c} (degC)", np.asarray(v, dtype=np.float64))
    tau = settings.rate_probe_tau_s
    for c in data.channels:
        out[f"rate({c})"] = (
            f"rate of change of {c} (degC/h, smoothed over {tau:g} s)",
            Rate(c, tau).batch(t, x, data.channels) * 3600.0,
        )
    out["dir"] = ("direction of the last move (+1 up, -1 down)", Direction().batch(t, x, data.channels))
    step = np.diff(x, prepend=x[:1])
    moved = np.abs(step) > CREEP_DEADBAND_UM
    idx = np.where(moved, np.arange(x.size), 0)
    np.maximum.accumulate(idx, out=idx)
    out["last_step"] = ("size of the last step (um)", np.where(moved[idx], step[idx], 0.0))
    out["time_since_step"] = ("time since the last step (s)", t - t[idx])
    return out


def residual_structure(
    residual: np.ndarray, variables: Mapping[str, tuple[str, np.ndarray]], settings: Settings = Settings()
) -> list[Disagreement]:
    """Binned residual means per variable and their significance, most structured first."""
    r = np.asarray(residual, dtype=np.float64)
    n = r.size
    deflate = ar1_deflation(r)
    found: list[Disagreement] = []
    for name, (desc, values) in variables.items():
        values = np.asarray(values, dtype=np.float64)
        uniq = np.unique(values)
        if uniq.size < 2:
            continue
        if uniq.size <= settings.bins:
            labels = np.searchsorted(uniq, values)
            edges = np.concatenate((uniq, uniq[-1:]))
            categorical = True
        else:
            edges = np.unique(np.quantile(values, np.linspace(0.0, 1.0, settings.bins + 1)))
            labels = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)
            categorical = False
        k = int(labels.max()) + 1
        counts = np.bincount(labels, minlength=k).astype(np.float64)
        keep = counts > 0
        if keep.sum() < 2:
            continue
        sums = np.bincount(labels, weights=r, minlength=k)
        means = np.divide(sums, counts, out=np.zeros(k), where=keep)
        grand = float(r.mean())
        ss_between = float(np.sum(counts[keep] * (means[keep] - grand) ** 2))
        ss_total = float(np.sum((r - grand) ** 2))
        ss_within = max(ss_total - ss_between, 1e-300)
        groups = int(keep.sum())
        df1, df2 = groups - 1, n - groups
        if df2 <= 0:
            continue
        f_stat = (ss_between / df1) / (ss_within / df2)
        p_iid = float(stats.f.sf(f_stat, df1, df2))
        df2_eff = max(n * deflate - groups, 2.0)
        p = float(stats.f.sf(f_stat * deflate, df1, df2_eff))
        sq = np.bincount(labels, weights=r * r, minlength=k)
        var = np.divide(sq, counts, out=np.zeros(k), where=keep) - means**2
        bins = []
        for j in np.flatnonzero(keep):
            lo = float(edges[j])
            hi = lo if categorical else float(edges[j + 1])
            bins.append({
                "lo": lo, "hi": hi, "n": int(counts[j]), "mean_um": float(means[j]),
                "se_um": float(math.sqrt(max(var[j], 0.0) / counts[j] / deflate)) if counts[j] > 1 else 0.0,
            })
        eta2 = ss_between / ss_total if ss_total > 0 else 0.0
        spread = float(means[keep].max() - means[keep].min())
        found.append(Disagreement(
            variable=name, description=desc, f_stat=f_stat, p_value=p, p_value_iid=p_iid, eta2=eta2,
            spread_um=spread, bins=bins, significant=p * len(variables) < settings.p_max and eta2 >= 0.05,
            values=values,
        ))
    found.sort(key=lambda d: (not d.significant, -d.eta2))
    return found


# --- the regression workspace ---------------------------------------------------------------


def _standardise(cols: np.ndarray) -> np.ndarray:
    if cols.shape[1] == 1:  # the common case, without a second copy
        col = cols[:, 0]
        mean, scale = float(col.mean()), float(col.std())
        return ((col - mean) / (scale or 1.0))[:, None]
    mean = cols.mean(axis=0)
    scale = cols.std(axis=0)
    scale[scale == 0] = 1.0
    return (cols - mean) / scale


class Workspace:
    """The working model's columns on the data, as per-block Gram matrices against its residual.

    ``A = [1, Z, r]`` with Z the standardised working columns and r the residual of the working
    model fitted on all rows; blocks are contiguous time blocks (the held-out folds). Adding columns
    F needs only ``A_b' F_b`` and ``F_b' F_b``: one pass over the rows per candidate column.
    """

    def __init__(self, columns: np.ndarray, y: np.ndarray, folds: np.ndarray) -> None:
        n = y.shape[0]
        self.n = n
        starts = np.flatnonzero(np.diff(folds, prepend=folds[0] - 1) != 0)
        self.bounds = [(int(a), int(b)) for a, b in zip(starts, [*starts[1:], n], strict=True)]
        Z = _standardise(columns) if columns.shape[1] else np.empty((n, 0))
        base = np.column_stack([np.ones(n), Z])
        coef, *_ = np.linalg.lstsq(base, y, rcond=None)
        self.coef = coef  # on [1, Z]: y = [1, Z] coef + residual
        self.residual = y - base @ coef
        self.A = np.column_stack([base, self.residual])
        self.G = np.stack([self.A[a:b].T @ self.A[a:b] for a, b in self.bounds])
        self.k = base.shape[1]  # columns incl. intercept

    @property
    def sse(self) -> float:
        return float(self.residual @ self.residual)

    def _augmented(self, F: np.ndarray | None, drop: Sequence[int]) -> tuple[np.ndarray, list[int]]:
        """Per-block Gram of [1, Z, F, r] and the regressor indices to use."""
        k = self.k
        m = 0 if F is None else F.shape[1]
        size = k + m + 1
        G = np.zeros((len(self.bounds), size, size))
        idx_old = [*range(k), k + m]  # positions of [1, Z] and r in the new matrix
        new = list(range(k, k + m))
        G[np.ix_(range(len(self.bounds)), idx_old, idx_old)] = self.G
        if m:
            assert F is not None
            for bi, (a, b) in enumerate(self.bounds):
                cross = self.A[a:b].T @ F[a:b]  # (k+1, m)
                g = G[bi]
                g[k:k + m, k:k + m] = F[a:b].T @ F[a:b]
                g[np.ix_(idx_old, new)] = cross
                g[np.ix_(new, idx_old)] = cross.T
        dropped = [1 + d for d in drop]
        if dropped:  # without those columns the target is r plus what they explained
            t = k + m
            b = self.coef[dropped]
            for g in G:
                col = g[:, t] + g[:, dropped] @ b
                col[t] = g[t, t] + 2.0 * b @ g[dropped, t] + b @ g[np.ix_(dropped, dropped)] @ b
                g[:, t] = col
                g[t, :] = col
        regressors = [i for i in range(k + m) if i not in dropped]
        return G, regressors

    @staticmethod
    def _solve(G: np.ndarray, S: list[int], target: int) -> np.ndarray:
        gss = G[np.ix_(S, S)]
        scale = np.sqrt(np.maximum(np.diag(gss), 1e-300))
        beta, *_ = np.linalg.lstsq(gss / np.outer(scale, scale), G[S, target] / scale, rcond=1e-12)
        return beta / scale

    def sse_with(self, F: np.ndarray) -> float:
        """Training SSE (all rows) of the working model plus columns F: one pass, no per-block split."""
        k, m = self.k, F.shape[1]
        total = np.zeros((k + m + 1, k + m + 1))
        old = [*range(k), k + m]
        total[np.ix_(old, old)] = self.G.sum(axis=0)
        cross = self.A.T @ F
        total[np.ix_(old, range(k, k + m))] = cross
        total[np.ix_(range(k, k + m), old)] = cross.T
        total[k:k + m, k:k + m] = F.T @ F
        S = list(range(k + m))
        beta = self._solve(total, S, k + m)
        return float(total[k + m, k + m] - beta @ total[S, k + m])

    def evaluate(self, F: np.ndarray | None, drop: Sequence[int] = ()) -> tuple[float, np.ndarray, int]:
        """(training SSE, held-out SSE per block, regressors incl. intercept)."""
        G, S = self._augmented(F, drop)
        total = G.sum(axis=0)
        target = total.shape[0] - 1
        beta = self._solve(total, S, target)
        sse = float(total[target, target] - beta @ total[S, target])
        held = np.empty(len(self.bounds))
        for bi in range(len(self.bounds)):
            train = total - G[bi]
            b = self._solve(train, S, target)
            g = G[bi]
            held[bi] = max(float(g[target, target] - 2.0 * b @ g[S, target] + b @ g[np.ix_(S, S)] @ b), 0.0)
        return max(sse, 0.0), held, len(S)

    def residual_with(self, F: np.ndarray | None, drop: Sequence[int] = ()) -> np.ndarray:
        G, S = self._augmented(F, drop)
        total = G.sum(axis=0)
        beta = self._solve(total, S, total.shape[0] - 1)
        full = np.zeros(self.k + (0 if F is None else F.shape[1]))
        full[S] = beta
        out = self.residual - self.A[:, : self.k] @ full[: self.k]
        if F is not None:
            out -= F @ full[self.k:]
        return out


# --- candidates -----------------------------------------------------------------------------


@dataclass
class Candidate:
    effect: str
    add: list[Term]  # terms the model gains (empty for a nuisance or an exclusion)
    remove: list[Term]
    params: dict[str, Any]
    searched: int  # nonlinear parameters found by search (charged in the F-test and the ranking)
    alternatives: int  # how many variants were tried for the family (Bonferroni)
    nuisance: dict[str, np.ndarray] = field(default_factory=dict, repr=False)  # not applied online
    p_value: float = math.nan
    f_stat: float = math.nan
    rms_before_um: float = math.nan
    rms_after_um: float = math.nan
    holdout_rms_before_um: float = math.nan
    holdout_rms_after_um: float = math.nan
    clears: bool = False
    blocks_improved: float = math.nan  # share of held-out blocks the candidate predicts better
    p_blocks: float = math.nan  # one-sided t-test over blocks that the held-out error falls
    p_iid: float = math.nan  # the same F-test taking rows as independent (what stepwisefit reports)
    trend_like: bool = False  # indistinguishable from a drift in time over this run
    profile: list[tuple[float, float]] = field(default_factory=list, repr=False)  # (param, training RMS)

    @property
    def holdout_gain(self) -> float:
        b, a = self.holdout_rms_before_um, self.holdout_rms_after_um
        return (b - a) / b if b > 0 else 0.0

    @property
    def label(self) -> str:
        parts = [t.name for t in self.add] + [f"-{t.name}" for t in self.remove] + list(self.nuisance)
        return f"{self.effect} [{', '.join(parts)}]"

    def rank_key(self, settings: Settings) -> float:
        return self.holdout_rms_after_um * (1.0 + settings.search_penalty * self.searched)

    def to_dict(self) -> dict[str, Any]:
        return {
            "effect": self.effect, "params": self.params, "p_value": _f(self.p_value),
            "rms_before_um": _f(self.rms_before_um), "rms_after_um": _f(self.rms_after_um),
            "holdout_rms_before_um": _f(self.holdout_rms_before_um),
            "holdout_rms_after_um": _f(self.holdout_rms_after_um),
            "terms_added": [t.name for t in self.add], "terms_removed": [t.name for t in self.remove],
            "applied_online": self.effect not in NOT_APPLIED_ONLINE,
            "f_stat": _f(self.f_stat), "holdout_gain": _f(self.holdout_gain),
            "blocks_improved": _f(self.blocks_improved),
        }


def _round_sig(value: float, digits: int = 3) -> float:
    return float(f"{value:.{digits}g}")


def _search_tau(objective: Callable[[float], float], lo: float, hi: float, settings: Settings
                ) -> tuple[float, list[tuple[float, float]]]:
    """Log grid then bounded minimisation on log τ; returns (best τ, profile of (τ, value))."""
    grid = np.geomspace(lo, hi, settings.grid_points)
    profile = [(float(tau), objective(float(tau))) for tau in grid]
    values = np.array([v for _, v in profile])
    i = int(np.argmin(values))
    a, b = math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, grid.size - 1)])
    best_tau, best = float(grid[i]), float(values[i])
    if b > a:
        res = optimize.minimize_scalar(
            lambda s: objective(math.exp(s)), bounds=(a, b), method="bounded",
            options={"maxiter": settings.refine_evals, "xatol": 0.01},
        )
        if float(res.fun) < best:
            best_tau, best = math.exp(float(res.x)), float(res.fun)
    rounded = _round_sig(best_tau)
    profile.append((rounded, objective(rounded)))
    profile.sort()
    return rounded, profile


class _Context:
    """The data and working model a round of candidates is evaluated against."""

    def __init__(self, data: Dataset, terms: list[Term], nuisance: dict[str, np.ndarray], folds: np.ndarray,
                 settings: Settings, excluded: set[str], delays: Mapping[str, float]) -> None:
        self.data, self.terms, self.nuisance, self.settings = data, terms, nuisance, settings
        self.excluded, self.delays = excluded, delays
        self.t = np.asarray(data.t, dtype=np.float64)
        self.x = np.asarray(data.x, dtype=np.float64)
        assert data.q is not None
        cols = [term.batch(self.t, self.x, data.channels) for term in terms] + list(nuisance.values())
        matrix = np.column_stack(cols) if cols else np.empty((len(data), 0))
        self.ws = Workspace(matrix, np.asarray(data.q, dtype=np.float64), folds)
        self.sse0, self.held_blocks0, self.k0 = self.ws.evaluate(None)
        self.deflate = ar1_deflation(self.ws.residual)
        self.held0 = float(self.held_blocks0.sum())

    def feature(self, term: Term) -> np.ndarray:
        return term.batch(self.t, self.x, self.data.channels)

    def columns(self, feats: Sequence[np.ndarray]) -> np.ndarray:
        return _standardise(np.column_stack(feats))

    def judge(self, cand: Candidate, F: np.ndarray | None, drop: Sequence[int] = ()) -> Candidate:
        n = self.ws.n
        sse1, held_blocks1, k1 = self.ws.evaluate(F, drop)
        held1 = float(held_blocks1.sum())
        cand.blocks_improved = float(np.mean(held_blocks1 < self.held_blocks0))
        sizes = np.array([b - a for a, b in self.ws.bounds], dtype=np.float64)
        gain = (self.held_blocks0 - held_blocks1) / sizes  # per-row MSE reduction in each block
        spread = float(np.std(gain, ddof=1)) if gain.size > 1 else 0.0
        if spread > 0:
            cand.p_blocks = float(stats.t.sf(float(np.mean(gain)) / (spread / math.sqrt(gain.size)), gain.size - 1))
        else:
            cand.p_blocks = 0.0 if float(np.mean(gain)) > 0 else 1.0
        cand.rms_before_um = math.sqrt(self.sse0 / n)
        cand.rms_after_um = math.sqrt(sse1 / n)
        cand.holdout_rms_before_um = math.sqrt(self.held0 / n)
        cand.holdout_rms_after_um = math.sqrt(held1 / n)
        if cand.remove:  # an exclusion: the F-test of the removed column(s), in the working model
            big, small, sse_big = self.k0, k1, self.sse0
            deflate = self.deflate
        else:
            big, small, sse_big = k1, self.k0, sse1
            # ρ of the noise: the residual before (H0) or after (H1), whichever is less autocorrelated.
            # Before overstates it while a slow effect is unexplained, after while a spiky one
            # (creep) is still in the working residual
            deflate = max(self.deflate, ar1_deflation(self.ws.residual_with(F, drop)))
        df1 = max(big - small, 0) + cand.searched
        df2 = max(n * deflate - big - cand.searched, 2.0)
        delta = abs(self.sse0 - sse1)
        if df1 <= 0 or sse_big <= 0:
            cand.f_stat, cand.p_value = math.inf, 0.0
        else:
            cand.f_stat = (delta / df1) / (sse_big / max(n - big - cand.searched, 1))
            cand.p_value = min(1.0, float(stats.f.sf(cand.f_stat * deflate, df1, df2)) * cand.alternatives)
            cand.p_iid = float(stats.f.sf(cand.f_stat, df1, max(n - big - cand.searched, 1)))
        bar = self.settings
        if cand.remove:
            # the hot plate's signature: the stepwise keeps it (its F-test taking rows as independent,
            # as stepwisefit does, is significant), yet nearly every held-out block is predicted better
            # without it
            cand.clears = (cand.p_iid < bar.exclusion_p_iid and cand.holdout_gain >= bar.exclusion_gain
                           and cand.blocks_improved >= bar.exclusion_blocks)
        else:
            needed = bar.trend_gain if cand.trend_like else bar.min_holdout_gain
            cand.clears = (cand.holdout_gain >= needed and cand.p_value < bar.p_max
                           and cand.blocks_improved >= 0.5)
        return cand


def _powers(terms: Sequence[Term]) -> set[int]:
    return {t.k for t in terms if isinstance(t, Power)}


def _geometric(ctx: _Context) -> list[Candidate]:
    have = _powers(ctx.terms)
    top = max(have, default=0)
    out = []
    for k in range(1, max(top + 1, 3) + 1):
        if k in have or k > ctx.settings.max_power:
            continue
        term = Power(k)
        cand = Candidate("geometric_order", [term], [], {"order": max(top, k), "term": term.name}, 0, 1)
        out.append(ctx.judge(cand, ctx.columns([ctx.feature(term)])))
    return out


def _liveliest_window(data: Dataset, rows: int) -> slice:
    """The ``rows`` consecutive rows over which the mean temperature spans the widest range."""
    n = len(data)
    if n <= rows or not data.channels:
        return slice(0, n)
    mean = np.mean(np.column_stack(list(data.channels.values())), axis=1)
    starts = range(0, n - rows + 1, max(rows // 2, 1))
    best = max(starts, key=lambda a: float(np.ptp(mean[a:a + rows])))
    return slice(best, best + rows)


def channel_delays(data: Dataset, max_rows: int = 20000) -> dict[str, float]:
    """How far each channel lags the fastest one (s): the reference is the channel the others lag most.

    Each pair's delay is the τ of ``a + b·lag(T_ref, τ)`` fitting ``T_c`` best (log grid), on at most
    ``max_rows`` consecutive rows (the window where the temperatures move most: decimating instead
    would blur delays of minutes). A lag found on channel c then lags the reference (≈ the air) by
    about τ + delay_c: first-order delays add for slow signals.
    """
    channels = list(data.channels)
    if len(channels) < 2:
        return dict.fromkeys(channels, 0.0)
    window = _liveliest_window(data, max_rows)
    t = np.asarray(data.t[window], dtype=np.float64)
    temps = {c: np.asarray(v[window], dtype=np.float64) for c, v in data.channels.items()}
    grid = np.geomspace(1.0, 4 * 3600.0, 36)
    delay: dict[tuple[str, str], float] = {}
    for ref in channels:
        lagged = [lag_filter(t, temps[ref], tau) for tau in grid]
        for c in channels:
            if c == ref:
                continue
            y = temps[c] - temps[c].mean()
            best, best_tau = math.inf, 0.0
            for tau, u in zip(grid, lagged, strict=True):
                u = u - u.mean()
                uu = float(u @ u)
                sse = float(y @ y) - (float(u @ y) ** 2 / uu if uu > 0 else 0.0)
                if sse < best:
                    best, best_tau = sse, float(tau)
            delay[ref, c] = best_tau if best_tau > grid[0] else 0.0
    reference = max(channels, key=lambda r: sum(delay[r, c] for c in channels if c != r))
    out = {c: delay[reference, c] for c in channels if c != reference}
    out[reference] = 0.0
    return out


def _thermal_response(ctx: _Context) -> list[Candidate]:
    """lag(c, τ) (plus c itself if the model lacks it) for every channel, τ searched.

    With c in the model, adding ``lag(c, τ)`` spans exactly what adding ``rate(c, τ)`` does, so one
    search serves both effects; the time constant names it: a structure lagging the air by τ above
    ``rate_tau_max_s`` is a thermal lag, a shorter one acts through the rate of change.
    """
    s = ctx.settings
    have = {t.name for t in ctx.terms}
    channels = list(ctx.data.channels)
    out = []
    for c in channels:
        base = [] if c in have else [ctx.feature(Channel(c))]

        def sse(tau: float, c: str = c, base: list[np.ndarray] = base) -> float:
            feats = [*base, Lag(c, tau).batch(ctx.t, ctx.x, ctx.data.channels)]
            return ctx.ws.sse_with(ctx.columns(feats))

        tau_max = min(s.lag_tau_s[1], max(float(ctx.t[-1] - ctx.t[0]), 2 * s.lag_tau_s[0]))
        tau, profile = _search_tau(sse, s.lag_tau_s[0], tau_max, s)
        extra = [] if c in have else [Channel(c)]
        behind_reference = _round_sig(tau + ctx.delays.get(c, 0.0))
        if tau <= s.rate_tau_max_s:
            term: Term = Rate(c, tau)
            effect, params = "temperature_rate", {"channel": c, "tau_s": tau}
        else:
            term = Lag(c, tau)
            effect, params = "thermal_lag", {"channel": c, "tau_s": tau, "tau_behind_fastest_s": behind_reference}
        if Lag(c, tau).name in have or Rate(c, tau).name in have:
            continue
        feats = [*base, ctx.feature(term)]
        cand = Candidate(effect, [*extra, term], [], params, 1, len(channels))
        cand.profile = [(p, math.sqrt(v / ctx.ws.n)) for p, v in profile]
        cand.trend_like = tau >= 0.9 * tau_max  # as long as the run: a trend, not an identified lag
        out.append(ctx.judge(cand, ctx.columns(feats)))
    return _prefer_fastest(out, ctx)


def _prefer_fastest(cands: list[Candidate], ctx: _Context) -> list[Candidate]:
    """Among near-equal lags of different channels keep the one on the fastest channel (the air's).

    A lag found on a slow channel stands for the air through two lags in series, whose delays add
    only approximately; when the fastest channel explains as much (held-out RMS within
    ``prefer_fastest_within``), its τ is the cleaner estimate of how far the hidden part lags the air.
    """
    if not cands or not ctx.delays:
        return cands
    reference = min(ctx.delays, key=lambda c: ctx.delays[c])
    best = min(cands, key=lambda c: c.holdout_rms_after_um)
    ref = [c for c in cands if c.params["channel"] == reference and c.clears]
    if not ref or ref[0] is best:
        return cands
    if ref[0].holdout_rms_after_um <= best.holdout_rms_after_um * (1.0 + ctx.settings.prefer_fastest_within):
        for c in cands:  # those ahead of the reference step aside: it now ranks first in its family
            if c.holdout_rms_after_um < ref[0].holdout_rms_after_um:
                c.clears = False
                c.params["deferred_to"] = reference
    return cands


def _missing_channel(ctx: _Context) -> list[Candidate]:
    """A monitored channel the model left out (stepwise can drop one when another effect masks it)."""
    have = {t.name for t in ctx.terms}
    missing = [c for c in ctx.data.channels if c not in have and c not in ctx.excluded]
    return [
        ctx.judge(Candidate("missing_channel", [Channel(c)], [], {"channel": c}, 0, len(missing)),
                  ctx.columns([ctx.feature(Channel(c))]))
        for c in missing
    ]


def _hysteresis(ctx: _Context) -> list[Candidate]:
    """``dir``, when the run approaches its points from both sides.

    In forward-only sweeps the only step down is the return to 0, so ``dir`` there is just "the row
    at x = 0" (a geometric or creep detail, not hysteresis): the direction must be the minority on
    at least ``min_direction_share`` of the rows.
    """
    term = Direction()
    if term in ctx.terms:
        return []
    f = ctx.feature(term)
    if min(float(np.mean(f > 0)), float(np.mean(f < 0))) < ctx.settings.min_direction_share:
        return []
    return [ctx.judge(Candidate("hysteresis", [term], [], {"deadband_um": term.deadband_um}, 0, 1),
                      ctx.columns([f]))]


def _coupling(ctx: _Context) -> list[Candidate]:
    channels = list(ctx.data.channels)
    out = []
    for c in channels:
        term = PositionCoupling(c)
        if term in ctx.terms:
            continue
        out.append(ctx.judge(Candidate("position_thermal_coupling", [term], [], {"channel": c}, 0, len(channels)),
                             ctx.columns([ctx.feature(term)])))
    return out


def _creep(ctx: _Context) -> list[Candidate]:
    if any(isinstance(t, Creep) for t in ctx.terms):
        return []
    if not np.any(np.abs(np.diff(ctx.x)) > CREEP_DEADBAND_UM):
        return []

    def sse(tau: float) -> float:
        return ctx.ws.sse_with(ctx.columns([Creep(tau).batch(ctx.t, ctx.x, ctx.data.channels)]))

    tau, profile = _search_tau(sse, *ctx.settings.creep_tau_s, ctx.settings)
    term = Creep(tau)
    cand = Candidate("creep", [term], [], {"tau_s": tau}, 1, 1)
    cand.profile = [(p, math.sqrt(v / ctx.ws.n)) for p, v in profile]
    return [ctx.judge(cand, ctx.columns([ctx.feature(term)]))]


def _drift(ctx: _Context) -> list[Candidate]:
    if "t" in ctx.nuisance:
        return []
    t_h = (ctx.t - ctx.t[0]) / 3600.0
    cand = Candidate("unmonitored_drift", [], [], {}, 0, 1, nuisance={"t": t_h}, trend_like=True)
    return [ctx.judge(cand, ctx.columns([t_h]))]


def _exclusion(ctx: _Context) -> list[Candidate]:
    channel_terms = [i for i, t in enumerate(ctx.terms) if isinstance(t, Channel)]
    if len(channel_terms) < 2:
        return []
    out = []
    for i in channel_terms:
        term = ctx.terms[i]
        cand = Candidate("sensor_exclusion", [], [term], {"channel": term.name}, 0, len(channel_terms))
        out.append(ctx.judge(cand, None, drop=[i]))
    return out


PROPOSERS: dict[str, Callable[[_Context], list[Candidate]]] = {
    "geometric_order": _geometric,
    "thermal_response": _thermal_response,
    "missing_channel": _missing_channel,
    "hysteresis": _hysteresis,
    "position_thermal_coupling": _coupling,
    "creep": _creep,
    "unmonitored_drift": _drift,
    "sensor_exclusion": _exclusion,
}


def drift_alike(ctx: _Context, chosen: Candidate) -> dict[str, Any]:
    """Whether a named thermal_lag looks, in this run, like an unmonitored drift (a line in time).

    When the room only falls and rises once during the run (the paper's 24-cycle calibration), what
    the thermocouples cannot explain of a lag of hours is nearly a straight line in time: the two
    effects are then told apart by noise, and the lag's τ is not pinned. The correlation of the two
    columns, each beyond the working model's terms, says so; the operator is told to record longer.
    """
    t_h = (ctx.t - ctx.t[0]) / 3600.0
    extra = [ctx.columns([ctx.feature(t)]) for t in chosen.add[:-1]]
    base = np.column_stack([ctx.ws.A[:, : ctx.ws.k], *extra])

    def beyond(v: np.ndarray) -> np.ndarray:
        coef, *_ = np.linalg.lstsq(base, v, rcond=None)
        return v - base @ coef

    a, b = beyond(ctx.feature(chosen.add[-1])), beyond(t_h)
    denom = math.sqrt(float(a @ a) * float(b @ b))
    corr = abs(float(a @ b)) / denom if denom > 0 else 0.0
    if corr < ctx.settings.twin_correlation:
        return {}
    return {"alike": "unmonitored_drift", "alike_correlation": _round_sig(corr, 3)}


def selection_pool(model: Model, data: Dataset) -> list[Term]:
    """The terms the given model's own selection chose from (its stepwise candidates) that the data can feed."""
    pool = []
    for name in model.selection.get("candidates") or []:
        try:
            term = parse_term(str(name))
        except UnknownTermError:
            continue
        if not isinstance(term, Bias) and all(c in data.channels for c in term.channels):
            pool.append(term)
    return pool


def readmit(data: Dataset, working: Sequence[Term], nuisance: Mapping[str, np.ndarray], pool: Sequence[Term],
            excluded: set[str], penter: float, premove: float) -> list[Term]:
    """Terms of the given model's pool that its own stepwise admits once the named effect's terms are in.

    A large hidden effect inflates the residual the paper's selection sees, so it can leave out a
    channel the cell needs (creep or hysteresis masking T2). Once the effect is named, the same
    selection (same ``penter``, the working terms kept) re-admits what it masked, as part of that
    step: otherwise the next round "finds" the masked channel again, dressed as a lag or a missing
    channel. Additions only; excluded channels stay out. The caller keeps them only if they also
    lower the held-out RMS (the stepwise's p-values take rows as independent).
    """
    have = set(working)
    optional = [t for t in pool if t not in have and not excluded.intersection({t.name, *t.channels})]
    if not optional:
        return []
    t, x = np.asarray(data.t, dtype=np.float64), np.asarray(data.x, dtype=np.float64)
    cols = [term.batch(t, x, data.channels) for term in [*working, *optional]]
    forced = len(working) + len(nuisance)
    X = np.column_stack(cols[: len(working)] + list(nuisance.values()) + cols[len(working):])
    keep = np.arange(X.shape[1]) < forced
    result = stepwisefit(X, np.asarray(data.q, dtype=np.float64), penter=penter, premove=max(premove, penter),
                         inmodel=keep.copy(), keep=keep)
    return [term for j, term in enumerate(optional) if result.inmodel[forced + j]]


# --- the workflow ---------------------------------------------------------------------------


@dataclass
class Round:
    """One pass over the catalogue: every candidate tried, and the one named (if any)."""

    candidates: list[Candidate]
    chosen: Candidate | None


@dataclass
class DiscoveryResult:
    baseline: dict[str, Any]
    disagreements: list[Disagreement]
    steps: list[Candidate]
    rounds: list[Round]
    final: dict[str, Any]
    model: Model
    residual_before: np.ndarray  # the given model's residual, um
    residual_after: np.ndarray  # the extended model's residual (nuisance included), um
    variables: dict[str, tuple[str, np.ndarray]]
    summary: str

    def to_dict(self, model_out: str | None = None) -> dict[str, Any]:
        return {
            "baseline": self.baseline,
            "disagreements": [d.to_dict() for d in self.disagreements],
            "steps": [s.to_dict() for s in self.steps],
            "final": self.final,
            "model_out": model_out,
        }


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(r)))) if r.size else math.nan


def _folds(data: Dataset) -> np.ndarray:
    folds = holdout_blocks(data)
    if np.any(np.diff(folds) < 0) or np.unique(folds).size < 2:  # cycles out of time order: time blocks
        n = len(data)
        folds = (np.arange(n) * 5) // max(n, 1)
    return folds


def _describe(c: Candidate) -> str:
    p = c.params
    if c.effect == "thermal_lag":
        return (f"a first-order thermal lag of {p['tau_s'] / 60:.0f} min on {p['channel']} (term {c.add[-1].name}; "
                f"about {p['tau_behind_fastest_s'] / 60:.0f} min behind the fastest channel)")
    if c.effect == "temperature_rate":
        return f"the rate of change of {p['channel']}, smoothed over {p['tau_s']:.0f} s (term {c.add[-1].name})"
    if c.effect == "creep":
        return f"creep after each step with a time constant of {p['tau_s']:g} s (term {c.add[0].name})"
    if c.effect == "hysteresis":
        return "hysteresis: an offset that depends on the direction of approach (term dir)"
    if c.effect == "position_thermal_coupling":
        return f"a position-thermal coupling, the stage's gain changing with {p['channel']} (term {c.add[0].name})"
    if c.effect == "geometric_order":
        return f"a higher geometric order (term {c.add[0].name})"
    if c.effect == "unmonitored_drift":
        return (f"a drift of {p.get('rate_um_per_h', 0):+.3f} um/h that no sensor explains (not applied online: "
                "add a sensor near its source, e.g. the interferometer's dead path)")
    if c.effect == "missing_channel":
        return f"channel {p['channel']}, which the model had left out (term {p['channel']})"
    if c.effect == "sensor_exclusion":
        return f"leaving out channel {p['channel']}, which fits the training blocks but hurts held-out ones"
    return c.effect


def _final_model(data: Dataset, given: Model, terms: list[Term], nuisance: dict[str, np.ndarray],
                 steps: list[Candidate], settings: Settings) -> tuple[Model, np.ndarray]:
    """Refit every working term (and nuisance) on all rows, then drop the nuisance.

    The nuisance (an unmonitored drift in run time) is taken at the start of the run, where the
    interferometer was zeroed (paper III.A): the model keeps clean thermal coefficients and the
    bias of the zeroed cell, and predicts nothing for a drift no sensor sees.
    """
    assert data.q is not None
    y = np.asarray(data.q, dtype=np.float64)
    feats = [t.batch(data.t, data.x, data.channels) for t in terms]
    cols = feats + list(nuisance.values())
    fit = ols(np.column_stack(cols), y)
    k = len(terms)
    bias = fit.intercept + sum(float(fit.coef[k + j] * v[0]) for j, v in enumerate(nuisance.values()))
    fitted = [FittedTerm(t, float(fit.coef[i]), float(fit.se[i]), float(fit.p[i])) for i, t in enumerate(terms)]
    fitted.append(FittedTerm(Bias(), bias, fit.intercept_se, fit.intercept_p))
    residual_full = y - fit.intercept - np.column_stack(cols) @ fit.coef
    channels = [c for c in data.channels if any(c in t.channels for t in terms)]
    selection = dict(given.selection)
    selection["discovery"] = {
        "base_model": given.id,
        "steps": [s.to_dict() for s in steps],
        "p_max": settings.p_max,
        "min_holdout_gain": settings.min_holdout_gain,
        "not_applied_online": {
            name: "fitted as a nuisance during discovery, left out of the model (0 at the start of the run)"
            for name in nuisance
        },
    }
    model = Model(
        terms=fitted,
        training=Training.of(data, channels),
        fit={"rmse_um": fit.rmse, "r2": fit.r2, "dof": fit.dof, "rows": len(data),
             "residual_rms_nm": _rms(residual_full) * 1000.0},
        selection=selection,
        provenance={**given.provenance, "created": dt.datetime.now(dt.UTC).isoformat(timespec="seconds"),
                    "discovered_from": data.source, "base_model": given.id},
    )
    return model, residual_full


def discover(data: Dataset, model: Model, settings: Settings = Settings()) -> DiscoveryResult:
    """The whole workflow on one recorded run: disagreements, named effects, the extended model."""
    data = data.valid_rows()
    if data.q is None:
        raise DiscoveryError(f"{data.source}: no q_um column (the command sent to the stage) to compare with")
    n = len(data)
    model.check_channels(list(data.channels), data.source)
    working = [ft.term for ft in model.terms if not isinstance(ft.term, Bias)]
    if n < 3 * (len(working) + 4):
        raise DiscoveryError(f"{data.source}: {n} rows are too few to test effects on a {len(working)}-term model")
    q = np.asarray(data.q, dtype=np.float64)
    residual0 = q - model.predict(data)
    variables = structure_variables(data, settings)
    disagreements = residual_structure(residual0, variables, settings)
    folds = _folds(data)
    delays = channel_delays(data)
    nuisance: dict[str, np.ndarray] = {}
    steps: list[Candidate] = []
    rounds: list[Round] = []
    excluded: set[str] = set()
    pool = selection_pool(model, data)
    penter = float(model.selection.get("penter", 0.05))
    premove = float(model.selection.get("premove", 0.10))
    ctx = _Context(data, working, nuisance, folds, settings, excluded, delays)
    baseline = {
        "model": model.id, "terms": [ft.term.name for ft in model.terms], "rows": n,
        "rms_um": _rms(residual0), "refit_rms_um": math.sqrt(ctx.sse0 / n),
        "holdout_rms_um": math.sqrt(ctx.held0 / n), "durbin_watson": durbin_watson(residual0),
        "lag1_autocorr": lag1_autocorr(residual0), "holdout_blocks": int(np.unique(folds).size),
    }
    for _ in range(settings.max_steps):
        cands = [c for propose in PROPOSERS.values() for c in propose(ctx)]
        cands = [c for c in cands if not (c.effect == "sensor_exclusion" and c.params["channel"] in excluded)]
        winners = sorted((c for c in cands if c.clears), key=lambda c: c.rank_key(settings))
        chosen = winners[0] if winners else None
        rounds.append(Round(cands, chosen))
        if chosen is None:
            break
        if chosen.effect == "unmonitored_drift":
            coef = _nuisance_coef(ctx, chosen.nuisance)
            chosen.params = {"rate_um_per_h": _round_sig(-coef["t"], 3)}
        if chosen.effect == "thermal_lag":
            chosen.params.update(drift_alike(ctx, chosen))
        steps.append(chosen)
        working = [t for t in working if t not in chosen.remove] + chosen.add
        excluded.update(t.name for t in chosen.remove)
        nuisance.update(chosen.nuisance)
        ctx = _Context(data, working, nuisance, folds, settings, excluded, delays)
        back = readmit(data, working, nuisance, pool, excluded, penter, premove)
        if back:  # the stepwise is in-sample: keep what it re-admits only if held-out blocks agree
            wider = _Context(data, working + back, nuisance, folds, settings, excluded, delays)
            if wider.held0 < ctx.held0:
                chosen.params["readmitted"] = [t.name for t in back]
                working, ctx = working + back, wider
    extended, residual1 = _final_model(data, model, working, nuisance, steps, settings)
    coefs = {ft.term.name: ft.coef for ft in extended.terms}
    for step in steps:
        if step.add:
            step.params["coef"] = {t.name: coefs[t.name] for t in step.add if t.name in coefs}
    extended.selection["discovery"]["steps"] = [s.to_dict() for s in steps]
    final = {
        "model": extended.id, "terms": extended.term_names(), "rms_um": _rms(residual1),
        "holdout_rms_um": math.sqrt(ctx.held0 / n),
        "not_applied_online": [s.effect for s in steps if s.effect in NOT_APPLIED_ONLINE],
    }
    gap0 = baseline["holdout_rms_um"]
    final["holdout_gap_removed"] = (gap0 - final["holdout_rms_um"]) / gap0 if gap0 > 0 else 0.0
    summary = summarise(disagreements, steps, baseline, final)
    final["summary"] = summary
    return DiscoveryResult(baseline, disagreements, steps, rounds, final, extended, residual0, residual1,
                           variables, summary)


def _nuisance_coef(ctx: _Context, nuisance: Mapping[str, np.ndarray]) -> dict[str, float]:
    """Coefficients (original units) of nuisance columns added to the working model."""
    cols = [t.batch(ctx.t, ctx.x, ctx.data.channels) for t in ctx.terms] + list(ctx.nuisance.values())
    extra = list(nuisance.values())
    fit = ols(np.column_stack(cols + extra), np.asarray(ctx.data.q, dtype=np.float64))
    return {name: float(fit.coef[len(cols) + j]) for j, name in enumerate(nuisance)}


def summarise(disagreements: Sequence[Disagreement], steps: Sequence[Candidate], baseline: Mapping[str, Any],
              final: Mapping[str, Any]) -> str:
    """The finding in words, for the operator."""
    lines = []
    top = [d for d in disagreements if d.significant][:3]
    if top:
        where = "; ".join(f"{d.description} (bins differ by {d.spread_um * 1000:.0f} nm, p = {d.p_value:.1g})"
                          for d in top)
        lines.append(f"Residuals track: {where}.")
    else:
        lines.append("Residuals show no significant structure against time, position, temperatures, "
                     "their rates, direction or steps.")
    if not steps:
        lines.append(f"No missing effect clears the bar; the model stands "
                     f"(held-out RMS {baseline['holdout_rms_um'] * 1000:.1f} nm).")
    for i, s in enumerate(steps, 1):
        lines.append(
            f"Step {i}: {_describe(s)} cuts the held-out RMS from {s.holdout_rms_before_um * 1000:.1f} to "
            f"{s.holdout_rms_after_um * 1000:.1f} nm ({100 * s.holdout_gain:.0f} % of the gap; p = {s.p_value:.1g})."
        )
        if s.params.get("alike"):
            lines.append(f"  In this run it looks like {s.params['alike']} (their columns correlate "
                         f"{s.params['alike_correlation']:.2f} beyond the model's terms: the room fell and rose "
                         "once), so the two are told apart by noise and a time constant is not pinned; a longer "
                         "run, in which the room settles, tells them apart.")
        if s.params.get("readmitted"):
            lines.append(f"  With it in, the model's own selection re-admits {', '.join(s.params['readmitted'])}, "
                         "which the hidden effect had masked.")
    if steps:
        lines.append(
            f"Overall the held-out RMS went from {baseline['holdout_rms_um'] * 1000:.1f} to "
            f"{final['holdout_rms_um'] * 1000:.1f} nm ({100 * final['holdout_gap_removed']:.0f} % removed)."
        )
    return "\n".join(lines)
