"""The discover() loop: try the catalogue, name the best effect, refit, re-admit, repeat; then the model."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.discovery.candidates import Candidate, Context
from nanodrift.calibration.discovery.catalogue import PROPOSERS, channel_delays, drift_alike, told_apart, untestable
from nanodrift.calibration.discovery.confirmation import (
    MEASURED_METHOD,
    NUISANCE_METHOD,
    FreshGain,
    expected_fresh,
    hidden_by_fit_um2,
    nested_held_out,
    round_sig,
    tau_range,
    worse_than,
)
from nanodrift.calibration.discovery.diagnostics import (
    Disagreement,
    durbin_watson,
    lag1_autocorr,
    residual_structure,
    structure_variables,
)
from nanodrift.calibration.discovery.settings import DEFAULT_SETTINGS, NOT_APPLIED_ONLINE, Settings
from nanodrift.calibration.discovery.summary import summarise
from nanodrift.model import hac
from nanodrift.model.identify import holdout_blocks, model_covariance, ols
from nanodrift.model.model import FittedTerm, Model, Training
from nanodrift.model.provenance import created_now, software
from nanodrift.model.segments import design_matrix, features, runs
from nanodrift.model.stepwise import stepwisefit
from nanodrift.model.terms import Bias, Term, UnknownTermError, parse_term


class DiscoveryError(ValueError):
    """The data cannot support discovery (too few rows, no q column); the message says why."""


def selection_pool(model: Model, data: Dataset) -> list[Term]:
    """The terms the given model's own selection chose from (its stepwise candidates) that the data can feed."""
    pool = []
    for name in model.selection.get("candidates") or []:
        try:
            term = parse_term(str(name), data.axes)
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
    cols = [features(term, data) for term in [*working, *optional]]
    forced = len(working) + len(nuisance)
    X = np.column_stack(cols[: len(working)] + list(nuisance.values()) + cols[len(working):])
    keep = np.arange(X.shape[1]) < forced
    result = stepwisefit(X, np.asarray(data.q, dtype=np.float64), penter=penter, premove=max(premove, penter),
                         inmodel=keep.copy(), keep=keep)
    return [term for j, term in enumerate(optional) if result.inmodel[forced + j]]


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
    #: effects this run's trajectory cannot show, with the run that would (also in ``final["untestable"]``)
    untestable: list[dict[str, str]] = field(default_factory=list)
    settings: Settings = DEFAULT_SETTINGS

    @property
    def found(self) -> bool:
        """Whether an effect was named; if not, ``model`` is the given model and nothing new should be written."""
        return bool(self.steps)

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


def _final_model(data: Dataset, given: Model, terms: list[Term], nuisance: dict[str, np.ndarray],
                 steps: list[Candidate], settings: Settings) -> tuple[Model, np.ndarray]:
    """Refit every working term (and nuisance) on all rows, then drop the nuisance.

    The nuisance (an unmonitored drift in run time) is taken at the start of the run, where the
    interferometer was zeroed (paper III.A): the model keeps clean thermal coefficients and the
    bias of the zeroed cell, and predicts nothing for a drift no sensor sees.
    """
    assert data.q is not None
    y = np.asarray(data.q, dtype=np.float64)
    X = design_matrix(terms, data)  # the terms' features, then the nuisance's: one copy of the rows
    if nuisance:
        X = np.column_stack([X, *nuisance.values()])
    fit = ols(X, y, hac.run_ids(len(y), runs(data)))
    k = len(terms)
    bias = fit.intercept + sum(float(fit.coef[k + j] * v[0]) for j, v in enumerate(nuisance.values()))
    fitted = [FittedTerm(t, float(fit.coef[i]), float(fit.se[i]), float(fit.p[i])) for i, t in enumerate(terms)]
    fitted.append(FittedTerm(Bias(), bias, fit.intercept_se, fit.intercept_p))
    covariance = model_covariance(X, y, fit, data, terms, X[:, k:] if nuisance else None)
    residual_full = y - fit.intercept - X @ fit.coef
    channels = [c for c in data.channels if any(c in t.channels for t in terms)]
    selection = dict(given.selection)
    selection["discovery"] = {
        "base_model": given.id,
        "steps": [s.to_dict(confirmation=False) for s in steps],
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
        fit={"rmse_um": fit.rmse, "r2": fit.r2, "dof": fit.dof, "se_method": fit.se_method, "hac_lag": fit.hac_lag,
             "rows": len(data),
             "residual_rms_nm": _rms(residual_full) * 1000.0},
        selection=selection,
        provenance={**given.provenance, "software": software(),
                    "created": created_now(),
                    "discovered_from": data.source, "base_model": given.id},
        covariance=covariance,
    )
    return model, residual_full


def discover(data: Dataset, model: Model, settings: Settings = DEFAULT_SETTINGS,
             fresh: Dataset | None = None) -> DiscoveryResult:
    """The whole workflow on one recorded run: disagreements, named effects, the extended model.

    Each named step carries the gain a fresh run of the same kind should show (and, for a searched
    time constant, the range the run supports); ``fresh``: a run discovery never saw, on which each
    step's gain is also measured.
    """
    if fresh is not None:
        fresh = _checked_run(fresh, model, empty="to measure the fresh-run gain on")
    data = _checked_run(data, model)
    n = len(data)
    working = [ft.term for ft in model.terms if not isinstance(ft.term, Bias)]
    if n < 3 * (len(working) + 4):
        raise DiscoveryError(f"{data.source}: {n} rows are too few to test effects on a {len(working)}-term model")
    q = np.asarray(data.q, dtype=np.float64)
    residual0 = q - model.predict(data)
    variables = structure_variables(data, settings)
    disagreements = residual_structure(residual0, variables, settings)
    folds = holdout_blocks(data)
    if np.any(np.diff(folds) < 0) or np.unique(folds).size < 2:  # cycles out of time order: time blocks
        folds = (np.arange(n) * 5) // max(n, 1)
    delays = channel_delays(data)
    nuisance: dict[str, np.ndarray] = {}
    steps: list[Candidate] = []
    rounds: list[Round] = []
    # channels the model's coherent selection left out on purpose (they would trade thermocouple noise against
    # each other: nanodrift.model.identify) are not "missing": neither proposed nor re-admitted
    excluded: set[str] = set(model.selection.get("opposing_dropped") or ())
    pool = selection_pool(model, data)
    penter = float(model.selection.get("penter", 0.05))
    premove = float(model.selection.get("premove", 0.10))
    ctx = Context(data, working, nuisance, folds, settings, excluded, delays)
    searched = 0  # time constants searched so far (each a fitted parameter the fresh-run estimate charges)
    search_hidden_mse = 0.0  # um^2: held-out MSE the named time constants gain when chosen without the block
    snapshots: list[tuple[list[Term], dict[str, np.ndarray]]] = []  # the working model after each step
    baseline: dict[str, Any] = {
        "model": model.id, "terms": [ft.term.name for ft in model.terms], "rows": n,
        "rms_um": _rms(residual0), "refit_rms_um": math.sqrt(ctx.sse0 / n),
        "holdout_rms_um": math.sqrt(ctx.held0 / n), "durbin_watson": durbin_watson(residual0),
        "lag1_autocorr": lag1_autocorr(residual0), "holdout_blocks": int(np.unique(folds).size),
    }
    for _ in range(settings.max_steps):
        cands = told_apart([c for propose in PROPOSERS.values() for c in propose(ctx)], settings)
        cands = [c for c in cands if not (c.effect == "sensor_exclusion" and c.params["channel"] in excluded)]
        winners = sorted((c for c in cands if c.clears), key=lambda c: c.rank_key(settings))
        chosen = winners[0] if winners else None
        rounds.append(Round(cands, chosen))
        searched_errors = chosen.fold_errors if chosen is not None else None
        for c in cands:  # each holds this round's working model (its Gram matrices): keep none beyond the round
            c.fold_errors = None
        if chosen is None:
            break
        if chosen.effect == "unmonitored_drift":
            rate = float(_extra_coefs(ctx, [*ctx.nuisance.values(), chosen.nuisance["t"]])[-1])
            chosen.params = {"rate_um_per_h": round_sig(-rate, 3)}
        if chosen.effect == "thermal_lag":
            chosen.params.update(drift_alike(ctx, chosen))
        if searched_errors is not None and chosen.tau_bounds is not None:
            tau = float(chosen.params["tau_s"])
            rows = np.array([b - a for a, b in ctx.ws.bounds], dtype=np.float64)
            chosen.tau_range = tau_range(worse_than(searched_errors, tau, rows, settings), tau, chosen.tau_bounds)
            nested = float(np.sum(nested_held_out(searched_errors, tau, chosen.tau_bounds)))
            chosen.holdout_rms_nested_um = math.sqrt(nested / n)
            # what choosing τ on all rows hid from the held-out blocks, in MSE (carried by every later model)
            search_hidden_mse += max(chosen.holdout_rms_nested_um**2 - chosen.holdout_rms_after_um**2, 0.0)
        steps.append(chosen)
        residual_before, params_before = ctx.ws.residual, ctx.k0 + searched  # not the whole context: memory
        searched += chosen.searched
        working = [t for t in working if t not in chosen.remove] + chosen.add
        excluded.update(t.name for t in chosen.remove)
        nuisance.update(chosen.nuisance)
        ctx = Context(data, working, nuisance, folds, settings, excluded, delays)
        back = readmit(data, working, nuisance, pool, excluded, penter, premove)
        if back:  # the stepwise is in-sample: keep what it re-admits only if held-out blocks agree
            wider = Context(data, working + back, nuisance, folds, settings, excluded, delays)
            if wider.held0 < ctx.held0:
                chosen.params["readmitted"] = [t.name for t in back]
                working, ctx = working + back, wider
        before_fixed = residual_before - _drift_column(ctx) if chosen.nuisance else residual_before
        chosen.fresh_expected, chosen.fresh_if_source_remains = _expected(
            before_fixed, residual_before, params_before, ctx, searched, search_hidden_mse)
        snapshots.append((list(working), dict(nuisance)))
    extended, residual1 = _final_model(data, model, working, nuisance, steps, settings)
    coefs = {ft.term.name: ft.coef for ft in extended.terms}
    for step in steps:
        if step.add:
            step.params["coef"] = {t.name: coefs[t.name] for t in step.add if t.name in coefs}
    extended.selection["discovery"]["steps"] = [s.to_dict(confirmation=False) for s in steps]
    final: dict[str, Any] = {
        "model": extended.id, "terms": extended.term_names(), "rms_um": _rms(residual1),
        "holdout_rms_um": math.sqrt(ctx.held0 / n),
        "not_applied_online": [s.effect for s in steps if s.effect in NOT_APPLIED_ONLINE],
    }
    if steps:
        given_fixed = residual0 - _drift_column(ctx) if nuisance else residual0
        overall, _ = _expected(given_fixed, residual0, len(model.terms), ctx, searched, search_hidden_mse)
        final.update(_fresh_keys("expected", overall))
        if fresh is not None:
            models = [model] + [_final_model(data, model, list(w), dict(u), steps[:i + 1], settings)[0]
                                for i, (w, u) in enumerate(snapshots)]
            errors = [_rms(np.asarray(fresh.q) - m.predict(fresh)) for m in models]
            for i, step in enumerate(steps):
                step.fresh_measured = FreshGain(errors[i], errors[i + 1], MEASURED_METHOD)
            final.update(_fresh_keys("measured", FreshGain(errors[0], errors[-1], MEASURED_METHOD)))
    gap0 = baseline["holdout_rms_um"]
    final["holdout_gap_removed"] = (gap0 - final["holdout_rms_um"]) / gap0 if gap0 > 0 else 0.0
    if not steps:  # nothing named: the given model stands (a refit under a new id would be the same model)
        extended = model
        final["model"] = model.id
    blind = untestable(data, settings)
    final["untestable"] = blind
    summary = summarise(disagreements, steps, baseline, final, blind)
    final["summary"] = summary
    return DiscoveryResult(baseline, disagreements, steps, rounds, final, extended, residual0, residual1,
                           variables, summary, blind, settings)


def _extra_coefs(ctx: Context, extra: Sequence[np.ndarray]) -> np.ndarray:
    """Coefficients (original units) of the columns ``extra`` fitted beside the working terms."""
    cols = [ctx.feature(t) for t in ctx.terms] + list(extra)
    return ols(np.column_stack(cols), np.asarray(ctx.data.q, dtype=np.float64)).coef[len(ctx.terms):]


def _checked_run(run: Dataset, model: Model, empty: str | None = None) -> Dataset:
    """The run's valid rows; refused without commands, rows (``empty``: for what) or a channel the model reads."""
    run = run.valid_rows()
    if run.q is None:
        raise DiscoveryError(f"{run.source}: no q_um column (the command sent to the stage) to compare with")
    if empty is not None and len(run) == 0:
        raise DiscoveryError(f"{run.source}: no valid rows {empty}")
    model.check_channels(list(run.channels), run.source)
    return run


def _drift_column(ctx: Context) -> np.ndarray:
    """What the working fit attributes to its nuisance columns (a drift no sensor sees), µm per row; 0 at t = 0."""
    if not ctx.nuisance:
        return np.zeros(ctx.ws.n)
    coef = _extra_coefs(ctx, list(ctx.nuisance.values()))
    return sum((coef[j] * v for j, v in enumerate(ctx.nuisance.values())), np.zeros(ctx.ws.n))


def _expected(before_fixed: np.ndarray, before: np.ndarray, params_before: int, after: Context,
              searched: int, search_hidden_mse: float) -> tuple[FreshGain, FreshGain | None]:
    """(the expected fresh-run RMS without and with the working model ``after``, the same if a nuisance remains).

    With a nuisance (a drift not applied online) the first is judged on a fresh run without it (its
    source fixed): the model without the effect keeps the coefficients that absorbed the drift
    (``before_fixed``); the second on one that still drifts, where the written model (drift left
    out, bias of the run's start) errs by the whole drift. ``search_hidden_mse``: what the held-out
    blocks gain when each named time constant is chosen without them.
    """
    n = after.ws.n
    in_after = math.sqrt(after.sse0 / n)
    omega = hidden_by_fit_um2(in_after, math.sqrt(after.held0 / n + search_hidden_mse))
    params_after = after.k0 + searched
    if not after.nuisance:
        return expected_fresh(_rms(before), in_after, omega, params_before, params_after), None
    fixed = expected_fresh(_rms(before_fixed), in_after, omega, params_before, params_after, NUISANCE_METHOD)
    still_drifting = after.ws.residual + _drift_column(after)  # the written model leaves the drift out
    remains = expected_fresh(_rms(before), _rms(still_drifting), omega, params_before, params_after,
                             "as above, on a fresh run that still drifts")
    return fixed, remains


def _fresh_keys(kind: str, value: FreshGain) -> dict[str, Any]:
    return {f"fresh_gain_{kind}": value.ratio, f"fresh_rms_{kind}_um": [value.rms_before_um, value.rms_after_um],
            f"fresh_gain_{kind}_by": value.method}
