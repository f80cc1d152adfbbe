"""Discovery figures and report.md for a lab notebook (issue 13, item 5): binary variables as points, scatter
points in the legend, titles in words, µm and °C, 150 dpi PNG plus SVG, parameters and rules in words."""

from __future__ import annotations

import re
import struct
from pathlib import Path

import numpy as np
import pytest
from helpers.discovery_helpers import cell_run, paper_model

from nanodrift.calibration.discovery import Candidate, discover
from nanodrift.calibration.discovery.settings import DEFAULT_SETTINGS
from nanodrift.model.terms import Lag
from nanodrift.reports.discovery import figure_residuals, format_params, markdown, verdict, write_report


@pytest.fixture(scope="module")
def hysteresis():
    """Hysteresis hidden in a bidirectional run: named, with ``dir`` the variable that shows it."""
    data = cell_run("hysteresis", seed=1, bidirectional=True)
    result = discover(data, paper_model(data))
    assert [s.effect for s in result.steps][:1] == ["hysteresis"], result.summary
    return result


@pytest.fixture(scope="module")
def nothing():
    """A forward-only calibration with nothing hidden: nothing found, hysteresis untestable."""
    data = cell_run("", seed=0)
    result = discover(data, paper_model(data))
    assert not result.steps, result.summary
    return result


@pytest.fixture(scope="module")
def drawn():
    """``figure_residuals(result, variable)`` drawn once per module for the tests that only read a figure (its
    labels, legend, points and lines); a test that renders one (``canvas.draw``) draws its own."""
    figures: dict[tuple[int, str], tuple[object, object]] = {}

    def draw(result, variable: str):
        key = (id(result), variable)
        if key not in figures:
            figures[key] = (result, figure_residuals(result, variable))  # the result kept: its id stays its own
        return figures[key][1]

    return draw


def texts(fig) -> list[str]:
    out = []
    for ax in fig.axes:
        out += [ax.get_title(), ax.get_xlabel(), ax.get_ylabel()]
        out += [t.get_text() for t in ax.get_xticklabels()]
        legend = ax.get_legend()
        if legend is not None:
            out += [t.get_text() for t in legend.get_texts()]
    return [t for t in out if t]


def png_dpi(path: Path) -> float:
    data = path.read_bytes()
    at = data.index(b"pHYs") + 4
    per_metre, _, unit = struct.unpack(">IIB", data[at:at + 9])
    assert unit == 1
    return per_metre * 0.0254


def test_a_binary_variable_is_drawn_as_points_per_value_not_a_line(hysteresis, drawn) -> None:
    ax = drawn(hysteresis, "dir").axes[0]
    assert [t.get_text() for t in ax.get_xticklabels()] == ["down", "up"]
    for line in ax.get_lines():
        xs, ys = line.get_xdata(), line.get_ydata()
        joins_values = line.get_linestyle() not in ("None", "none", "", " ") and len(set(xs)) > 1
        assert not joins_values or set(ys) == {0.0}, "a line joins 'down' and 'up'"  # only the zero line


def test_scatter_points_are_in_the_legend_and_visible_there(hysteresis, drawn) -> None:
    for variable in ("dir", "t"):
        legend = drawn(hysteresis, variable).axes[0].get_legend()
        entries = [t.get_text() for t in legend.get_texts()]
        assert "given model: each row" in entries and "extended model: each row" in entries, entries
        for text, handle in zip(entries, legend.legend_handles, strict=True):
            if "each row" in text:
                assert handle.get_alpha() == 1.0  # the plot's faint points, drawn solid in the legend


@pytest.mark.parametrize(("variable", "title", "unit"), [
    ("last_step", "Residuals against the size of the last step", "(µm)"),
    ("rate(T2)", "Residuals against the rate of change of T2", "(°C/h"),
    ("T1", "Residuals against temperature T1", "(°C)"),
    ("x", "Residuals against position", "(µm)"),
    ("t", "Residuals against time", "(h)"),
])
def test_titles_are_words_and_units_are_micrometres_and_degrees(hysteresis, drawn, variable, title, unit) -> None:
    fig = drawn(hysteresis, variable)
    ax = fig.axes[0]
    assert ax.get_title() == title
    assert unit in ax.get_xlabel()
    joined = " ".join(texts(fig))
    assert "last_step" not in joined and "rate(" not in joined
    assert not re.search(r"\bum\b|degC", joined)


def test_a_forward_only_last_step_is_three_levels_not_a_blurred_scatter(nothing, drawn) -> None:
    ax = drawn(nothing, "last_step").axes[0]
    assert [t.get_text() for t in ax.get_xticklabels()] == ["−480", "0", "30"]


def test_the_report_writes_150_dpi_png_and_svg_of_every_figure(hysteresis, tmp_path) -> None:
    files = write_report(hysteresis, tmp_path, "m2.json")
    pngs = [f for f in files if f.suffix == ".png"]
    assert {p.stem for p in pngs} >= {"gap", "residuals_vs_dir"}
    for png in pngs:
        assert png_dpi(png) == pytest.approx(150, abs=0.5)
        svg = png.with_suffix(".svg")
        assert svg in files and "<svg" in svg.read_text()
    report = (tmp_path / "report.md").read_text()
    for png in pngs:
        assert f"]({png.name})" in report


def test_report_md_gives_parameters_in_words_and_explains_every_rule(hysteresis) -> None:
    report = markdown(hysteresis, ["gap.png"], "m2.json")
    assert "{'" not in report and "':" not in report  # no raw Python dicts
    rules = report.split("## Rules applied", 1)[1]
    cited = {int(n) for n in re.findall(r"\(rule (\d+)\)", report)} | {1, 2}
    for n in cited:
        assert re.search(rf"^{n}\. \*\*", rules, re.MULTILINE), f"rule {n} is cited but never explained"
    assert "a move counts when larger than 0.5 µm" in report  # hysteresis's parameter, in words


def test_a_deferred_candidate_says_why_in_words() -> None:
    c = Candidate("thermal_lag", [Lag("T4", 2100.0)], [], {"channel": "T4", "tau_s": 2100.0,
                  "tau_behind_fastest_s": 2250.0, "deferred_to": "T3"}, 1, 4)
    text = format_params(c)
    assert text.startswith("channel T4, time constant τ = 35 min")
    assert "deferred to the same effect on T3, the fastest channel (rule 5)" in text
    assert "deferred_to" not in text and "{" not in text
    assert verdict(c, False, DEFAULT_SETTINGS) == "deferred to T3 (rule 5)"


def test_nothing_found_is_reported_with_what_the_run_cannot_show(nothing, tmp_path) -> None:
    write_report(nothing, tmp_path, None)
    report = (tmp_path / "report.md").read_text()
    assert "nothing found; no model written" in report
    cannot = report.split("## What this run cannot show", 1)[1]
    assert "**hysteresis**" in cannot and "nanodrift simulate --scenario bidirectional" in cannot



def test_time_and_temperatures_are_drawn_as_continuous_axes_on_a_real_report(nothing, drawn) -> None:
    """A forward-only calibration (408 rows over 3.3 h): every row at its own time, binned means across the run."""
    hours = nothing.variables["t"][1] / 3600.0
    for variable, span in (("t", (hours.min(), hours.max())), ("T1", None), ("rate(T1)", None)):
        ax = drawn(nothing, variable).axes[0]
        xs = np.concatenate([c.get_offsets()[:, 0] for c in ax.collections if len(c.get_offsets())])
        values = nothing.variables[variable][1] / (3600.0 if variable == "t" else 1.0)
        assert np.unique(values).size > 100
        assert set(np.round(xs, 9)) == set(np.round(values, 9)), variable  # each row at its value, no category
        assert not [t.get_text() for t in ax.get_xticklabels() if t.get_text() and not _numeric(t.get_text())]
        means = [line for line in ax.get_lines() if len(line.get_xdata()) >= 10]
        assert means, f"{variable}: no binned-mean line"
        if span is not None:
            assert xs.min() == pytest.approx(span[0], abs=1e-9) and xs.max() == pytest.approx(span[1], abs=1e-9)
            centres = means[0].get_xdata()
            assert centres[0] < 0.2 * span[1] and centres[-1] > 0.8 * span[1]  # the means cover the run


def _numeric(text: str) -> bool:
    try:
        float(text.replace("−", "-"))
    except ValueError:
        return False
    return True


def test_a_value_with_one_row_shows_that_row_beside_its_mean(nothing, drawn) -> None:
    """Forward-only "last step": 0 µm is one row (the first); its point must not hide under the mean marker."""
    ax = drawn(nothing, "last_step").axes[0]
    zero = [t.get_text() for t in ax.get_xticklabels()].index("0")
    points = np.concatenate([c.get_offsets() for c in ax.collections if len(c.get_offsets())])
    here = points[np.abs(points[:, 0] - zero) < 0.5]
    mean_x = [x for line in ax.get_lines() if line.get_marker() == "D" for x in line.get_xdata()
              if abs(x - zero) < 0.5]
    assert len(here) >= 1 and len(mean_x) == 1
    assert np.min(np.abs(here[:, 0] - mean_x[0])) > 0.1  # beside the diamond, not under it


@pytest.mark.parametrize("variable", ["t", "last_step", "dir"])
def test_the_legend_sits_below_the_data(nothing, hysteresis, variable) -> None:
    for result in (nothing, hysteresis):
        fig = figure_residuals(result, variable)
        fig.canvas.draw()
        ax = fig.axes[0]
        legend, frame = ax.get_legend().get_window_extent(), ax.get_window_extent()
        assert legend.y1 <= frame.y0, "the legend overlaps the plotted data"


def test_nothing_found_shows_the_given_model_never_hidden_under_its_refit(nothing, drawn) -> None:
    """The same terms refitted on the same run change nothing: one series, said so, not two stacked."""
    legend = drawn(nothing, "t").axes[0].get_legend()
    entries = [t.get_text() for t in legend.get_texts()]
    assert entries == ["given model: each row", "given model: binned mean"], entries
    assert "changes no residual by more than 0.1 nm" in legend.get_title().get_text()


def test_a_given_model_from_another_run_is_drawn_over_its_refit(drawn) -> None:
    """Nothing found with a model fitted elsewhere: both series, the given model's drawn last and on top."""
    data = cell_run("", seed=0, cycles=12)
    result = discover(data, paper_model(cell_run("", seed=7, cycles=12)))
    assert not result.found, result.summary
    assert np.max(np.abs(result.residual_before - result.residual_after)) * 1000 > 0.1
    for variable in ("t", "last_step"):
        entries = [t.get_text() for t in drawn(result, variable).axes[0].get_legend().get_texts()]
        assert {"given model: each row", "the given terms refitted on this run: each row"} <= set(entries)
    lines = {line.get_label(): line for line in drawn(result, "t").axes[0].get_lines()}
    given, refit = lines["given model: binned mean"], lines["the given terms refitted on this run: binned mean"]
    assert given.get_zorder() > refit.get_zorder()  # drawn over the refit's line
    assert given.get_linestyle() != refit.get_linestyle() and given.get_markerfacecolor() == "white"
    ax = drawn(result, "last_step").axes[0]
    means = [line.get_xdata() for line in ax.get_lines() if line.get_marker() == "D"]
    assert len(means) == 2 and np.all(np.abs(means[0] - means[1]) > 0.2)  # side by side, never stacked
