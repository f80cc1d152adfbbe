"""The effect catalogue: each physical effect proposes its term(s), judged against the working model."""

from __future__ import annotations

import math
from collections.abc import Callable
from functools import partial
from typing import Any

import numpy as np

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.discovery.candidates import Candidate, Context, pinned, search_tau
from nanodrift.calibration.discovery.confirmation import round_sig
from nanodrift.calibration.discovery.settings import Settings
from nanodrift.model.axis_terms import AxisProduct
from nanodrift.model.effect_terms import CREEP_DEADBAND_UM, Creep, PositionCoupling, Rate
from nanodrift.model.identify import curvature_candidates
from nanodrift.model.segments import features, run_time_s, spans_s
from nanodrift.model.terms import Channel, ChannelSquare, Direction, Lag, Power, Term

#: the names an effect can be given (the vocabulary of the README's discovery section)
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
    "thermal_curvature",
    "crosstalk",
    "coupled_bending",
)


def _geometric(ctx: Context) -> list[Candidate]:
    axis = ctx.data.axis
    have = {t.k for t in ctx.terms if isinstance(t, Power) and t.axis == axis}  # the axis' own powers
    top = max(have, default=0)
    powers = [Power(k, axis) for k in range(1, max(top + 1, 3) + 1) if k not in have and k <= ctx.settings.max_power]
    return [ctx.judge_term("geometric_order", t, {"order": max(top, t.k), "term": t.name}, 1) for t in powers]


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
    window = data.select(_liveliest_window(data, max_rows))
    temps = {c: np.asarray(v, dtype=np.float64) for c, v in window.channels.items()}
    grid = np.geomspace(1.0, 4 * 3600.0, 36)
    delay: dict[tuple[str, str], float] = {}
    for ref in channels:
        lagged = [features(Lag(ref, float(tau)), window) for tau in grid]
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


def _thermal_response(ctx: Context) -> list[Candidate]:
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
            feats = [*base, features(Lag(c, tau), ctx.data)]
            return ctx.ws.sse_with(ctx.columns(feats))

        tau_max = min(s.lag_tau_s[1], max(max(spans_s(ctx.data)), 2 * s.lag_tau_s[0]))
        tau = search_tau(sse, s.lag_tau_s[0], tau_max, s)
        extra = [] if c in have else [Channel(c)]
        behind_reference = round_sig(tau + ctx.delays.get(c, 0.0))
        if tau <= s.rate_tau_max_s:
            term: Term = Rate(c, tau)
            effect, params = "temperature_rate", {"channel": c, "tau_s": tau}
        else:
            term = Lag(c, tau)
            effect, params = "thermal_lag", {"channel": c, "tau_s": tau, "tau_behind_fastest_s": behind_reference}
        if Lag(c, tau).name in have or Rate(c, tau).name in have:
            continue
        feats = [*base, ctx.feature(term)]
        cand = Candidate(effect, [*extra, term], [], params, 1, len(channels),
                         trend_like=tau >= 0.9 * tau_max,  # as long as the run: a trend, not an identified lag
                         pinned=pinned(sse, tau, ctx.ws.n * ctx.deflate, s), tau_bounds=(s.lag_tau_s[0], tau_max),
                         fold_errors=partial(_fold_errors_lag, ctx, c, base))
        out.append(ctx.judge(cand, ctx.columns(feats)))
    return _prefer_fastest(out, ctx)


def _fold_errors_lag(ctx: Context, channel: str, base: list[np.ndarray], tau: float
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Per block (training SSE without it, its held-out SSE) with ``lag(channel, tau)`` (and the channel) added."""
    return ctx.ws.fold_errors(ctx.columns([*base, features(Lag(channel, tau), ctx.data)]))


def _fold_errors_creep(ctx: Context, tau: float) -> tuple[np.ndarray, np.ndarray]:
    return ctx.ws.fold_errors(ctx.columns([features(Creep(tau), ctx.data)]))


def _prefer_fastest(cands: list[Candidate], ctx: Context) -> list[Candidate]:
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


def _missing_channel(ctx: Context) -> list[Candidate]:
    """A monitored channel the model left out (stepwise can drop one when another effect masks it)."""
    have = {t.name for t in ctx.terms}
    missing = [c for c in ctx.data.channels if c not in have and c not in ctx.excluded]
    return [ctx.judge_term("missing_channel", Channel(c), {"channel": c}, len(missing)) for c in missing]


def _thermal_curvature(ctx: Context) -> list[Candidate]:
    """A channel's square (the bracket's bending), where the run spans enough of the channel to see it
    (:func:`nanodrift.model.identify.curvature_candidates`: records of days, not a 0.5 °C calibration)."""
    if any(isinstance(t, ChannelSquare) for t in ctx.terms):
        return []
    squares = curvature_candidates(ctx.data, ctx.excluded)
    return [ctx.judge_term("thermal_curvature", t, {"channel": t.channel, "centre_c": t.centre_c}, len(squares))
            for t in squares]


def _hysteresis(ctx: Context) -> list[Candidate]:
    """``dir``, when the run approaches its points from both sides.

    In forward-only sweeps the only step down is the return to 0, so ``dir`` there is just "the row
    at x = 0" (a geometric or creep detail, not hysteresis): the direction must be the minority on
    at least ``min_direction_share`` of the rows.
    """
    term = Direction(axis=ctx.data.axis)
    if term in ctx.terms:
        return []
    f = ctx.feature(term)
    if _minority_direction_share(f) < ctx.settings.min_direction_share:
        return []
    return [ctx.judge(Candidate("hysteresis", [term], [], {"deadband_um": term.deadband_um}, 0, 1),
                      ctx.columns([f]))]


def _minority_direction_share(direction: np.ndarray) -> float:
    """The share of rows reached moving in the less common direction (0: every point from one side)."""
    return min(float(np.mean(direction > 0)), float(np.mean(direction < 0)))


#: the run that shows what a forward-only calibration cannot (the simulated cell, then the stage)
BIDIRECTIONAL_HINT = ("record a bidirectional run (up and down sweeps): `nanodrift simulate --scenario bidirectional` "
                      "on the simulated cell, `nanodrift calibrate` with `[procedure] trajectory = \"bidirectional\"` "
                      "on the stage")


def untestable(data: Dataset, settings: Settings) -> list[dict[str, str]]:
    """Effects this run's trajectory cannot show, whatever the model: ``{"effect", "reason", "hint"}``.

    Read from the data's own motion, not from how it was recorded: a forward-only calibration (the
    paper's Fig. 7) approaches every point moving up, so ``dir`` only marks the return to 0 and a
    direction-dependent offset (hysteresis) is invisible; a run with no steps cannot show creep. In a
    multi-axis cell, the modelled axis' own motion.
    """
    x = np.asarray(data.own_position, dtype=np.float64)
    out = []
    direction = features(Direction(axis=data.axis), data)
    share = _minority_direction_share(direction)
    if share < settings.min_direction_share:
        way = "up" if float(np.mean(direction > 0)) >= 0.5 else "down"
        out.append({
            "effect": "hysteresis",
            "reason": f"{100 * (1 - share):.0f} % of the rows are reached moving {way} (forward-only sweeps), "
                      "so an offset that depends on the direction of approach cannot show",
            "hint": BIDIRECTIONAL_HINT,
        })
    if not np.any(np.abs(np.diff(x)) > CREEP_DEADBAND_UM):
        out.append({
            "effect": "creep",
            "reason": f"the stage never moves by more than {CREEP_DEADBAND_UM:g} µm, so settling after a step "
                      "cannot show",
            "hint": "record a run with steps (the paper's calibration trajectory: `nanodrift calibrate`)",
        })
    return out


def _coupling(ctx: Context) -> list[Candidate]:
    terms = [PositionCoupling(c, ctx.data.axis) for c in ctx.data.channels]
    return [ctx.judge_term("position_thermal_coupling", t, {"channel": t.channel}, len(terms))
            for t in terms if t not in ctx.terms]


def _creep(ctx: Context) -> list[Candidate]:
    if any(isinstance(t, Creep) for t in ctx.terms) or not np.any(np.abs(np.diff(ctx.x)) > CREEP_DEADBAND_UM):
        return []

    axis = ctx.data.axis

    def sse(tau: float) -> float:
        return ctx.ws.sse_with(ctx.columns([features(Creep(tau, axis=axis), ctx.data)]))

    tau = search_tau(sse, *ctx.settings.creep_tau_s, ctx.settings)
    term = Creep(tau, axis=axis)
    cand = Candidate("creep", [term], [], {"tau_s": tau}, 1, 1,
                     pinned=pinned(sse, tau, ctx.ws.n * ctx.deflate, ctx.settings),
                     tau_bounds=ctx.settings.creep_tau_s, fold_errors=partial(_fold_errors_creep, ctx))
    return [ctx.judge(cand, ctx.columns([ctx.feature(term)]))]


def _drift(ctx: Context) -> list[Candidate]:
    if "t" in ctx.nuisance:
        return []
    t_h = run_time_s(ctx.data) / 3600.0
    cand = Candidate("unmonitored_drift", [], [], {}, 0, 1, nuisance={"t": t_h}, trend_like=True)
    return [ctx.judge(cand, ctx.columns([t_h]))]


def _exclusion(ctx: Context) -> list[Candidate]:
    channels = [(i, t) for i, t in enumerate(ctx.terms) if isinstance(t, Channel)]
    if len(channels) < 2:
        return []
    return [ctx.judge(Candidate("sensor_exclusion", [], [t], {"channel": t.name}, 0, len(channels)), None, drop=[i])
            for i, t in channels]


def _cross_axis(ctx: Context) -> list[Candidate]:
    """What only a multi-axis cell shows: the modelled axis moved by another axis' position.

    ``crosstalk``: a share of another axis' position (``y`` in x's model), whether the actuators
    couple or the axes are not orthogonal: both move x in proportion to y, the data cannot tell
    them apart and the compensation is the same (the share in µrad is the equivalent angle).
    ``coupled_bending``: the stage bends when both axes are out (``x*y``). Each is named only if it
    clears the same bar as every effect.
    """
    data = ctx.data
    if not data.multi_axis:
        return []
    axis, others = data.axis, [b for b in data.axes if b != data.axis]
    out = []
    for b in others:
        term = Power(1, b)
        if term not in ctx.terms:
            out.append(ctx.judge_term("crosstalk", term, {"axis": b}, len(others)))
        product = AxisProduct(axis, b)
        if product not in ctx.terms:
            out.append(ctx.judge_term("coupled_bending", product, {"axes": product.name}, len(others)))
    return out


PROPOSERS: dict[str, Callable[[Context], list[Candidate]]] = {
    "geometric_order": _geometric,
    "thermal_response": _thermal_response,
    "missing_channel": _missing_channel,
    "thermal_curvature": _thermal_curvature,
    "hysteresis": _hysteresis,
    "position_thermal_coupling": _coupling,
    "creep": _creep,
    "unmonitored_drift": _drift,
    "sensor_exclusion": _exclusion,
    "cross_axis": _cross_axis,
}


def told_apart(cands: list[Candidate], settings: Settings) -> list[Candidate]:
    """A drift in time clears only if it predicts held-out blocks clearly better than any thermal lag.

    In a run where the room falls and rises once, a lag of hours and a line in time explain the
    same slow disagreement; naming the drift then fits the thermal coefficients around a trend that
    was thermal, and the written model (the drift left out, the bias of the run's start) is worst
    exactly where the lag acts. ``drift_vs_lag``: the drift's held-out RMS must be below that
    fraction of the best lag candidate's (pinned or not: it only has to show the run is ambiguous).
    """
    lags = [c.holdout_rms_after_um for c in cands if c.effect in ("thermal_lag", "temperature_rate")]
    if not lags:
        return cands
    for c in cands:
        if c.effect == "unmonitored_drift" and c.clears and c.holdout_rms_after_um > settings.drift_vs_lag * min(lags):
            c.clears = False
            c.params["not_told_from"] = "thermal_lag"
    return cands


def drift_alike(ctx: Context, chosen: Candidate) -> dict[str, Any]:
    """Whether a named thermal_lag looks, in this run, like an unmonitored drift (a line in time).

    When the room only falls and rises once during the run (the paper's 24-cycle calibration), what
    the thermocouples cannot explain of a lag of hours is nearly a straight line in time: the two
    effects are then told apart by noise, and the lag's τ is not pinned. The correlation of the two
    columns, each beyond the working model's terms, says so; the operator is told to record longer.
    """
    t_h = run_time_s(ctx.data) / 3600.0
    extra = [ctx.columns([ctx.feature(t)]) for t in chosen.add[:-1]]
    base = np.column_stack([ctx.ws.A[:, : ctx.ws.k], *extra])

    def beyond(v: np.ndarray) -> np.ndarray:
        coef, *_ = np.linalg.lstsq(base, v, rcond=None)
        rest: np.ndarray = v - base @ coef
        return rest

    a, b = beyond(ctx.feature(chosen.add[-1])), beyond(t_h)
    denom = math.sqrt(float(a @ a) * float(b @ b))
    corr = abs(float(a @ b)) / denom if denom > 0 else 0.0
    if corr < ctx.settings.twin_correlation:
        return {}
    return {"alike": "unmonitored_drift", "alike_correlation": round_sig(corr, 3)}
