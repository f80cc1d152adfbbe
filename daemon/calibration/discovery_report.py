"""The discovery report: PNG figures (matplotlib, Agg) and a markdown summary, written atomically.

Figures: the residuals before and after against each variable that located the gap (scatter plus
binned means), the residuals against time, and the held-out RMS shrinking step by step.
"""

from __future__ import annotations

import io
import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from daemon.atomic import atomic_write_bytes, atomic_write_text
from daemon.calibration.discovery import Candidate, DiscoveryResult

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


def _save(fig: plt.Figure, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(path, buf.getvalue())


def _binned(values: np.ndarray, r: np.ndarray, bins: int = 12) -> tuple[np.ndarray, np.ndarray]:
    uniq = np.unique(values)
    if uniq.size <= bins:
        return uniq, np.array([r[values == u].mean() for u in uniq])
    edges = np.unique(np.quantile(values, np.linspace(0, 1, bins + 1)))
    idx = np.clip(np.searchsorted(edges, values, side="right") - 1, 0, edges.size - 2)
    centres = np.array([values[idx == i].mean() for i in range(edges.size - 1) if np.any(idx == i)])
    means = np.array([r[idx == i].mean() for i in range(edges.size - 1) if np.any(idx == i)])
    return centres, means


def _step_variable(step: Candidate) -> str:
    if step.effect in ("thermal_lag", "temperature_rate"):
        channel = step.params["channel"]
        return f"rate({channel})" if step.effect == "temperature_rate" else channel
    return EFFECT_VARIABLE.get(step.effect, "t")


def figure_variables(result: DiscoveryResult, limit: int = 4) -> list[str]:
    """Variables to plot: those the steps point at, then the most significant disagreements."""
    names: list[str] = []
    for step in result.steps:
        names.append(_step_variable(step))
    names += [d.variable for d in result.disagreements if d.significant]
    names.append("t")
    seen: list[str] = []
    for n in names:
        if n in result.variables and n not in seen:
            seen.append(n)
    return seen[:limit]


def plot_residuals(result: DiscoveryResult, variable: str, path: Path) -> None:
    desc, values = result.variables[variable]
    n = values.size
    stride = max(1, n // 20000)  # a scatter of 1e6 points says nothing more than 2e4
    fig, ax = plt.subplots(figsize=(7, 4))
    for r, label, colour in ((result.residual_before, "given model", "tab:red"),
                             (result.residual_after, "extended model", "tab:blue")):
        nm = r * 1000.0
        ax.scatter(values[::stride], nm[::stride], s=4, alpha=0.25, color=colour)
        centres, means = _binned(values, nm)
        ax.plot(centres, means, "o-", color=colour, label=f"{label} (binned mean)")
    ax.axhline(0.0, color="k", lw=0.5)
    ax.set_xlabel(desc)
    ax.set_ylabel("residual q_measured - q_pred (nm)")
    ax.set_title(f"Residuals against {variable}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def plot_gap(result: DiscoveryResult, path: Path) -> None:
    labels = ["given model\n(refit)"] + [f"+ {s.effect}" for s in result.steps]
    held = [result.baseline["holdout_rms_um"]] + [s.holdout_rms_after_um for s in result.steps]
    train = [result.baseline["refit_rms_um"]] + [s.rms_after_um for s in result.steps]
    fig, ax = plt.subplots(figsize=(max(5, 1.8 * len(labels)), 4))
    pos = np.arange(len(labels))
    ax.bar(pos - 0.2, np.array(held) * 1000, 0.4, label="held-out blocks")
    ax.bar(pos + 0.2, np.array(train) * 1000, 0.4, label="training (all rows)")
    ax.set_xticks(pos, labels, fontsize=8)
    ax.set_ylabel("RMS (nm)")
    ax.set_title("The gap, step by step")
    ax.legend(fontsize=8)
    fig.tight_layout()
    _save(fig, path)


def _fmt(v: float | None, scale: float = 1.0, digits: str = ".1f") -> str:
    return "-" if v is None or not math.isfinite(v) else format(v * scale, digits)


def markdown(result: DiscoveryResult, figures: list[str], model_out: str | None) -> str:
    b, f = result.baseline, result.final
    lines = ["# Discovery report", "", "## Finding", "", result.summary, ""]
    lines += [
        "## Models", "",
        f"- given model `{b['model']}`: {', '.join(b['terms'])}; RMS {_fmt(b['rms_um'], 1000)} nm, "
        f"held-out {_fmt(b['holdout_rms_um'], 1000)} nm over {b['holdout_blocks']} time blocks, "
        f"Durbin-Watson {b['durbin_watson']:.2f}, lag-1 autocorrelation {b['lag1_autocorr']:.2f}",
        f"- extended model `{f['model']}`" + (f" -> `{model_out}`" if model_out else "")
        + f": {', '.join(f['terms'])}; held-out {_fmt(f['holdout_rms_um'], 1000)} nm",
    ]
    if f["not_applied_online"]:
        lines.append(f"- named but not applied online: {', '.join(f['not_applied_online'])}")
    lines += ["", "## Where the residuals disagree", "",
              "| variable | F | p (AR(1)-deflated) | eta^2 | bin spread (nm) | significant |",
              "|---|---|---|---|---|---|"]
    for d in result.disagreements:
        lines.append(f"| {d.description} | {d.f_stat:.3g} | {d.p_value:.2g} | {d.eta2:.3f} | "
                     f"{d.spread_um * 1000:.1f} | {'yes' if d.significant else 'no'} |")
    for i, rnd in enumerate(result.rounds, 1):
        lines += ["", f"## Round {i}: candidates", "",
                  "| effect | terms | params | p | held-out before (nm) | after (nm) | gain | clears |",
                  "|---|---|---|---|---|---|---|---|"]
        for c in sorted(rnd.candidates, key=lambda c: c.holdout_rms_after_um):
            mark = " (named)" if c is rnd.chosen else ""
            lines.append(
                f"| {c.effect}{mark} | {c.label.split('[', 1)[1].rstrip(']')} | {c.params} | {c.p_value:.2g} | "
                f"{_fmt(c.holdout_rms_before_um, 1000)} | {_fmt(c.holdout_rms_after_um, 1000)} | "
                f"{100 * c.holdout_gain:.1f} % | {'yes' if c.clears else 'no'} |"
            )
    lines += ["", "## Figures", ""] + [f"![{name}]({name})" for name in figures]
    lines += ["", "## Method", "",
              "Residuals r = q_measured - q_pred. Each catalogue effect's term(s) are added to the refitted "
              "model (time constants by a log grid then bounded minimisation of the training SSE); a "
              "candidate is named when its partial F-test p (AR(1)-deflated, one extra degree of freedom "
              "per searched parameter, Bonferroni over the channels tried) is below "
              f"{result.model.selection['discovery']['p_max']} and it cuts the RMS on held-out time blocks "
              f"by at least {100 * result.model.selection['discovery']['min_holdout_gain']:.0f} %.", ""]
    return "\n".join(lines)


def write_report(result: DiscoveryResult, directory: str | Path, model_out: str | None = None) -> list[Path]:
    """Write the figures and ``report.md`` into ``directory``; returns the files written."""
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    figures: list[str] = []
    for variable in figure_variables(result):
        name = f"residuals_vs_{variable.replace('(', '_').replace(')', '')}.png"
        plot_residuals(result, variable, out / name)
        figures.append(name)
    plot_gap(result, out / "gap.png")
    figures.append("gap.png")
    written += [out / name for name in figures]
    atomic_write_text(out / "report.md", markdown(result, figures, model_out))
    written.append(out / "report.md")
    return written
