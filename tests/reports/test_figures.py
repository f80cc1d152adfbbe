"""Figures fit for a lab notebook (issue 13, item 5): units, titles, readable legends, linear axes
where the values span less than a decade, no empty legend entries, 150 dpi PNG plus SVG."""

import re
import struct
from pathlib import Path

import pytest

from nanodrift.calibration.iso9283 import summarize
from nanodrift.calibration.plans import PlannedStep, StepResult, validation_plan
from nanodrift.reports.validation import figure_accuracy, figure_drift, table1, write_report


def a_test(name: str, compensated: bool, error_um: float, drift_um: float):
    """A validation run whose every visit lands ``error_um`` (+ a little per point) off its target."""
    steps = []
    for s in validation_plan(3):
        q = s.target_um - drift_um if compensated else s.target_um
        x = s.target_um + error_um * (1 + s.target_um / 960.0)
        steps.append(StepResult(PlannedStep.on_x(s.index, s.cycle, s.target_um), 29.0 * s.index, q_um={"x": q},
                                positions_um={"x": x},
                                temperatures={"T1": 21.7 + 1e-4 * s.index, "T4": 21.6}, valid=True))
    return summarize(name, steps, compensated=compensated)


def texts(fig) -> list[str]:
    out = [t.get_text() for t in fig.texts]
    for ax in fig.axes:
        out += [ax.get_title(), ax.get_xlabel(), ax.get_ylabel()]
        legend = ax.get_legend()
        if legend is not None:
            out += [t.get_text() for t in legend.get_texts()]
    return [t for t in out if t]


def legend_entries(ax) -> list[str]:
    legend = ax.get_legend()
    return [] if legend is None else [t.get_text() for t in legend.get_texts()]


@pytest.fixture(scope="module")
def figures():
    """Fig. 11 (accuracy) and fig. 9 (drift) of one uncompensated and one compensated test, drawn once for the
    tests that only read them (titles, labels, legends): laying a figure out takes half a second."""
    results = [a_test("test1", False, 0.3, 0.0), a_test("test2", True, 0.05, 0.3)]
    return figure_accuracy(results), figure_drift(results)


def test_every_panel_is_titled_and_labelled_with_units(figures):
    for fig in figures:
        for ax in fig.axes:
            assert ax.get_title(), "an untitled panel"
            assert ax.get_ylabel()
        assert not re.search(r"\bum\b", " ".join(texts(fig)))  # µm, never "um"
    accuracy, drift = figures
    value_axes = [ax for ax in drift.axes if "(nm)" in ax.get_ylabel()]
    temperature_axes = [ax for ax in drift.axes if ax.get_ylabel() == "temperature (°C)"]
    assert len(value_axes) == len(temperature_axes) == 2
    assert all(ax.get_ylabel().startswith("drift") for ax in value_axes)  # a quantity, not just "nm"
    assert all(ax.get_xlabel() == "time (h)" for ax in temperature_axes)
    assert accuracy.axes[1].get_xlabel() == "test point x′ (µm)"


def test_legends_are_readable_and_never_empty(figures):
    for fig in figures:
        for ax in fig.axes:
            legend = ax.get_legend()
            if legend is not None:
                assert min(t.get_fontsize() for t in legend.get_texts()) >= 9


def test_without_compensation_has_no_with_compensation_entry():
    only = [a_test("test1", False, 0.3, 0.0)]
    accuracy = figure_accuracy(only)
    assert legend_entries(accuracy.axes[0]) == ["without compensation"]
    assert all("with" not in entry.split() for entry in legend_entries(accuracy.axes[1]))
    drift = figure_drift(only)
    assert not any("with compensation" in entry for ax in drift.axes for entry in legend_entries(ax))


def test_linear_axis_within_a_decade_log_with_plain_labels_beyond():
    close = [a_test("test2", True, 0.2, 0.3)]  # 200..300 nm with, 500..700 nm without: less than a decade
    ax = figure_accuracy(close).axes[1]
    assert ax.get_yscale() == "linear" and ax.get_ylim()[0] == 0.0

    wide = [a_test("test2", True, 0.01, 0.5)]  # 10 nm with, 500 nm without
    ax = figure_accuracy(wide).axes[1]
    assert ax.get_yscale() == "log"
    labels = [ax.yaxis.get_major_formatter()(v, i) for i, v in enumerate((20.0, 100.0, 500.0))]
    assert labels == ["20", "100", "500"]  # never "2×10¹"


def png_dpi(path: Path) -> float:
    data = path.read_bytes()
    at = data.index(b"pHYs") + 4
    per_metre, _, unit = struct.unpack(">IIB", data[at:at + 9])
    assert unit == 1
    return per_metre * 0.0254


def test_report_writes_150_dpi_png_and_svg_of_each_figure(tmp_path):
    results = [a_test("test1", False, 0.3, 0.0), a_test("test2", True, 0.05, 0.3)]
    files = write_report(results, tmp_path, table1(results), {})
    for stem in ("fig9_drift_at_zero", "fig11_accuracy"):
        png, svg = tmp_path / f"{stem}.png", tmp_path / f"{stem}.svg"
        assert png in files and svg in files
        assert png_dpi(png) == pytest.approx(150, abs=0.5)
        text = svg.read_text()
        assert text.lstrip().startswith("<?xml") and "<svg" in text
    assert "°C" in (tmp_path / "fig9_drift_at_zero.svg").read_text()  # text kept as text
