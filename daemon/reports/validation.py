"""Table I as text or JSON, and a report directory: figures after the paper's Fig. 9 and 11, raw data.

``--report DIR`` writes:
- ``table1.txt`` and ``validation.json``: what ``validate`` prints;
- ``fig9_drift_at_zero.png`` / ``.svg``: per test, the drift at the zero position over time (the
  uncompensated position, measured or computed), the compensation the model applied (x' - q'), a
  ±2σ band of the compensated position's expected error, and the temperatures, each channel's
  training range shaded (outside it the model extrapolates);
- ``fig11_accuracy.png`` / ``.svg``: accuracy and repeatability with and without compensation per
  test (bars) and accuracy per point, on a linear axis unless the values span more than a decade;
PNGs are 150 dpi; the SVGs keep text as text. Every figure carries a footer saying where it came
from (:func:`laid_out`: the model id, its data file, the cell and seed).
- ``validation_raw.csv``: one row per step: test, cycle, target, command, measured position, the
  computed uncompensated position, validity and the temperatures; on a simulated cell a column
  ``x_true_um``, the position the stage truly attained (hardware has no such column); last,
  ``q_sigma_um``, the σ of the step's command (nan without the model).

On a simulated cell every figure is also given against the true position (``TestResult.x_true_um``):
the interferometer's view includes its noise and slow wander, the truth does not.

A cell of several axes (:func:`cell_table`, :func:`write_cell_report`): Table I per axis and the ISO
9283 pose accuracy AP / repeatability RP in 2-D/3-D, each test scored against the true position and
against the interferometers; ``--report DIR`` writes ``table1_axes.txt``, ``validation.json`` and
``fig_cell_accuracy.png``/``.svg`` (the attained points around each target in the plane of the first
two axes, with and without the model, and the per-axis and 2-D/3-D accuracy bars).
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from nanodrift.atomic import atomic_write_text, atomic_writer
from nanodrift.calibration.iso9283 import TestResult

if TYPE_CHECKING:
    from matplotlib.typing import RcKeyType

    from nanodrift.model.model import Training

PAPER_TABLE1: dict[str, tuple[float, float | None]] = {
    "test1": (546.0, None),
    "test2": (378.0, 35.0),
    "test3": (478.0, 62.0),
    "test4": (492.0, 57.0),
    "test5": (2225.0, 646.0),
}


EMPTY = "—"  # a cell with no value (test 1 has no "with compensation")


def _nm(v: float | None) -> str:
    return EMPTY if v is None or not math.isfinite(v) else f"{v:.0f} nm"


def ratio_text(ratio: float | None) -> str:
    """An improvement factor as people write it: ``4.0×``; ``—`` when there is none."""
    return EMPTY if ratio is None or not math.isfinite(ratio) else f"{ratio:.1f}×"


#: Table I's columns, against the interferometer (:func:`table1`) and against the truth (:func:`truth_table`)
TABLE1_HEAD = f"{'Test':<10}{'Without comp.':>15}{'With comp.':>12}{'Improvement':>13}"


def _table1_row(r: TestResult, without_nm: float, with_nm: float, ratio: float | None) -> str:
    star = "*" if r.compensated else " "  # "without" computed from the compensated run, not measured
    return f"{r.name:<10}{_nm(without_nm) + star:>15}{_nm(with_nm):>12}{ratio_text(ratio):>13}"


def table1(results: Sequence[TestResult], paper: Mapping[str, tuple[float, float | None]] | None = None) -> str:
    """Table I: accuracy (mean over the test points) without and with compensation."""
    head = TABLE1_HEAD
    if paper:
        head += f"   | paper: {'without':>8}{'with':>8}{'ratio':>7}"
    lines = ["TABLE I  accuracy with and without compensation (mean of |mean attained - target| over the points)",
             head, "-" * len(head)]
    for r in results:
        line = _table1_row(r, r.accuracy_without_nm, r.accuracy_nm, r.improvement)
        if paper and r.name in paper:
            p0, p1 = paper[r.name]
            line += f"   |        {p0:>6.0f}{(f'{p1:.0f}' if p1 else EMPTY):>8}{ratio_text(p0 / p1 if p1 else None):>7}"
        if r.invalid_steps:
            line += f"  ({r.invalid_steps} invalid steps)"
        if r.extrapolating_steps:
            line += f"  [{r.extrapolating_steps} steps extrapolating]"
        lines.append(line)
    lines.append("* from calculation, not measurement: x_without = x_measured - (q' - x') over the same period.")
    return "\n".join(lines)


def truth_table(results: Sequence[TestResult]) -> str:
    """Table I again, scored against the true attained position (a simulated cell only; "" without truth)."""
    known = [r for r in results if r.has_truth]
    if not known:
        return ""
    lines = ["Against the TRUE position (simulated cell only): Table I without the interferometer's noise and wander",
             TABLE1_HEAD, "-" * len(TABLE1_HEAD)]
    for r in known:
        without, with_ = r.true_accuracy_nm()
        lines.append(_table1_row(r, without, with_, without / with_ if r.compensated else None))
    return "\n".join(lines)


#: the share of errors within ±2 σ a calibrated q_sigma keeps (95 % for a normal error; 90-98 % allowed)
COVERAGE_GOAL = (0.90, 0.98)


def coverage_lines(result: TestResult) -> tuple[list[str], str | None]:
    """What ``validate`` says about q_sigma (and the truth, on a simulated cell), and a warning if miscalibrated.

    The errors judged are the true ones when the cell knows them, else the interferometer's (which
    carry its wander too, so they are judged against sqrt(q_sigma² + wander²)). Under 90 % within
    ±2σ: q_sigma understates the error. Over 98 %: it overstates it only if the errors are also
    small against σ (RMS under half the median σ); a run's steps share one offset (the calibration's
    coefficients are off the same way for all of them), so a run whose offset is within 2σ has
    every step inside, which alone says little. With ``--adapt`` the σ judged is the corrected
    command's (``q_sigma_adapted``, what the tracker leaves), not the model's.
    """
    sigmas = result.command_sigma_um
    if not (result.compensated and sigmas):
        return [], None
    name = "q_sigma_adapted" if sigmas is result.q_sigma_adapted_um else "q_sigma"
    median_nm = float(np.median(sigmas)) * 1e3
    measured = result.coverage()
    wander = (f"; the interferometer's wander, {result.measurement_sigma_um * 1e3:.0f} nm, added in quadrature"
              if result.measurement_sigma_um > 0 else "")
    lines = [f"uncertainty: {measured * 100:.0f} % of the steps' measured errors (position - target) lie within "
             f"±2 {name} (median {name} {median_nm:.0f} nm{wander}); a calibrated {name} keeps 90-98 %"]
    valid = [s for s in result.steps if s.valid]
    a = result.axis
    errors = [(s.true_um if result.has_truth else s.positions_um)[a] - s.step.target(a) for s in valid]
    if result.has_truth:
        judged, what = result.coverage_true(), "true errors"
        lines.append(f"against the true position (simulated cell): accuracy {_nm(result.accuracy_true_nm)} with "
                     f"compensation (interferometer: {_nm(result.accuracy_nm)}); {judged * 100:.0f} % of the true "
                     f"errors (true position - target) within ±2 {name}")
    else:
        judged, what = measured, "measured errors"
    lo, hi = COVERAGE_GOAL
    rms_nm = float(np.sqrt(np.mean(np.square(errors)))) * 1e3 if errors else math.nan
    if not math.isfinite(judged) or lo <= judged <= hi or (judged > hi and rms_nm >= 0.5 * median_nm):
        return lines, None
    side = ("understates the error" if judged < lo
            else f"overstates the error (RMS error {rms_nm:.0f} nm against a median {name} of {median_nm:.0f} nm)")
    return lines, (f"{name} is not calibrated on this run: {judged * 100:.0f} % of the {what} within ±2 {name} "
                   f"(expected {lo * 100:.0f}-{hi * 100:.0f} % over {len(valid)} steps); it {side}")


def step_sigmas_um(result: TestResult) -> list[float]:
    """Per step, the standard uncertainty of its command (the tracker's with ``--adapt``, else the model's
    q_sigma); nan for a test without the model or a model without σ."""
    sigmas = list(result.command_sigma_um) if result.compensated else []
    return sigmas if len(sigmas) == len(result.steps) else [math.nan] * len(result.steps)


def raw_csv(results: Sequence[TestResult]) -> str:
    """One row per step; the last column ``q_sigma_um`` is the command's σ (:func:`step_sigmas_um`)."""
    channels = list(dict.fromkeys(c for r in results for s in r.steps for c in s.temperatures))
    truth = any(r.has_truth for r in results)  # a simulated cell: the column hardware cannot have
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["test", "t_s", "cycle", "target_um", "q_um", "x_measured_um", "x_without_um", "valid",
                     *channels, *(["x_true_um"] if truth else []), "q_sigma_um"])
    for r in results:
        trues = r.x_true_um if r.has_truth else [math.nan] * len(r.steps)
        sigmas = step_sigmas_um(r)
        for s, x_true, sigma in zip(r.steps, trues, sigmas, strict=True):
            a = r.axis
            writer.writerow([r.name, repr(s.t_s), s.step.cycle, repr(s.step.target(a)), repr(s.q_um[a]),
                             repr(s.positions_um[a]), repr(s.x_without_um(a)), int(s.valid),
                             *(repr(s.temperatures.get(c, math.nan)) for c in channels),
                             *([repr(x_true)] if truth else []), repr(sigma)])
    return out.getvalue()


#: matplotlib settings for figures pasted into a lab notebook: readable at 100 %, text kept as text in SVG
STYLE: dict[RcKeyType, Any] = {
    "font.size": 10,
    "axes.titlesize": 11,
    "axes.labelsize": 10,
    "legend.fontsize": 9,
    "xtick.labelsize": 9,
    "ytick.labelsize": 9,
    "svg.fonttype": "none",
}
PNG_DPI = 150


def pyplot() -> Any:
    """matplotlib's pyplot on the Agg backend, imported only when a figure is drawn (half a second): what imports
    the reports for their words and tables does not pay for it."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt
WITHOUT_COLOR, WITH_COLOR = "#4c72b0", "#dd8452"


def write_report(results: Sequence[TestResult], directory: str | Path, text: str, doc: Mapping[str, Any], *,
                 provenance: str = "", training: Training | None = None) -> list[Path]:
    """Write the report files (each atomically); returns their paths.

    ``provenance``: the figures' footer (:func:`provenance_text`); ``training``: the model's training
    ranges, shaded on the figures."""
    out = Path(directory)
    written = _write_texts(out, {"table1.txt": text + "\n", "validation.json": json.dumps(doc, indent=2) + "\n",
                                 "validation_raw.csv": raw_csv(results)})
    return written + write_figures(results, out, provenance=provenance, training=training)


def _write_texts(out: Path, texts: Mapping[str, str]) -> list[Path]:
    """Each file of ``texts`` (name -> content) into ``out``, atomically; their paths."""
    out.mkdir(parents=True, exist_ok=True)
    for name, text in texts.items():
        atomic_write_text(out / name, text)
    return [out / name for name in texts]


def write_figures(results: Sequence[TestResult], directory: str | Path, *, provenance: str = "",
                  training: Training | None = None) -> list[Path]:
    """fig9 and fig11 as PNG and SVG into ``directory`` (each atomically); returns their paths."""
    plt = pyplot()
    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written: list[Path] = []
    with plt.rc_context(STYLE):
        for stem, draw in (("fig9_drift_at_zero", figure_drift), ("fig11_accuracy", figure_accuracy)):
            fig = draw(results, provenance=provenance, training=training)
            written.extend(save_figure(fig, out / stem))
            plt.close(fig)
    return written


def provenance_text(model_id: str, model_data: str | None, cell: str) -> str:
    """The figures' footer: ``model m-… (fitted on calibration.csv) · simulated cell, test2, --seed 3``."""
    fitted = f" (fitted on {model_data})" if model_data else ""
    return f"model {model_id}{fitted} · {cell}"


#: the footer's height (inches) and the offset (points) of a note drawn above it
FOOTER_IN, FOOTER_PT = 0.22, 15


def with_footer(fig: Any, provenance: str) -> Any:
    """A figure drawn without a footer, given one (:func:`laid_out`); unchanged when ``provenance`` is ""."""
    return laid_out(fig, provenance) if provenance else fig


def laid_out(fig: Any, provenance: str, bottom: float = 0.0) -> Any:
    """``fig`` with a small grey footer at the bottom left saying where it came from (none when ``provenance`` is
    ""), laid out above it and ``bottom`` (a share of the figure's height) more."""
    if provenance:
        fig.text(0.006, 0.006, provenance, ha="left", va="bottom", fontsize=7, color="0.35", gid="provenance")
    fig.tight_layout(rect=(0, (FOOTER_IN / fig.get_figheight() if provenance else 0.0) + bottom, 1, 1))
    return fig


def figure_drift(results: Sequence[TestResult], *, provenance: str = "", training: Training | None = None) -> Any:
    """After the paper's Fig. 9 and 10: per test, the drift at x' = 0 over time, and the temperatures
    with each channel's training range shaded (a test outside it is a model extrapolating)."""
    plt = pyplot()
    with plt.rc_context(STYLE):
        return laid_out(_draw_drift(plt, results, training), provenance)


def _draw_drift(plt: Any, results: Sequence[TestResult], training: Training | None) -> Any:
    fig, axes = plt.subplots(2 * len(results), 1, figsize=(9, 4.2 * len(results) + 0.4), squeeze=False,
                             gridspec_kw={"height_ratios": [3, 1.4] * len(results)})
    for i, r in enumerate(results):
        ax, tax = axes[2 * i, 0], axes[2 * i + 1, 0]
        a = r.axis
        zero = [s for s in r.steps if s.step.target(a) == 0.0 and s.valid]
        hours = [s.t_s / 3600.0 for s in zero]
        ax.axhline(0.0, color="0.6", lw=0.8)
        if r.compensated:
            ax.plot(hours, [1e3 * s.x_without_um(a) for s in zero], "o-", ms=4, color=WITHOUT_COLOR,
                    label="drift without compensation (computed: x − (q′ − x′))")
            ax.plot(hours, [1e3 * (s.step.target(a) - s.q_um[a]) for s in zero], "s--", ms=4, color="0.35",
                    label="compensation applied (x′ − q′)")
            ax.plot(hours, [1e3 * s.positions_um[a] for s in zero], "D-", ms=4, color=WITH_COLOR,
                    label="position with compensation (measured)")
            _sigma_band(ax, r, zero, hours)
        else:
            ax.plot(hours, [1e3 * s.positions_um[a] for s in zero], "o-", ms=4, color=WITHOUT_COLOR,
                    label="drift (measured position, no compensation)")
        if r.has_truth:
            true_zero = [s.true_um[a] for s in zero]
            ax.plot(hours, [1e3 * x for x in true_zero], "-", lw=1.0, color="0.15",
                    label="true position (simulated cell: no interferometer noise or wander)")
        ax.set_title(f"{r.name} ({'with' if r.compensated else 'without'} compensation): position at x′ = 0 µm")
        ax.set_ylabel("drift at x′ = 0 µm (nm)")
        ax.grid(alpha=0.3)
        if zero:
            ax.legend(loc="best", framealpha=0.85)
        valid = [s for s in r.steps if s.valid]
        channels = list(dict.fromkeys(c for s in valid for c in s.temperatures))
        for channel in channels:
            points = [(s.t_s / 3600.0, s.temperatures[channel]) for s in valid if channel in s.temperatures]
            (line,) = tax.plot([t for t, _ in points], [v for _, v in points], lw=1.2, label=channel)
            if training is not None and channel in training.channel_ranges:
                low, high = training.channel_ranges[channel]
                tax.axhspan(low, high, color=line.get_color(), alpha=0.08, lw=0, label=f"{channel} training range",
                            gid=f"training-range-{channel}")
                for edge in (low, high):  # the edges stay readable where several channels' bands overlap
                    tax.axhline(edge, color=line.get_color(), lw=0.8, ls=":")
        tax.set_title(f"{r.name}: temperatures")
        tax.set_ylabel("temperature (°C)")
        tax.yaxis.get_major_formatter().set_useOffset(False)
        tax.grid(alpha=0.3)
        if channels:
            tax.legend(loc="center left", bbox_to_anchor=(1.0, 0.5), ncol=1, frameon=False)
        tax.sharex(ax)
        tax.set_xlabel("time (h)")
    return fig


def _sigma_band(ax: Any, result: TestResult, zero: Sequence[Any], hours: Sequence[float]) -> None:
    """±2σ about x′ = 0 for the compensated position: σ of the command (q_sigma) with the position sensor's
    wander (the measured error carries both); nothing when the model gives no σ."""
    by_step = dict(zip((id(s) for s in result.steps), step_sigmas_um(result), strict=True))
    sigmas = [by_step[id(s)] for s in zero]
    if not sigmas or not all(map(math.isfinite, sigmas)):
        return
    m2 = result.measurement_sigma_um ** 2
    band = np.array([2e3 * math.sqrt(sigma * sigma + m2) for sigma in sigmas])
    ax.fill_between(hours, -band, band, color=WITH_COLOR, alpha=0.15, lw=0, gid="sigma-band",
                    label="±2σ expected error (q_sigma with the sensor's wander)")


def figure_accuracy(results: Sequence[TestResult], *, provenance: str = "", training: Training | None = None
                    ) -> Any:
    """After the paper's Fig. 11: Table I as bars, repeatability as bars, and the accuracy at each test point.

    ``axes[0]`` is Table I, ``axes[1]`` the per-point accuracy, ``axes[2]`` the repeatability (drawn
    between them)."""
    plt = pyplot()
    with plt.rc_context(STYLE):
        fig = _draw_accuracy(plt, results, training)
        compensated = any(r.compensated for r in results)
        if compensated:
            fig.axes[0].annotate("* without compensation: computed from the same run, x − (q′ − x′)", (0, 0),
                                 xycoords="figure fraction", xytext=(8, 4 + (FOOTER_PT if provenance else 0)),
                                 textcoords="offset points", fontsize=8, color="0.3")
        return laid_out(fig, provenance, 0.04 if compensated else 0.0)


PAIR_WIDTH, SINGLE_WIDTH = 0.38, 0.6  # bar widths: a without/with pair per test, or one bar


def _bar_shift(results: Sequence[TestResult]) -> float:
    """How far a compensated test's "without" and "with" bars stand either side of its tick."""
    return PAIR_WIDTH / 2 if any(r.compensated for r in results) else 0.0


def _bars(ax: Any, results: Sequence[TestResult], without: Sequence[float], with_: Sequence[float]) -> None:
    """Per test a "without" bar and, for a compensated test, a "with" bar beside it, labelled in nm."""
    compensated = [i for i, r in enumerate(results) if r.compensated]
    width = PAIR_WIDTH if compensated else SINGLE_WIDTH
    shift = _bar_shift(results)
    bars = ax.bar([i - shift if r.compensated else i for i, r in enumerate(results)], without, width,
                  color=WITHOUT_COLOR, label="without compensation")
    ax.bar_label(bars, fmt="%.0f", padding=2, fontsize=9)
    if compensated:
        bars = ax.bar([i + shift for i in compensated], [with_[i] for i in compensated], width, color=WITH_COLOR,
                      label="with compensation")
        ax.bar_label(bars, fmt="%.0f", padding=2, fontsize=9)
    ax.set_xticks(range(len(results)), [r.name + ("*" if r.compensated else "") for r in results])
    ax.set_xlim(-0.75, len(results) - 0.25)
    ax.margins(y=0.12)
    ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=2, frameon=False)


def _truth_marks(ax: Any, results: Sequence[TestResult]) -> None:
    """On the Table I bars: where each bar would stand against the true position (a simulated cell only)."""
    marks: list[tuple[float, float]] = []  # (bar position, accuracy against the truth)
    shift = _bar_shift(results)
    for i, r in enumerate(results):
        if r.has_truth:
            without, with_ = r.true_accuracy_nm()
            marks += [(i - shift, without), (i + shift, with_)] if r.compensated else [(i, without)]
    if marks:
        ax.scatter([x for x, _ in marks], [y for _, y in marks], marker="D", s=22, color="0.1", zorder=3,
                   label="against the true position")
        ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.08), ncol=2, frameon=False)


def _draw_accuracy(plt: Any, results: Sequence[TestResult], training: Training | None) -> Any:
    fig = plt.figure(figsize=(16, 5.2))
    grid = fig.add_gridspec(1, 3, width_ratios=(1, 1, 1.4))
    ax1, ax2, ax_rep = fig.add_subplot(grid[0, 0]), fig.add_subplot(grid[0, 2]), fig.add_subplot(grid[0, 1])
    _bars(ax1, results, [r.accuracy_without_nm for r in results], [r.accuracy_nm for r in results])
    _truth_marks(ax1, results)
    ax1.set_ylabel("accuracy (nm)")
    ax1.set_title("Table I: mean accuracy per test")
    _bars(ax_rep, results, [r.repeatability_without_nm for r in results], [r.repeatability_nm for r in results])
    ax_rep.set_ylabel("repeatability (nm)")
    ax_rep.set_title("mean repeatability per test (ISO 9283 RP)")
    _draw_points(ax2, results, training)
    return fig


def _draw_points(ax2: Any, results: Sequence[TestResult], training: Training | None) -> None:
    values: list[float] = []
    for k, r in enumerate(results):
        color = f"C{k}"
        xs = [p.target_um[r.axis] for p in r.points_without]
        ax2.plot(xs, [p.accuracy_nm for p in r.points_without], "o--", ms=4, color=color, alpha=0.7,
                 mfc="none", label=f"{r.name} without" + (" (computed)" if r.compensated else ""))
        values.extend(p.accuracy_nm for p in r.points_without)
        if r.compensated:
            ax2.plot(xs, [p.accuracy_nm for p in r.points], "o-", ms=4, color=color, label=f"{r.name} with")
            values.extend(p.accuracy_nm for p in r.points)
    ax2.set_xlabel("test point x′ (µm)")
    ax2.set_ylabel("accuracy (nm)")
    ax2.set_title("accuracy at each test point (ISO 9283)")
    points = sorted({p.target_um[r.axis] for r in results for p in r.points_without})
    if points:
        ax2.set_xticks(points)
        if training is not None and (points[0] < training.x_range[0] or points[-1] > training.x_range[1]):
            ax2.axvspan(*training.x_range, color="0.5", alpha=0.1, lw=0, label="training x range",
                        gid="training-range-x")
    value_axis(ax2, values)
    ax2.grid(alpha=0.3)
    ax2.legend(loc="upper center", bbox_to_anchor=(0.5, -0.12), ncol=3 if len(results) > 1 else 2, frameon=False)


def value_axis(ax: Any, values: Sequence[float]) -> None:
    """Linear from 0 when the values span less than a decade; else log, labelled in plain numbers."""
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter  # only when a report is asked for

    positive = [v for v in values if math.isfinite(v) and v > 0]
    if not positive or max(positive) < 10 * min(positive):
        ax.set_yscale("linear")
        ax.set_ylim(bottom=0)
        return
    ax.set_yscale("log")
    ax.yaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0)))
    ax.yaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:g}"))
    ax.yaxis.set_minor_formatter(NullFormatter())


def save_figure(fig: Any, stem: Path) -> list[Path]:
    """``stem.png`` at 150 dpi for a notebook page and ``stem.svg`` to scale or edit, both atomically."""
    paths = []
    for suffix, options in ((".png", {"dpi": PNG_DPI}), (".svg", {"metadata": {"Date": None}})):
        path = stem.with_suffix(suffix)
        with atomic_writer(path, "wb") as handle:
            fig.savefig(handle, format=suffix[1:], **options)
        paths.append(path)
    return paths


# ----- a cell of several axes ---------------------------------------------------------------------------

#: Tan, Clévy, Chaillet (Micromachines 2015): a 2-DoF stage's 2-D accuracy without / with compensation, nm
ANCHOR_2DOF_NM = (1400.0, 200.0)
#: what :func:`cell_table` says of its "without" columns (a driven cell's validate says how it ran instead)
SAME_ROOM_NOTE = "without comp.: the same plan run uncompensated (command = target) in the same room, same noise."


def cell_table(name: str, truth: TestResult, measured: TestResult) -> str:
    """Table I per axis and the ISO 9283 pose accuracy AP / repeatability RP in the cell's dimension, against
    the true position (``truth``) and the position sensors (``measured``): the same test scored twice."""
    axes = truth.axes
    dim = f"{len(axes)}-D"
    head = (f"{'Test':<8}{'':<8}{'Without comp.':>15}{'With comp.':>12}{'Improvement':>13}   | "
            f"{'interferometer: without':>24}{'with':>9}")
    lines = [f"TABLE I per axis and ISO 9283 pose accuracy AP in {dim} (mean over P1..P{len(truth.points_without)}), "
             "against the TRUE position | against the interferometers", head, "-" * len(head)]

    def row(label: str, t0: float, t1: float, m0: float, m1: float) -> str:
        return (f"{name:<8}{label:<8}{_nm(t0):>15}{_nm(t1):>12}{ratio_text(t0 / t1 if t1 else None):>13}   | "
                f"{_nm(m0):>24}{_nm(m1):>9}")

    for a in axes:
        lines.append(row(f"axis {a}", truth.axis_accuracy_nm(a, with_model=False), truth.axis_accuracy_nm(a),
                         measured.axis_accuracy_nm(a, with_model=False), measured.axis_accuracy_nm(a)))
    lines.append(row(f"AP {dim}", truth.accuracy_without_nm, truth.accuracy_nm,
                     measured.accuracy_without_nm, measured.accuracy_nm))
    lines.append(row(f"RP {dim}", truth.repeatability_without_nm, truth.repeatability_nm,
                     measured.repeatability_without_nm, measured.repeatability_nm))
    lines.append(SAME_ROOM_NOTE)
    lines.append(f"AP: distance from the barycentre of the attained points to the target; RP: l̄ + 3 S_l (ISO 9283). "
                 f"Anchor (Tan, Clévy, Chaillet 2015, 2-DoF): {ANCHOR_2DOF_NM[0]:.0f} nm -> {ANCHOR_2DOF_NM[1]:.0f} nm "
                 f"({ANCHOR_2DOF_NM[0] / ANCHOR_2DOF_NM[1]:.0f}×)")
    lines.append("")
    lines.append(f"per point (against the true position): AP / RP in {dim}, without -> with")
    for i, p0 in enumerate(truth.points_without):
        where = ", ".join(f"{a} = {p0.target_um[a]:g}" for a in axes)
        p1 = truth.points[i] if truth.compensated else None
        after = f" -> {p1.accuracy_nm:6.1f} / {p1.repeatability_nm:5.1f} nm" if p1 else ""
        lines.append(f"  ({where}) µm: {p0.accuracy_nm:7.1f} / {p0.repeatability_nm:5.1f} nm{after} "
                     f"({p0.visits} visits)")
    return "\n".join(lines)


def cell_json(name: str, truth: TestResult, measured: TestResult, **extra: Any) -> dict[str, Any]:
    def part(scores: TestResult) -> dict[str, Any]:
        return {"without": scores.scores_dict(with_model=False), "with": scores.scores_dict(with_model=True),
                "improvement_ratio": None if not math.isfinite(scores.improvement) else round(scores.improvement, 3)}

    return {**extra, "test": name, "axes": list(truth.axes), "against_truth": part(truth),
            "against_interferometer": part(measured)}


def write_cell_report(directory: str | Path, text: str, doc: Mapping[str, Any], truth: TestResult,
                      targets_um: Mapping[str, np.ndarray], attained_without: Mapping[str, np.ndarray],
                      attained_with: Mapping[str, np.ndarray] | None, *, provenance: str = "") -> list[Path]:
    """Write the report files (each atomically); returns their paths. ``provenance``: the figure's footer."""
    plt = pyplot()
    out = Path(directory)
    written = _write_texts(out, {"table1_axes.txt": text + "\n", "validation.json": json.dumps(doc, indent=2) + "\n"})
    with plt.rc_context(STYLE):  # the notebook-readable fonts of fig9 and fig11, text kept as text in the SVG
        fig = with_footer(_cell_figure(plt, truth, targets_um, attained_without, attained_with), provenance)
        written.extend(save_figure(fig, out / "fig_cell_accuracy"))
        plt.close(fig)
    return written


def _cell_figure(plt: Any, truth: TestResult, targets_um: Mapping[str, np.ndarray],
            attained_without: Mapping[str, np.ndarray], attained_with: Mapping[str, np.ndarray] | None) -> Any:
    axes = truth.axes
    a, b = axes[0], axes[1]
    points = truth.points_without
    fig, panels = plt.subplots(1, len(points) + 1, figsize=(3.8 * (len(points) + 1), 4.2))
    for ax, p in zip(panels[:-1], points, strict=True):
        here = np.all([np.asarray(targets_um[k]) == p.target_um[k] for k in axes], axis=0)
        for attained, label, color in ((attained_without, "without", "tab:red"), (attained_with, "with", "tab:blue")):
            if attained is None:
                continue
            da = (np.asarray(attained[a])[here] - p.target_um[a]) * 1e3
            db = (np.asarray(attained[b])[here] - p.target_um[b]) * 1e3
            ax.scatter(da, db, s=6, color=color, alpha=0.6, label=label)
            ax.plot([da.mean()], [db.mean()], marker="+", color=color, markersize=12)
        ax.plot([0], [0], marker="x", color="black")
        ax.set_title(", ".join(f"{k} = {p.target_um[k]:g}" for k in axes) + " µm")
        ax.set_xlabel(f"{a} - target (nm)")
        ax.set_ylabel(f"{b} - target (nm)")
        ax.set_aspect("equal", adjustable="datalim")
    panels[0].legend()
    bars = panels[-1]
    labels = [f"axis {k}" for k in axes] + [f"AP {len(axes)}-D"]
    without = [truth.axis_accuracy_nm(k, with_model=False) for k in axes] + [truth.accuracy_without_nm]
    x = np.arange(len(labels))
    bars.bar(x - 0.2, without, 0.4, color="tab:red", label="without")
    if truth.compensated:
        with_ = [truth.axis_accuracy_nm(k) for k in axes] + [truth.accuracy_nm]
        bars.bar(x + 0.2, with_, 0.4, color="tab:blue", label="with")
    bars.set_xticks(x, labels)
    bars.set_ylabel("accuracy vs truth (nm)")
    bars.legend()
    fig.tight_layout()
    return fig
