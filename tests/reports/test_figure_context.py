"""Issue 19, item 7: every figure says where it came from, fig9 shades the training range, fig11 shows
repeatability as well as accuracy, and the truth of a simulated cell is drawn and written beside the
interferometer's view (an optional per-step ``x_true_um``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nanodrift.calibration import iso9283
from nanodrift.calibration.iso9283 import summarize
from nanodrift.calibration.plans import PlannedStep, StepResult, validation_plan
from nanodrift.model.model import Training
from nanodrift.reports.validation import figure_accuracy, figure_drift, raw_csv, table1, truth_table, write_report

TRAINING = Training(x_range=(0.0, 480.0), channel_ranges={"T1": (21.55, 21.98), "T4": (21.50, 21.95)}, rows=408,
                    t_span_s=12000.0)
FOOTER = "model m-0123456789ab (fitted on calibration.csv) · simulated cell: test2, --seed 3"


def a_test(name: str, compensated: bool, error_um: float, drift_um: float, spread_um: float = 0.0,
           truth_offset_um: float | None = None) -> iso9283.TestResult:
    """Every visit lands ``error_um`` off its target, ± ``spread_um`` alternately; with ``truth_offset_um``
    the true position is known and lies that far from what was measured."""
    steps = []
    for s in validation_plan(4):
        q = s.target_um - drift_um if compensated else s.target_um
        x = s.target_um + error_um + (spread_um if s.index % 2 else -spread_um)
        truth = {"x": x - truth_offset_um} if truth_offset_um is not None else {}
        steps.append(StepResult(PlannedStep.on_x(s.index, s.cycle, s.target_um), 29.0 * s.index, q_um={"x": q},
                                positions_um={"x": x}, temperatures={"T1": 21.7 + 1e-4 * s.index, "T4": 21.6},
                                valid=True, true_um=truth))
    return summarize(name, steps, compensated=compensated)


def test_every_figure_carries_its_provenance_footer(tmp_path):
    results = [a_test("test2", True, 0.04, 0.3)]
    for draw in (figure_drift, figure_accuracy):
        fig = draw(results, provenance=FOOTER)
        assert FOOTER in [t.get_text() for t in fig.texts], draw.__name__
    write_report(results, tmp_path, table1(results), {}, provenance=FOOTER)
    for stem in ("fig9_drift_at_zero", "fig11_accuracy"):
        assert "m-0123456789ab" in (tmp_path / f"{stem}.svg").read_text()  # kept as text in the SVG


def test_fig9_shades_each_channels_training_range_on_the_temperature_panel():
    fig = figure_drift([a_test("test5", True, 0.1, 1.4)], training=TRAINING)
    (temperatures,) = [ax for ax in fig.axes if ax.get_ylabel() == "temperature (°C)"]
    bands = {p.get_gid(): p for p in temperatures.patches if (p.get_gid() or "").startswith("training-range-")}
    assert set(bands) == {"training-range-T1", "training-range-T4"}
    for channel, (low, high) in TRAINING.channel_ranges.items():
        band = bands[f"training-range-{channel}"]
        corners = temperatures.transData.inverted().transform(band.get_verts())  # data coordinates
        assert corners[:, 1].min() == pytest.approx(low) and corners[:, 1].max() == pytest.approx(high)
    bottom, top = temperatures.get_ylim()
    assert bottom <= 21.50 and top >= 21.98  # the band is in view even when the test is far above it


def test_fig11_draws_repeatability_bars_per_test():
    results = [a_test("test1", False, 0.3, 0.0, spread_um=0.02), a_test("test2", True, 0.04, 0.3, spread_um=0.05)]
    fig = figure_accuracy(results)
    (repeatability,) = [ax for ax in fig.axes if ax.get_ylabel() == "repeatability (nm)"]
    heights = sorted(round(bar.get_height(), 6) for bar in repeatability.patches)
    expected = sorted(round(float(np.mean(values)), 6) for values in (
        [p.repeatability_nm for p in results[0].points_without],
        [p.repeatability_nm for p in results[1].points_without],
        [p.repeatability_nm for p in results[1].points]))
    assert heights == expected  # test1: one bar (no "with"); test2: without and with
    assert [t.get_text() for t in repeatability.get_xticklabels()] == ["test1", "test2*"]


def test_the_truth_is_written_and_drawn_only_where_it_is_known():
    measured = a_test("test2", True, 0.04, 0.3)
    known = a_test("test3", True, 0.04, 0.3, truth_offset_um=0.03)
    assert known.true_accuracy_nm()[1] == pytest.approx(10.0)  # 40 nm measured, the truth 30 nm closer
    assert math.isnan(measured.true_accuracy_nm()[1])
    header = raw_csv([measured]).splitlines()[0]
    assert "x_true_um" not in header  # hardware's columns, as before
    rows = raw_csv([measured, known]).splitlines()
    assert rows[0].endswith(",x_true_um,q_sigma_um")  # the σ column appended after it (issue 27)
    assert rows[1].split(",")[-2] == "nan"
    assert float(rows[-1].split(",")[-2]) == pytest.approx(known.x_true_um[-1])
    assert truth_table([measured]) == ""
    assert "10 nm" in truth_table([measured, known]).splitlines()[-1]
    marks = [c for c in figure_accuracy([measured, known]).axes[0].collections
             if c.get_label() == "against the true position"]
    assert len(marks) == 1 and sorted(marks[0].get_offsets()[:, 1].round(6)) == pytest.approx(
        sorted(known.true_accuracy_nm()))
    assert "true_position" not in measured.to_dict() and known.to_dict()["true_position"]["with_comp_nm"] == 10.0
