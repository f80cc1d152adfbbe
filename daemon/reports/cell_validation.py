"""A multi-axis cell's ISO 9283 validation as text, JSON and figures: Table I per axis, AP/RP in 2-D/3-D.

Each test is scored twice: against the true position (the simulated cell knows it) and against the
interferometers' readings, so a reader sees what the beams' own noise and wander add. ``--report DIR``
writes ``table1_axes.txt``, ``validation.json`` and ``fig_cell_accuracy.png``/``.svg``: the attained
points around each target in the plane of the first two axes (with and without the model, in nm
from the target) and the per-axis and 2-D/3-D accuracy bars.
"""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.atomic import atomic_write_text
from nanodrift.calibration.iso9283 import CellTestResult
from nanodrift.reports.validation import EMPTY, ratio_text, save_figure

#: Tan, Clévy, Chaillet (Micromachines 2015): a 2-DoF stage's 2-D accuracy without / with compensation, nm
ANCHOR_2DOF_NM = (1400.0, 200.0)


@dataclass
class CellScores:
    """One test of a multi-axis cell against one reference: without the model, and with it (None: not run)."""

    without: CellTestResult
    with_model: CellTestResult | None

    @property
    def improvement(self) -> float:
        return self.without.accuracy_nm / self.with_model.accuracy_nm if self.with_model else math.nan


def _nm(value: float | None) -> str:
    return EMPTY if value is None or not math.isfinite(value) else f"{value:.0f} nm"


def cell_table(name: str, truth: CellScores, measured: CellScores) -> str:
    """Table I per axis and the ISO 9283 pose accuracy AP / repeatability RP in the cell's dimension."""
    axes = truth.without.axes
    dim = f"{len(axes)}-D"
    head = (f"{'Test':<8}{'':<8}{'Without comp.':>15}{'With comp.':>12}{'Improvement':>13}   | "
            f"{'interferometer: without':>24}{'with':>9}")
    lines = [f"TABLE I per axis and ISO 9283 pose accuracy AP in {dim} (mean over P1..P{len(truth.without.points)}), "
             "against the TRUE position | against the interferometers", head, "-" * len(head)]

    def row(label: str, t0: float, t1: float | None, m0: float, m1: float | None) -> str:
        ratio = t0 / t1 if t1 else None
        return (f"{name:<8}{label:<8}{_nm(t0):>15}{_nm(t1):>12}{ratio_text(ratio):>13}   | "
                f"{_nm(m0):>24}{_nm(m1):>9}")

    def w(scores: CellScores) -> CellTestResult | None:
        return scores.with_model

    for a in axes:
        with_t, with_m = w(truth), w(measured)
        lines.append(row(f"axis {a}", truth.without.axis_accuracy_nm(a),
                         with_t.axis_accuracy_nm(a) if with_t else None,
                         measured.without.axis_accuracy_nm(a), with_m.axis_accuracy_nm(a) if with_m else None))
    with_t, with_m = w(truth), w(measured)
    lines.append(row(f"AP {dim}", truth.without.accuracy_nm, with_t.accuracy_nm if with_t else None,
                     measured.without.accuracy_nm, with_m.accuracy_nm if with_m else None))
    lines.append(row(f"RP {dim}", truth.without.repeatability_nm, with_t.repeatability_nm if with_t else None,
                     measured.without.repeatability_nm, with_m.repeatability_nm if with_m else None))
    lines.append("without comp.: the same plan run uncompensated (command = target) in the same room, same noise.")
    lines.append(f"AP: distance from the barycentre of the attained points to the target; RP: l̄ + 3 S_l (ISO 9283). "
                 f"Anchor (Tan, Clévy, Chaillet 2015, 2-DoF): {ANCHOR_2DOF_NM[0]:.0f} nm -> {ANCHOR_2DOF_NM[1]:.0f} nm "
                 f"({ANCHOR_2DOF_NM[0] / ANCHOR_2DOF_NM[1]:.0f}×)")
    lines.append("")
    lines.append(f"per point (against the true position): AP / RP in {dim}, without -> with")
    for i, p0 in enumerate(truth.without.points):
        where = ", ".join(f"{a} = {p0.target_um[a]:g}" for a in axes)
        p1 = with_t.points[i] if with_t else None
        after = f" -> {p1.accuracy_nm:6.1f} / {p1.repeatability_nm:5.1f} nm" if p1 else ""
        lines.append(f"  ({where}) µm: {p0.accuracy_nm:7.1f} / {p0.repeatability_nm:5.1f} nm{after} "
                     f"({p0.visits} visits)")
    return "\n".join(lines)


def cell_json(name: str, truth: CellScores, measured: CellScores, **extra: Any) -> dict[str, Any]:
    def part(scores: CellScores) -> dict[str, Any]:
        return {"without": scores.without.to_dict(),
                "with": scores.with_model.to_dict() if scores.with_model else None,
                "improvement_ratio": None if not math.isfinite(scores.improvement) else round(scores.improvement, 3)}

    return {**extra, "test": name, "axes": list(truth.without.axes), "against_truth": part(truth),
            "against_interferometer": part(measured)}


def write_cell_report(directory: str | Path, text: str, doc: Mapping[str, Any], truth: CellScores,
                      targets_um: Mapping[str, np.ndarray], attained_without: Mapping[str, np.ndarray],
                      attained_with: Mapping[str, np.ndarray] | None) -> list[Path]:
    """Write the report files (each atomically); returns their paths."""
    import matplotlib  # figures only when a report is asked for

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "table1_axes.txt", out / "validation.json"]
    atomic_write_text(written[0], text + "\n")
    atomic_write_text(written[1], json.dumps(doc, indent=2) + "\n")
    fig = _figure(plt, truth, targets_um, attained_without, attained_with)
    written.extend(save_figure(fig, out / "fig_cell_accuracy"))
    plt.close(fig)
    return written


def _figure(plt: Any, truth: CellScores, targets_um: Mapping[str, np.ndarray],
            attained_without: Mapping[str, np.ndarray], attained_with: Mapping[str, np.ndarray] | None) -> Any:
    axes = truth.without.axes
    a, b = axes[0], axes[1]
    points = truth.without.points
    fig, panels = plt.subplots(1, len(points) + 1, figsize=(3.0 * (len(points) + 1), 3.2))
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
        ax.set_title(", ".join(f"{k}={p.target_um[k]:g}" for k in axes) + " µm", fontsize=8)
        ax.set_xlabel(f"{a} - target (nm)")
        ax.set_ylabel(f"{b} - target (nm)")
        ax.set_aspect("equal", adjustable="datalim")
    panels[0].legend(fontsize=7)
    bars = panels[-1]
    labels = [f"axis {k}" for k in axes] + [f"AP {len(axes)}-D"]
    without = [truth.without.axis_accuracy_nm(k) for k in axes] + [truth.without.accuracy_nm]
    x = np.arange(len(labels))
    bars.bar(x - 0.2, without, 0.4, color="tab:red", label="without")
    if truth.with_model is not None:
        with_ = [truth.with_model.axis_accuracy_nm(k) for k in axes] + [truth.with_model.accuracy_nm]
        bars.bar(x + 0.2, with_, 0.4, color="tab:blue", label="with")
    bars.set_xticks(x, labels, fontsize=7)
    bars.set_ylabel("accuracy vs truth (nm)")
    bars.legend(fontsize=7)
    fig.tight_layout()
    return fig

