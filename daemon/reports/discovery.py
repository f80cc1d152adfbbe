"""The discovery report for a lab notebook: figures (150 dpi PNG + SVG) and ``report.md``, written atomically.

Figures (each ``.png`` and ``.svg``):
- ``residuals_vs_<variable>``: the residuals of the given and the extended model against each variable
  that located the gap, titled in words with units in µm and °C: time, temperatures and rates as a
  scatter of every row plus binned means; a genuinely discrete variable (``dir``: down/up; step sizes
  or positions that take a few values) as points per value, jittered, each beside its mean and 95 %
  interval (a line between "down" and "up" would mean nothing). The given model is drawn last (never
  hidden); a refit that changes nothing is not drawn twice; the legend sits below the axes;
- ``gap``: the RMS on held-out blocks and on all rows, step by step.

``report.md`` says what was found, what the run cannot show and how to record one that can, the
candidates of every round with their parameters in words, why each was or was not named, and every
rule the method applies (with the values of this run's bar).

One module of ~480 lines on purpose: the figures and the text describe the same findings and change
together; apart, each would have to re-derive what the other shows.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.atomic import atomic_write_text
from nanodrift.calibration.discovery import Candidate, DiscoveryResult
from nanodrift.calibration.discovery.settings import Settings
from nanodrift.reports.validation import STYLE, WITH_COLOR, WITHOUT_COLOR, pyplot, save_figure, with_footer

#: where the method is written out in full (the report's Method section points there)
METHOD_DOC = "daemon/calibration/discovery/METHOD.md"

#: the variable that shows each effect best, for the before/after figures
EFFECT_VARIABLE = {
    "geometric_order": "x",
    "position_thermal_coupling": "x",
    "hysteresis": "dir",
    "creep": "last_step",
    "unmonitored_drift": "t",
    "missing_channel": "t",
    "sensor_exclusion": "t",
}

#: effect names (the JSON vocabulary) in words
EFFECT_WORDS = {
    "geometric_order": "a higher geometric order",
    "thermal_lag": "a thermal lag",
    "temperature_rate": "the rate of change of a temperature",
    "hysteresis": "hysteresis",
    "position_thermal_coupling": "a position–thermal coupling",
    "creep": "creep",
    "unmonitored_drift": "an unmonitored drift",
    "sensor_exclusion": "leaving a sensor out",
    "missing_channel": "a channel the model left out",
    "thermal_curvature": "a curvature in a temperature (bending)",
    "crosstalk": "crosstalk from another axis",
    "coupled_bending": "coupled bending of two axes",
}

BEFORE_COLOR, AFTER_COLOR = WITH_COLOR, WITHOUT_COLOR  # given model: orange, extended: blue
MAX_LEVELS = 8  # a variable with this many distinct values (or tight clusters) or fewer is drawn per value
#: the variables that can be genuinely discrete (a direction, step sizes, positions a run visits); time,
#: temperatures and their rates are continuous however few rows a run has
MAYBE_DISCRETE = ("dir", "last_step", "time_since_step", "x")
SAME_NM = 0.1  # residuals that agree within this are one series (a refit that changes nothing)
MINUS = "−"


# ----- variables in words ------------------------------------------------------------------------------
def describe_variable(name: str, settings: Settings) -> tuple[str, str, Callable[[np.ndarray], np.ndarray]]:
    """(words for a title, axis label with its unit, transform of the stored values to that unit)."""
    same = np.asarray
    if name == "t":
        return "time", "time since the start of the run (h)", lambda v: v / 3600.0
    if name == "x":
        return "position", "position x (µm)", same
    if name == "dir":
        return "the direction of the last move", "direction of the last move", same
    if name == "last_step":
        return "the size of the last step", "size of the last step (µm)", same
    if name == "time_since_step":
        return "the time since the last step", "time since the last step (s)", same
    if name.startswith("rate(") and name.endswith(")"):
        channel = name[5:-1]
        return (f"the rate of change of {channel}",
                f"rate of change of {channel} (°C/h, smoothed over {settings.rate_probe_tau_s:g} s)", same)
    return f"temperature {name}", f"temperature {name} (°C)", same


def _category_label(name: str, value: float) -> str:
    if name == "dir":
        return {-1.0: "down", 0.0: "no move yet", 1.0: "up"}.get(float(value), f"{value:g}")
    return f"{value:.3g}".replace("-", MINUS)


# ----- figures -----------------------------------------------------------------------------------------
def _binned(values: np.ndarray, r: np.ndarray, bins: int = 12) -> tuple[np.ndarray, np.ndarray]:
    edges = np.unique(np.quantile(values, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)
    present = [i for i in range(edges.size - 1) if np.any(idx == i)]
    return (np.array([values[idx == i].mean() for i in present]), np.array([r[idx == i].mean() for i in present]))


def _refit_changes_nothing(result: DiscoveryResult) -> bool:
    """Nothing found, and the given terms refitted on this run move no residual by more than :data:`SAME_NM`."""
    before, after = result.residual_before, result.residual_after
    return not result.found and before.shape == after.shape and (
        before.size == 0 or float(np.max(np.abs(before - after))) * 1000.0 <= SAME_NM)


def _series(result: DiscoveryResult) -> list[tuple[np.ndarray, str, str]]:
    """(residual µm, label, colour) per model drawn: the given model last, so it is never hidden.

    When nothing is found the second series is the given terms refitted on this run; when that changes
    nothing (:func:`_refit_changes_nothing`) it is not drawn (the legend's title says why)."""
    if _refit_changes_nothing(result):
        return [(result.residual_before, "given model", BEFORE_COLOR)]
    label = "extended model" if result.found else "the given terms refitted on this run"
    return [(result.residual_after, label, AFTER_COLOR), (result.residual_before, "given model", BEFORE_COLOR)]


def _opaque_legend(ax: Any, result: DiscoveryResult) -> None:
    """The legend below the axes (never on the data), its scatter entries solid and large enough to see."""
    plt = pyplot()
    title = (f"nothing found; refitting the given terms on this run changes no residual by more than {SAME_NM:g} nm"
             if _refit_changes_nothing(result) else None)
    handles, labels = ax.get_legend_handles_labels()
    legend = ax.legend(handles, labels, loc="upper center", bbox_to_anchor=(0.5, -0.15), framealpha=0.85,
                       ncol=2 if max(len(t) for t in labels) <= 48 else 1, title=title,
                       title_fontsize=plt.rcParams["legend.fontsize"])
    for handle in legend.legend_handles:
        if handle is not None:
            handle.set_alpha(1.0)
            if hasattr(handle, "set_sizes"):
                handle.set_sizes([20.0])


def figure_residuals(result: DiscoveryResult, variable: str) -> Any:
    """The residuals before and after against ``variable``: scatter + binned means, or points per value."""
    plt = pyplot()
    with plt.rc_context(STYLE):
        words, label, transform = describe_variable(variable, result.settings)
        values = transform(np.asarray(result.variables[variable][1], dtype=np.float64))
        fig, ax = plt.subplots(figsize=(7.5, 5.4))
        levels = _levels(values) if variable in MAYBE_DISCRETE else None
        if levels is not None:
            _draw_categorical(ax, result, variable, *levels)
        else:
            _draw_continuous(ax, result, values)
        ax.axhline(0.0, color="0.4", lw=0.7, zorder=1)
        ax.set_xlabel(label)
        ax.set_ylabel(f"residual q {MINUS} q_pred (nm)")
        ax.set_title(f"Residuals against {words}")
        ax.grid(alpha=0.3)
        _opaque_legend(ax, result)
        fig.tight_layout()
        return fig


def _levels(values: np.ndarray, most: int = MAX_LEVELS) -> tuple[np.ndarray, np.ndarray] | None:
    """(each value replaced by its level's mean, the levels) when the values are at most ``most`` levels.

    A level is an exact value, or a tight cluster: measured steps are 29.6 or -479.9 µm, so values
    closer than a hundredth of the range are one level when every such cluster is narrower than a
    twentieth of the range (a forward-only run's "last step" is three levels: 0, +30, -480). Values
    spread evenly over their range (time, a temperature) form one wide cluster: not levels, None.
    """
    if values.size == 0:
        return None
    distinct = np.unique(values)
    if distinct.size <= most:
        return values, distinct
    span = float(np.ptp(values))
    ordered = np.sort(values)
    splits = ordered[1:][np.diff(ordered) > span / 100.0]
    if splits.size + 1 > most:
        return None
    label = np.searchsorted(splits, values, side="right")
    clusters = [values[label == k] for k in range(splits.size + 1)]
    if max(float(np.ptp(c)) for c in clusters) > span / 20.0:
        return None
    means = np.array([float(c.mean()) for c in clusters])
    return means[label], means


def _draw_continuous(ax: Any, result: DiscoveryResult, values: np.ndarray) -> None:
    """Every row as a faint point at its value, and the binned means as a line (drawn over the points)."""
    stride = max(1, values.size // 20000)  # a scatter of 1e6 points says nothing more than 2e4
    series = _series(result)
    for k, (r, label, colour) in enumerate(series):
        nm = r * 1000.0
        ax.scatter(values[::stride], nm[::stride], s=5, alpha=0.25, color=colour, linewidths=0,
                   label=f"{label}: each row", zorder=2)
        centres, means = _binned(values, nm)
        given_on_top = len(series) > 1 and k == len(series) - 1
        ax.plot(centres, means, "o--" if given_on_top else "o-", color=colour, lw=1.8, ms=5,
                mfc="white" if given_on_top else colour, label=f"{label}: binned mean", zorder=3 + k)


def _draw_categorical(ax: Any, result: DiscoveryResult, variable: str, values: np.ndarray,
                      categories: np.ndarray) -> None:
    """Per value and model, the rows as a jittered strip and beside it their mean with its 95 % interval.

    The mean sits beside its strip, not on it, so a value with one row still shows that row; a value
    with few rows draws them larger and darker."""
    rng = np.random.default_rng(0)  # the jitter only spreads the points; the same report draws the same
    stride = max(1, values.size // 20000)
    series = _series(result)
    width = 0.8 / len(series)  # each model's slot within a value's ±0.4
    for k, (r, label, colour) in enumerate(series):
        nm = r * 1000.0
        slot = -0.4 + width * (k + 0.5)
        strip, mean_at = slot - 0.18 * width, slot + 0.25 * width
        xs, ys, sizes, means, errors = [], [], [], [], []
        for j, value in enumerate(categories):
            here = nm[values == value]
            shown = here[::stride]
            xs.append(j + strip + rng.uniform(-0.15 * width, 0.15 * width, shown.size))
            ys.append(shown)
            sizes.append(np.full(shown.size, 5.0 if here.size >= 30 else 18.0))
            means.append(float(here.mean()))
            errors.append(1.96 * float(here.std(ddof=1)) / math.sqrt(here.size) if here.size > 1 else 0.0)
        counts = np.concatenate(sizes)
        ax.scatter(np.concatenate(xs), np.concatenate(ys), s=counts,
                   alpha=0.3, color=colour, linewidths=0, label=f"{label}: each row", zorder=2)
        few = counts > 5.0  # the points of values with few rows, drawn again darker
        if few.any():
            ax.scatter(np.concatenate(xs)[few], np.concatenate(ys)[few], s=18.0, alpha=0.9, color=colour,
                       linewidths=0, zorder=2)
        ax.errorbar(np.arange(categories.size) + mean_at, means, yerr=errors, fmt="D", ms=7, color=colour,
                    mec="black", capsize=4, lw=1.5, label=f"{label}: mean ± 95 %", zorder=3)
    ax.set_xticks(range(categories.size), [_category_label(variable, v) for v in categories])
    ax.set_xlim(-0.6, categories.size - 0.4)


def _step_label(step: Candidate) -> str:
    terms = ", ".join(t.name for t in step.add) or ", ".join(f"{MINUS}{t.name}" for t in step.remove)
    return f"+ {EFFECT_WORDS.get(step.effect, step.effect)}" + (f"\n{terms}" if terms else "")


def figure_gap(result: DiscoveryResult) -> Any:
    """The RMS on held-out blocks and on all rows: the given model refitted, then after each step."""
    plt = pyplot()
    with plt.rc_context(STYLE):
        labels = ["given model\n(refitted)"] + [_step_label(s) for s in result.steps]
        held = [result.baseline["holdout_rms_um"]] + [s.holdout_rms_after_um for s in result.steps]
        train = [result.baseline["refit_rms_um"]] + [s.rms_after_um for s in result.steps]
        fig, ax = plt.subplots(figsize=(max(6.0, 2.2 * len(labels)), 4.5))
        pos = np.arange(len(labels))
        bars = ax.bar(pos - 0.2, np.array(held) * 1000, 0.4, color=AFTER_COLOR, label="held-out blocks")
        ax.bar_label(bars, fmt="%.1f", padding=2)
        bars = ax.bar(pos + 0.2, np.array(train) * 1000, 0.4, color="0.6", label="all rows (training)")
        ax.bar_label(bars, fmt="%.1f", padding=2)
        ax.set_xticks(pos, labels)
        ax.set_ylabel("RMS of the residual (nm)")
        ax.set_title("The gap, step by step" if result.found else "The gap: nothing named, the model stands")
        ax.margins(y=0.15)
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.22), ncol=2, framealpha=0.85)  # off the bars
        fig.tight_layout()
        return fig


def _step_variable(step: Candidate) -> str:
    if step.effect in ("thermal_curvature", "thermal_lag"):  # the bending and a lag show against the temperature
        return str(step.params["channel"])
    if step.effect == "temperature_rate":
        return f"rate({step.params['channel']})"
    return EFFECT_VARIABLE.get(step.effect, "t")


def figure_variables(result: DiscoveryResult, limit: int = 4) -> list[str]:
    """Variables to plot: those the steps point at, then the most significant disagreements."""
    names = [_step_variable(s) for s in result.steps] + [d.variable for d in result.disagreements if d.significant]
    return [n for n in dict.fromkeys([*names, "t"]) if n in result.variables][:limit]


# ----- report.md ---------------------------------------------------------------------------------------
def _fmt(v: float | None, scale: float = 1.0, digits: str = ".1f") -> str:
    return "–" if v is None or not math.isfinite(v) else format(v * scale, digits)


def _minutes(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


def format_params(c: Candidate) -> str:
    """A candidate's parameters as a person reads them (never a raw dict)."""
    p = c.params
    parts: list[str] = []
    if c.effect in ("thermal_lag", "temperature_rate"):
        parts.append(f"channel {p['channel']}, time constant τ = {_minutes(float(p['tau_s']))}")
        if "tau_behind_fastest_s" in p:
            parts.append(f"about {_minutes(float(p['tau_behind_fastest_s']))} behind the fastest channel")
    elif c.effect == "creep":
        parts.append(f"time constant τ = {_minutes(float(p['tau_s']))}")
    elif c.effect == "hysteresis":
        parts.append(f"a move counts when larger than {p.get('deadband_um', 0):g} µm")
    elif c.effect == "geometric_order":
        parts.append(f"term {p.get('term')}, order {p.get('order')}")
    elif c.effect == "unmonitored_drift":
        rate = p.get("rate_um_per_h")
        parts.append(f"{rate:+.3f} µm/h" if rate is not None else "a straight line in time")
        parts.append("fitted as a nuisance, not applied online")
    elif c.effect in ("position_thermal_coupling", "missing_channel"):
        parts.append(f"channel {p['channel']}")
    elif c.effect == "thermal_curvature":
        parts.append(f"channel {p['channel']}, about {p['centre_c']:g} °C")
    elif c.effect == "sensor_exclusion":
        parts.append(f"leave {p['channel']} out")
    elif c.effect == "crosstalk":
        parts.append(f"from axis {p['axis']}")
    elif c.effect == "coupled_bending":
        parts.append(f"term {p['axes']}")
    if p.get("deferred_to"):
        parts.append(f"deferred to the same effect on {p['deferred_to']}, the fastest channel (rule 5)")
    if p.get("alike"):
        parts.append(f"looks like {EFFECT_WORDS.get(p['alike'], p['alike'])} in this run "
                     f"(correlation {p['alike_correlation']:.2f}; rule 8)")
    if p.get("readmitted"):
        parts.append(f"re-admits {', '.join(p['readmitted'])} (rule 7)")
    if p.get("coef"):
        parts.append("fitted coefficients (µm of command per unit of the term): "
                     + ", ".join(f"{name} = {value:.4g}" for name, value in p["coef"].items()))
    return "; ".join(parts)


def _change(gain: float) -> str:
    """A held-out gain in words: a cut, or a rise when the candidate predicts held-out blocks worse."""
    if gain >= 0:
        return f"cuts the held-out RMS by {100 * gain:.1f} %"
    return f"raises the held-out RMS by {-100 * gain:.1f} %"


def verdict(c: Candidate, chosen: bool, settings: Settings) -> str:
    """Why a candidate was or was not named, in words and in the terms of the rules below.

    Every p cited is the candidate's :attr:`Candidate.bar_p`, the one the report's p column shows.
    """
    if chosen:
        return "**named**"
    if c.params.get("deferred_to"):
        return f"deferred to {c.params['deferred_to']} (rule 5)"
    if c.clears:
        return "clears the bar; another ranked first (rule 3)"
    why = []
    if c.remove:
        if not c.p_iid < settings.exclusion_p_iid:
            why.append(f"kept without conviction: the stepwise's own test of {c.params['channel']} (rows taken as "
                       f"independent) gives p {c.bar_p:.2g}, not below {settings.exclusion_p_iid:g}, so the model "
                       "hardly leans on it; rule 6 removes only a channel the fit leans on hard yet predicts new "
                       "data worse with (the paper's hot plate), and a weakly kept one is not that signature")
        if c.holdout_gain < settings.exclusion_gain:
            why.append(f"leaving it out {_change(c.holdout_gain)} (a cut of {100 * settings.exclusion_gain:.0f} % is "
                       "needed)")
        if c.blocks_improved < settings.exclusion_blocks:
            why.append(f"leaving it out predicts {100 * c.blocks_improved:.0f} % of the held-out blocks better, fewer "
                       f"than {100 * settings.exclusion_blocks:.0f} %")
        return "; ".join(why) + " (rule 6)" if why else "not named"
    needed = settings.trend_gain if c.trend_like else settings.min_holdout_gain
    if not c.p_value < settings.p_max:
        why.append(f"p {c.bar_p:.2g} ≥ {settings.p_max:g}: the improvement could be chance (rule 2)")
    if c.holdout_gain < needed:
        why.append(f"it {_change(c.holdout_gain)} (a cut of {100 * needed:.0f} % is needed"
                   + (": trend-like, rule 4)" if c.trend_like else ", rule 2)"))
    if c.blocks_improved < 0.5:
        why.append(f"improves only {100 * c.blocks_improved:.0f} % of the blocks (rule 2)")
    if not c.pinned:
        factor = f"{settings.pin_factor:g}"
        why.append(f"its time constant is not pinned: the fit at {factor}× or 1/{factor}× τ is not worse beyond "
                   "chance (rule 11)")
    if c.params.get("not_told_from"):
        why.append("the run cannot tell this drift from a slow thermal lag (rule 12)")
    return "; ".join(why) or "not named"


def rules(settings: Settings, result: DiscoveryResult) -> list[str]:
    """Every rule the method applies, numbered, with this run's values (the report's candidates cite them)."""
    s = settings
    return [
        "1. **Residual structure.** r = q − q_pred (the command the cell needed minus the model's). Against "
        "each variable the residuals are binned (at most "
        f"{s.bins} bins, one per value for a variable with few values) and a one-way ANOVA F-test is run with "
        "the sample size deflated for lag-1 autocorrelation ρ (n(1 − ρ)/(1 + ρ) effective rows). A variable "
        f"is flagged when that p, times the number of variables (Bonferroni), is below {s.p_max:g} and the "
        "bins explain at least 5 % of the residual variance (η²).",
        "2. **The bar.** A candidate is named only if its partial F-test p (deflated as in rule 1; one extra "
        "degree of freedom per searched time constant; Bonferroni over the channels tried) is below "
        f"{s.p_max:g}, it cuts the RMS on held-out blocks (whole cycles, each predicted by a fit on the "
        f"others) by at least {100 * s.min_holdout_gain:.0f} %, and it improves at least half of the blocks.",
        "3. **Ranking.** Of the candidates that clear the bar, the one with the lowest held-out RMS is named, "
        f"each searched time constant charged {100 * s.search_penalty:.0f} % of it (a simpler term wins a tie). "
        f"Its terms are added, the model refitted, and the search repeats (at most {s.max_steps} steps).",
        "4. **Trends.** A drift in time, or a lag as long as the run, must cut the held-out RMS by "
        f"{100 * s.trend_gain:.0f} %: over a few hours the interferometer's slow wander can look like a trend. "
        "An unmonitored drift is named but never applied online (the model would be wrong within days): "
        "it is fitted as a nuisance so the other coefficients stay clean, and left out of the model.",
        "5. **Fastest channel.** Lags of different channels that explain nearly as much (held-out RMS within "
        f"{100 * s.prefer_fastest_within:.0f} %) are deferred to the fastest channel (the one closest to the "
        "air): a lag behind a slow channel adds two delays only approximately.",
        "6. **Sensor exclusion** (the paper's hot plate). A channel is left out when the stepwise keeps it with "
        f"conviction (p < {s.exclusion_p_iid:g} taking rows as independent) yet leaving it out predicts at least "
        f"{100 * s.exclusion_blocks:.0f} % of the held-out blocks better and cuts their RMS by "
        f"{100 * s.exclusion_gain:.0f} %.",
        "7. **Re-admission.** A large hidden effect can make the paper's stepwise leave out a channel or power "
        "the cell needs; once the effect is named, the model's own selection is rerun and what it re-admits "
        "joins the step if it also lowers the held-out RMS.",
        "8. **Look-alikes.** A thermal lag whose column, beyond the model's terms, correlates with a line in "
        f"time by at least {s.twin_correlation:g} is flagged: in a run where the room falls and rises once the "
        "two look the same; a longer run tells them apart.",
        "9. **What a run can show.** Hysteresis is only tested when at least "
        f"{100 * s.min_direction_share:.0f} % of the rows are approached moving the other way: in forward-only "
        "sweeps the only move down is the return to 0 µm. Creep needs steps."
        + (" In this run: " + "; ".join(b["effect"] for b in result.untestable) + " could not be tested."
           if result.untestable else ""),
        f"10. **Time constants** are searched on a log grid ({s.grid_points} points: lags "
        f"{_minutes(s.lag_tau_s[0])}–{_minutes(s.lag_tau_s[1])}, creep {s.creep_tau_s[0]:g}–{s.creep_tau_s[1]:g} s) "
        "then refined by bounded minimisation of the training error; a lag shorter than "
        f"{_minutes(s.rate_tau_max_s)} acts through the rate of change and is named a temperature rate.",
        f"11. **Pinned time constants.** A searched time constant must be pinned by the run: the fit at "
        f"{s.pin_factor:g}× τ and at τ / {s.pin_factor:g} must both be worse than at τ beyond chance "
        f"(likelihood ratio, χ²₁ 95 % = {s.pin_chi2:g}, on the autocorrelation-deflated rows); otherwise applying τ "
        "can make a fresh run worse.",
        f"12. **Drift or lag.** An unmonitored drift is named only when its held-out RMS is below "
        f"{100 * s.drift_vs_lag:.0f} % of the best thermal lag's: otherwise the run cannot tell a source no sensor "
        "sees from a slow thermal one.",
        "13. **What a fresh run should show.** Held-out blocks of the run an effect was chosen on flatter it (they "
        "share its room history and slow interferometer wander), so each step also gives the RMS expected on a fresh "
        "run of the same kind: the in-sample error plus what fitting hides (measured as held-out minus in-sample "
        "error on the model with the effect, charged to the model without it in proportion to its parameters). "
        "With `--fresh` the gain is also measured on a run discovery never saw. A named time constant comes with "
        "the range the run supports: the τ whose held-out blocks are not worse than at the τ named (one-sided "
        f"paired t-test over the blocks, {100 * s.tau_range_confidence:.0f} %); an edge at the end of the searched "
        "range means the run cannot pin τ on that side. Rule 11 tests τ on the training fit; the range, on blocks "
        "the fit did not see, is the stricter: where they disagree, the range says what the run can tell.",
    ]


def markdown(result: DiscoveryResult, figures: Sequence[str], model_out: str | None) -> str:
    b, f, s = result.baseline, result.final, result.settings
    lines = ["# Discovery report", "", "## Finding", "", result.summary, ""]
    lines += [
        "## Models", "",
        f"- given model `{b['model']}`: {', '.join(b['terms'])}; RMS {_fmt(b['rms_um'], 1000)} nm, "
        f"held-out {_fmt(b['holdout_rms_um'], 1000)} nm over {b['holdout_blocks']} time blocks, "
        f"Durbin-Watson {b['durbin_watson']:.2f}, lag-1 autocorrelation {b['lag1_autocorr']:.2f}",
    ]
    if result.found:
        lines.append(f"- extended model `{f['model']}`" + (f" → `{model_out}`" if model_out else "")
                     + f": {', '.join(f['terms'])}; held-out {_fmt(f['holdout_rms_um'], 1000)} nm")
    else:
        lines.append("- nothing found; no model written: no effect clears the bar (rule 2), so the given model "
                     "stands (a copy under a new id would be the same model)")
    if "fresh_gain_expected" in f and len(result.steps) > 1:  # one step: the finding says its expectation
        before, after = f["fresh_rms_expected_um"]
        lines.append(f"- expected on a fresh run of the same kind (rule 13), from the given model as it is: "
                     f"{_fmt(before, 1000)} → "
                     f"{_fmt(after, 1000)} nm, RMS × {f['fresh_gain_expected']:.2f}")
    if "fresh_gain_measured" in f:
        before, after = f["fresh_rms_measured_um"]
        lines.append(f"- measured on the fresh run given (`--fresh`): {_fmt(before, 1000)} → {_fmt(after, 1000)} nm, "
                     f"RMS × {f['fresh_gain_measured']:.2f}")
    if f.get("not_applied_online"):
        lines.append(f"- named but not applied online (rule 4): {', '.join(f['not_applied_online'])}")
    if result.untestable:
        lines += ["", "## What this run cannot show", ""]
        for blind in result.untestable:
            lines.append(f"- **{blind['effect']}**: {blind['reason']}. To test it, {blind['hint']}.")
    tested = max(len(result.variables), 1)
    lines += ["", "## Where the residuals disagree (rule 1)", "",
              f"F and η² are on the rows as given; p deflates the rows for the residuals' lag-1 autocorrelation "
              f"({b['lag1_autocorr']:.2f}) and is multiplied by the {tested} variables tested (Bonferroni): a "
              f"variable is flagged when that p is below {s.p_max:g} and η² ≥ 0.05, so a large F on strongly "
              "autocorrelated residuals (a slow drift: few independent stretches) can stay unflagged.", "",
              "| variable | F | p (deflated, × variables) | η² | spread of the bin means (nm) | flagged |",
              "|---|---|---|---|---|---|"]
    for d in result.disagreements:
        lines.append(f"| {d.description} | {d.f_stat:.3g} | {min(d.p_value * tested, 1.0):.2g} | {d.eta2:.3f} | "
                     f"{d.spread_um * 1000:.1f} | {'yes' if d.significant else 'no'} |")
    for i, rnd in enumerate(result.rounds, 1):
        lines += ["", f"## Round {i}: candidates", "",
                  "Held-out RMS before and after adding the candidate; gain = the share of the held-out RMS it "
                  "removes; blocks = the share of held-out blocks it predicts better.", "",
                  "p: the test the verdict cites (rule 2's partial F-test; for leaving a sensor out, rule 6's "
                  "stepwise test taking rows as independent).", "",
                  "| effect | terms | parameters | p | held-out before (nm) | after (nm) | gain | blocks | verdict |",
                  "|---|---|---|---|---|---|---|---|---|"]
        for c in sorted(rnd.candidates, key=lambda c: c.holdout_rms_after_um):
            terms = ", ".join([t.name for t in c.add] + [f"{MINUS}{t.name}" for t in c.remove]
                              + [f"{n} (nuisance)" for n in c.nuisance]) or "–"
            lines.append(
                f"| {c.effect} | {terms} | {format_params(c)} | "
                f"{c.bar_p:.2g}{' (rows independent)' if c.remove else ''} | "
                f"{_fmt(c.holdout_rms_before_um, 1000)} | {_fmt(c.holdout_rms_after_um, 1000)} | "
                f"{100 * c.holdout_gain:.1f} % | {_fmt(c.blocks_improved, 100, '.0f')} % | "
                f"{verdict(c, c is rnd.chosen, s)} |"
            )
    lines += ["", "## Figures", "", "Each figure is also written as SVG beside the PNG.", ""]
    lines += [f"![{Path(name).stem}]({name})" for name in figures]
    lines += ["", "## Rules applied", "", *rules(s, result)]
    lines += ["", f"The full method: `{METHOD_DOC}` in nanodrift's source.", ""]
    return "\n".join(lines)


def write_report(result: DiscoveryResult, directory: str | Path, model_out: str | None = None, *,
                 provenance: str = "") -> list[Path]:
    """Write the figures (PNG + SVG) and ``report.md`` into ``directory``; returns the files written.

    ``provenance``: each figure's footer (the model and the data files it was run on)."""
    plt = pyplot()
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    drawings: list[tuple[str, Callable[[], Any]]] = [
        (f"residuals_vs_{v.replace('(', '_').replace(')', '')}", partial(figure_residuals, result, v))
        for v in figure_variables(result)]
    drawings.append(("gap", partial(figure_gap, result)))
    for stem, draw in drawings:
        fig = with_footer(draw(), provenance)
        try:
            written += save_figure(fig, out / stem)
        finally:
            plt.close(fig)
    atomic_write_text(out / "report.md", markdown(result, [f"{stem}.png" for stem, _ in drawings], model_out))
    written.append(out / "report.md")
    return written
