"""Table I as text or JSON, and a report directory: figures after the paper's Fig. 9 and 11, raw data.

``--report DIR`` writes:
- ``table1.txt`` and ``validation.json``: what ``validate`` prints;
- ``fig9_drift_at_zero.png``: per test, the drift at the zero position over time (the uncompensated
  position, measured or computed) and the compensation the model applied (x' - q');
- ``fig11_accuracy.png``: accuracy with and without compensation per test (bars) and per point;
- ``validation_raw.csv``: one row per step: test, cycle, target, command, measured position, the
  computed uncompensated position, validity and the temperatures.
"""

from __future__ import annotations

import csv
import io
import json
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

from daemon.atomic import atomic_write_text, atomic_writer
from daemon.calibration.validation import TestResult, x_without

PAPER_TABLE1: dict[str, tuple[float, float | None]] = {
    "test1": (546.0, None),
    "test2": (378.0, 35.0),
    "test3": (478.0, 62.0),
    "test4": (492.0, 57.0),
    "test5": (2225.0, 646.0),
}


def _nm(v: float) -> str:
    return "\\" if not math.isfinite(v) else f"{v:.0f} nm"


def table1(results: Sequence[TestResult], paper: Mapping[str, tuple[float, float | None]] | None = None) -> str:
    """Table I: accuracy (mean over the test points) without and with compensation."""
    head = f"{'Test':<10}{'Without comp.':>15}{'With comp.':>12}{'Improvement':>22}"
    if paper:
        head += f"   | paper: {'without':>8}{'with':>8}{'ratio':>7}"
    lines = ["TABLE I  accuracy with and without compensation (mean of |mean attained - target| over the points)",
             head, "-" * len(head)]
    for r in results:
        star = "*" if r.compensated else " "
        ratio = r.improvement
        imp = "\\" if not math.isfinite(ratio) else f"{ratio:.1f}x ({(ratio - 1) * 100:.0f}%)"
        line = f"{r.name:<10}{_nm(r.accuracy_without_nm) + star:>15}{_nm(r.accuracy_nm):>12}{imp:>22}"
        if paper and r.name in paper:
            p0, p1 = paper[r.name]
            pr = f"{p0 / p1:.1f}x" if p1 else "\\"
            line += f"   |        {p0:>6.0f}{(f'{p1:.0f}' if p1 else chr(92)):>8}{pr:>7}"
        if r.invalid_steps:
            line += f"  ({r.invalid_steps} invalid steps)"
        if r.extrapolating_steps:
            line += f"  [{r.extrapolating_steps} steps extrapolating]"
        lines.append(line)
    lines.append("* from calculation, not measurement: x_without = x_measured - (q' - x') over the same period.")
    return "\n".join(lines)


def results_json(results: Sequence[TestResult], **extra: Any) -> dict[str, Any]:
    return {"tests": [r.to_dict() for r in results], **extra}


def raw_csv(results: Sequence[TestResult]) -> str:
    channels: list[str] = []
    for r in results:
        for s in r.steps:
            channels.extend(c for c in s.temperatures if c not in channels)
    out = io.StringIO()
    writer = csv.writer(out, lineterminator="\n")
    writer.writerow(["test", "t_s", "cycle", "target_um", "q_um", "x_measured_um", "x_without_um", "valid",
                     *channels])
    for r in results:
        for s in r.steps:
            writer.writerow([r.name, repr(s.t_s), s.step.cycle, repr(s.step.target_um), repr(s.q_um), repr(s.x_um),
                             repr(x_without(s)), int(s.valid),
                             *(repr(s.temperatures.get(c, math.nan)) for c in channels)])
    return out.getvalue()


def write_report(results: Sequence[TestResult], directory: str | Path, text: str, doc: Mapping[str, Any]) -> list[Path]:
    """Write the report files (each atomically); returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    written = [out / "table1.txt", out / "validation.json", out / "validation_raw.csv"]
    atomic_write_text(written[0], text + "\n")
    atomic_write_text(written[1], json.dumps(doc, indent=2) + "\n")
    atomic_write_text(written[2], raw_csv(results))

    fig, axes = plt.subplots(len(results), 1, figsize=(8, 2.2 * len(results) + 0.6), squeeze=False)
    for ax, r in zip(axes[:, 0], results, strict=True):
        zero = [s for s in r.steps if s.step.target_um == 0.0 and s.valid]
        hours = [s.t_s / 3600.0 for s in zero]
        ax.plot(hours, [1e3 * x_without(s) for s in zero], "o-", ms=3, label="drift (uncompensated position)")
        if r.compensated:
            ax.plot(hours, [1e3 * (s.step.target_um - s.q_um) for s in zero], "s-", ms=3,
                    label="compensation (x' - q')")
            ax.plot(hours, [1e3 * s.x_um for s in zero], ".-", ms=3, label="compensated position")
        ax.set_title(f"{r.name}: at the zero position", fontsize=9)
        ax.set_ylabel("nm")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, loc="best")
    axes[-1, 0].set_xlabel("time (h, backend clock)")
    fig.tight_layout()
    written.append(_save(fig, out / "fig9_drift_at_zero.png"))
    plt.close(fig)

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4))
    names = [r.name for r in results]
    idx = range(len(results))
    ax1.bar([i - 0.2 for i in idx], [r.accuracy_without_nm for r in results], 0.4, label="without compensation")
    ax1.bar([i + 0.2 for i in idx], [r.accuracy_nm if r.compensated else 0.0 for r in results], 0.4,
            label="with compensation")
    ax1.set_xticks(list(idx), [n + ("*" if r.compensated else "") for n, r in zip(names, results, strict=True)])
    ax1.set_ylabel("accuracy (nm)")
    ax1.set_title("Table I (* without: computed)", fontsize=9)
    ax1.legend(fontsize=8)
    for r in results:
        xs = [p.target_um for p in r.points]
        ax2.plot(xs, [p.accuracy_without_nm for p in r.points], "--", alpha=0.6, label=f"{r.name} without")
        if r.compensated:
            ax2.plot(xs, [p.accuracy_nm for p in r.points], "o-", ms=3, label=f"{r.name} with")
    ax2.set_xlabel("test point x' (um)")
    ax2.set_ylabel("accuracy (nm)")
    ax2.set_yscale("log")
    ax2.legend(fontsize=6, ncol=2)
    fig.tight_layout()
    written.append(_save(fig, out / "fig11_accuracy.png"))
    plt.close(fig)
    return written


def _save(fig: Any, path: Path) -> Path:
    with atomic_writer(path, "wb") as handle:
        fig.savefig(handle, format="png", dpi=110)
    return path
