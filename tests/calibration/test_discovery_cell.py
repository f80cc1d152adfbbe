"""Discovery on a multi-axis cell: per axis, against every axis' position, with the cross-axis effects."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from nanodrift.calibration.dataset import write_csv
from nanodrift.calibration.discovery import discover_cell
from nanodrift.calibration.discovery.catalogue import untestable
from nanodrift.calibration.discovery.diagnostics import structure_variables
from nanodrift.calibration.discovery.settings import DEFAULT_SETTINGS
from nanodrift.model.cell_model import CellModel, load_any_model, save_cell_model
from nanodrift.model.identify import fit, fit_cell
from nanodrift.model.terms import Channel, Power
from tests.helpers.synthetic import xy_run


def _independent_axes(data) -> CellModel:
    """What two one-axis cells side by side would serve: each axis on its own position and the channels."""
    models = {}
    for axis in data.axes:
        view = data.axis_view(axis)
        models[axis] = fit(view, order=3, candidates=lambda n, a=axis, v=view: [
            *(Power(k, a) for k in range(n, 0, -1)), *(Channel(c) for c in v.channels)]).model
    return CellModel(data.axes, models)


@pytest.fixture(scope="module")
def xy():
    return xy_run(cycles=4, seed=3)


def test_an_axis_blind_to_the_other_is_told_its_crosstalk_and_bending(xy) -> None:
    result = discover_cell(xy, _independent_axes(xy))
    for axis, other in (("x", "y"), ("y", "x")):
        named = [(s.effect, [t.name for t in s.add]) for s in result.axes[axis].steps]
        assert named[0] == ("crosstalk", [other]), named
        assert ("coupled_bending", ["x*y"]) in named, named
        # the residual is checked against the other axis' position, and that is where it disagrees first
        assert result.axes[axis].disagreements[0].variable == other
        assert result.axes[axis].final["holdout_rms_um"] < 0.1 * result.axes[axis].baseline["holdout_rms_um"]
    assert result.found and result.model.id != result.given.id


def test_a_cell_model_with_its_cross_terms_has_nothing_cross_axis_left(xy) -> None:
    result = discover_cell(xy, fit_cell(xy, order=3).model)
    named = {s.effect for r in result.axes.values() for s in r.steps}
    assert not named & {"crosstalk", "coupled_bending"}


def test_every_axis_position_is_a_structure_variable_and_motion_is_the_modelled_axis(xy) -> None:
    variables = structure_variables(xy.axis_view("y"))
    np.testing.assert_array_equal(variables["y"][1], xy.positions["y"])
    assert "of axis y" in variables["dir"][0]
    x_view = structure_variables(xy.axis_view("x"))
    np.testing.assert_array_equal(x_view["y"][1], xy.positions["y"])
    assert "of axis" not in x_view["dir"][0]  # x's own motion is described as in a one-axis cell


def test_discover_writes_a_cell_model_from_the_command_line(tmp_path: Path, xy) -> None:
    data, given, out = tmp_path / "xy.csv", tmp_path / "given.json", tmp_path / "extended.json"
    write_csv(xy, data)
    save_cell_model(_independent_axes(xy), given)
    done = subprocess.run([sys.executable, "-m", "nanodrift.cli", "discover", str(data), "--model", str(given),
                           "--out", str(out), "--json"], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    assert sorted(doc["axes"]) == ["x", "y"] and doc["model_out"] == str(out)
    assert doc["axes"]["x"]["steps"][0]["effect"] == "crosstalk"
    extended = load_any_model(out)
    assert isinstance(extended, CellModel) and doc["final"]["model"] == extended.id
    assert "y" in extended.models["x"].term_names() and "x" in extended.models["y"].term_names()


def test_what_a_run_cannot_show_is_judged_on_the_modelled_axis_motion(xy) -> None:
    forward_x = xy.select(np.argsort(xy.positions["x"], kind="stable"))  # x only ever steps up, y both ways
    forward_x.t = np.arange(len(forward_x)) * 29.0
    assert [u["effect"] for u in untestable(forward_x.axis_view("x"), DEFAULT_SETTINGS)] == ["hysteresis"]
    assert untestable(forward_x.axis_view("y"), DEFAULT_SETTINGS) == []
