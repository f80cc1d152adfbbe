"""A candidate effect and how it is judged: partial F-test honest about the search, held-out blocks, the bar."""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy import special

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.discovery.confirmation import FreshGain, TauRange, round_sig
from nanodrift.calibration.discovery.diagnostics import ar1_deflation
from nanodrift.calibration.discovery.settings import NOT_APPLIED_ONLINE, Settings
from nanodrift.calibration.discovery.workspace import Workspace, standardise
from nanodrift.model.model import json_float
from nanodrift.model.segments import features
from nanodrift.model.terms import Term


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
    p_iid: float = math.nan  # the same F-test taking rows as independent (what stepwisefit reports)
    trend_like: bool = False  # indistinguishable from a drift in time over this run
    pinned: bool = True  # its searched parameter is determined by the run (see pinned())
    #: per block, (training SSE of the fit on the other blocks, held-out SSE of the block) as a function of the
    #: searched time constant, and its search range: kept (for the round only) so that the τ range and the
    #: τ chosen without each block are computed for the candidate that is named, and only for it
    fold_errors: Callable[[float], tuple[np.ndarray, np.ndarray]] | None = field(default=None, repr=False)
    tau_bounds: tuple[float, float] | None = None
    #: held-out RMS with the time constant chosen without each block (the search confirmed on unseen blocks)
    holdout_rms_nested_um: float = math.nan
    tau_range: TauRange | None = None  # the τ the run supports (named candidates with a searched τ)
    fresh_expected: FreshGain | None = None  # what a fresh run of the same kind should show
    fresh_measured: FreshGain | None = None  # what the fresh run given (--fresh) showed
    fresh_if_source_remains: FreshGain | None = None  # a nuisance: the fresh run still drifts

    @property
    def bar_p(self) -> float:
        """The p the bar tests, and the one a verdict cites (see :attr:`bar_p_test`)."""
        return self.p_iid if self.remove else self.p_value

    @property
    def bar_p_test(self) -> str:
        if self.remove:
            return ("the stepwise's F-test of the channel, rows taken as independent (how firmly the paper's "
                    "selection keeps it)")
        return ("partial F-test of the added terms, autocorrelation-deflated, one degree of freedom per searched "
                "time constant, Bonferroni over the channels tried")

    @property
    def holdout_gain(self) -> float:
        b, a = self.holdout_rms_before_um, self.holdout_rms_after_um
        return (b - a) / b if b > 0 else 0.0

    def rank_key(self, settings: Settings) -> float:
        return self.holdout_rms_after_um * (1.0 + settings.search_penalty * self.searched)

    def to_dict(self, confirmation: bool = True) -> dict[str, Any]:
        """The step for ``--json``; ``confirmation=False``: without the p the bar tested, the τ range and the
        fresh-run gain (the form a model file's ``selection`` records, unchanged by them)."""
        out: dict[str, Any] = {
            "effect": self.effect, "params": self.params, "p_value": json_float(self.p_value),
            "rms_before_um": json_float(self.rms_before_um), "rms_after_um": json_float(self.rms_after_um),
            "holdout_rms_before_um": json_float(self.holdout_rms_before_um),
            "holdout_rms_after_um": json_float(self.holdout_rms_after_um),
            "terms_added": [t.name for t in self.add], "terms_removed": [t.name for t in self.remove],
            "applied_online": self.effect not in NOT_APPLIED_ONLINE,
            "f_stat": json_float(self.f_stat), "holdout_gain": json_float(self.holdout_gain),
            "blocks_improved": json_float(self.blocks_improved),
        }
        if confirmation:
            out.update({"p_bar": json_float(self.bar_p), "p_bar_test": self.bar_p_test})
            if (r := self.tau_range) is not None:
                out.update({"tau_range_s": [r.lo_s, r.hi_s], "tau_pinned": r.pinned, "tau_range": r.words(),
                            "holdout_rms_nested_um": json_float(self.holdout_rms_nested_um)})
                if "tau_behind_fastest_s" in self.params:
                    shift = float(self.params["tau_behind_fastest_s"]) - float(self.params["tau_s"])
                    out["tau_behind_fastest_range_s"] = [round_sig(r.lo_s + shift), round_sig(r.hi_s + shift)]
            for key, value in (("expected", self.fresh_expected), ("measured", self.fresh_measured),
                               ("if_source_remains", self.fresh_if_source_remains)):
                if value is not None:
                    out[f"fresh_gain_{key}"] = json_float(value.ratio)
                    out[f"fresh_rms_{key}_um"] = [json_float(value.rms_before_um), json_float(value.rms_after_um)]
                    out[f"fresh_gain_{key}_by"] = value.method
        return out


def search_tau(objective: Callable[[float], float], lo: float, hi: float, settings: Settings) -> float:
    """Log grid then bounded minimisation on log τ; returns the best τ (3 significant digits)."""
    grid = np.geomspace(lo, hi, settings.grid_points)
    values = np.array([objective(float(tau)) for tau in grid])
    i = int(np.argmin(values))
    a, b = math.log(grid[max(i - 1, 0)]), math.log(grid[min(i + 1, grid.size - 1)])
    best_tau, best = float(grid[i]), float(values[i])
    if b > a:
        # imported here: scipy.optimize costs every fit/calibrate process ~0.3 s of CPU, and only a τ search needs it
        from scipy.optimize import minimize_scalar

        res = minimize_scalar(
            lambda s: objective(math.exp(s)), bounds=(a, b), method="bounded",
            options={"maxiter": settings.refine_evals, "xatol": 0.01},
        )
        if float(res.fun) < best:
            best_tau, best = math.exp(float(res.x)), float(res.fun)
    return round_sig(best_tau)


def pinned(objective: Callable[[float], float], tau: float, n_eff: float, settings: Settings) -> bool:
    """Whether the run tells ``tau`` from ``tau`` x and / ``pin_factor``: both fit worse beyond chance.

    ``objective`` is the training SSE; SSE(τ') - SSE(τ) > SSE(τ) · χ²₁(95 %) / n_eff is the
    likelihood-ratio test of τ' against τ on the effective rows (autocorrelation-deflated).
    """
    best = objective(tau)
    margin = best * settings.pin_chi2 / max(n_eff, 1.0)
    return all(objective(tau * k) - best > margin for k in (settings.pin_factor, 1.0 / settings.pin_factor))


class Context:
    """The data and working model a round of candidates is evaluated against."""

    def __init__(self, data: Dataset, terms: list[Term], nuisance: dict[str, np.ndarray], folds: np.ndarray,
                 settings: Settings, excluded: set[str], delays: Mapping[str, float]) -> None:
        self.data, self.terms, self.nuisance, self.settings = data, terms, nuisance, settings
        self.excluded, self.delays = excluded, delays
        self.t = np.asarray(data.t, dtype=np.float64)
        self.x = np.asarray(data.own_position, dtype=np.float64)  # the modelled axis' position
        assert data.q is not None
        cols = [features(term, data) for term in terms] + list(nuisance.values())
        matrix = np.column_stack(cols) if cols else np.empty((len(data), 0))
        self.ws = Workspace(matrix, np.asarray(data.q, dtype=np.float64), folds)
        self.sse0, self.held_blocks0, self.k0 = self.ws.evaluate(None)
        self.deflate = ar1_deflation(self.ws.residual)
        self.held0 = float(self.held_blocks0.sum())

    def feature(self, term: Term) -> np.ndarray:
        return features(term, self.data)

    def columns(self, feats: Sequence[np.ndarray]) -> np.ndarray:
        return standardise(np.column_stack(feats))

    def judge_term(self, effect: str, term: Term, params: dict[str, Any], alternatives: int) -> Candidate:
        """The candidate that adds ``term`` alone (no parameter searched), judged."""
        return self.judge(Candidate(effect, [term], [], params, 0, alternatives), self.columns([self.feature(term)]))

    def judge(self, cand: Candidate, F: np.ndarray | None, drop: Sequence[int] = ()) -> Candidate:
        n = self.ws.n
        sse1, held_blocks1, k1 = self.ws.evaluate(F, drop)
        held1 = float(held_blocks1.sum())
        cand.blocks_improved = float(np.mean(held_blocks1 < self.held_blocks0))
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
            cand.p_value = min(1.0, float(special.fdtrc(df1, df2, cand.f_stat * deflate)) * cand.alternatives)
            cand.p_iid = float(special.fdtrc(df1, max(n - big - cand.searched, 1), cand.f_stat))
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
                           and cand.blocks_improved >= 0.5 and cand.pinned)
        return cand
