"""A multi-axis model: its CSV, its file, and the daemon's streaming path against the batch one."""

import json

import numpy as np
import pytest

from nanodrift.calibration.dataset import DataError, read_csv, write_csv
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.runs import cell_command
from nanodrift.model.cell_model import CellModel, load_any_model, save_cell_model
from nanodrift.model.identify import fit, fit_cell
from nanodrift.model.model import Model, ModelFileError, save_model


@pytest.fixture(scope="module")
def xy_data():
    return simulate_dataset("train", axes="xy", cycles=8, seed=21)


@pytest.fixture(scope="module")
def xy_model(xy_data):
    return fit_cell(xy_data, order=3).model


def test_multi_axis_csv_round_trip(tmp_path, xy_data):
    path = tmp_path / "xy.csv"
    write_csv(xy_data, path)
    header = path.read_text().splitlines()[0].split(",")
    assert header[:5] == ["t_s", "x_um", "y_um", "q_x_um", "q_y_um"] and "y_true_um" in header
    back = read_csv(path)
    assert back.axes == ("x", "y") and list(back.channels) == ["T1", "T2", "T3", "T4"]
    for a in "xy":
        np.testing.assert_array_equal(back.positions[a], xy_data.positions[a])
        np.testing.assert_array_equal(back.commands[a], xy_data.commands[a])
        np.testing.assert_array_equal(back.extra[f"{a}_true_um"], xy_data.extra[f"{a}_true_um"])


@pytest.mark.parametrize(("text", "expected"), [
    ("t_s,x_um,y_um,q_um,T1\n0,0,0,0,20\n", "names its commands q_x_um, q_y_um, not q_um"),
    ("t_s,x_um,y_um,q_x_um,T1\n0,0,0,0,20\n", "missing column 'q_y_um'"),
    ("t_s,x_um,y_um,q_x_um,q_y_um,q_z_um,T1\n0,0,0,0,0,0,20\n", "q_z_um commands an axis with no position column"),
    ("t_s,x_um,y_um,q_x_um,q_y_um,T1\n0,0,0,0,0,20\n1,30,oops,30,0,20\n", "row 3, column y_um: 'oops' is not a number"),
])
def test_multi_axis_csv_refusals_name_row_and_column(tmp_path, text, expected):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(DataError) as err:
        read_csv(path)
    assert expected in str(err.value) and str(path) in str(err.value)


def test_stream_equals_batch(xy_data, xy_model):
    batch = xy_model.predict(xy_data)
    command = cell_command(xy_model)
    worst = 0.0
    for i in range(len(xy_data)):
        q = command({a: float(xy_data.positions[a][i]) for a in "xy"}, float(xy_data.t[i]),
                    {c: float(v[i]) for c, v in xy_data.channels.items()})
        worst = max(worst, *(abs(q[a] - batch[a][i]) for a in "xy"))
    assert worst < 1e-9
    assert np.sqrt(np.mean((batch["y"] - xy_data.commands["y"]) ** 2)) < 0.05  # it also fits: tens of nm


def test_model_file_round_trip_id_and_tamper(tmp_path, xy_data, xy_model):
    path = tmp_path / "xy.json"
    save_cell_model(xy_model, path)
    loaded = load_any_model(path)
    assert isinstance(loaded, CellModel) and loaded.axes == ("x", "y") and loaded.id == xy_model.id
    for a in "xy":
        np.testing.assert_array_equal(loaded.predict(xy_data)[a], xy_model.predict(xy_data)[a])
    doc = json.loads(path.read_text())
    doc["models"]["x"]["terms"][0]["coef"] *= 1.001
    path.write_text(json.dumps(doc))
    with pytest.raises(ModelFileError, match=r"models\.x: its id .* does not match its content"):
        load_any_model(path)
    assert isinstance(load_any_model(path, check_id=False), CellModel)


def test_a_cell_of_one_axis_is_the_one_axis_model_and_file(tmp_path, xy_data, xy_model):
    one = fit(xy_data.alone("x"), order=3).model
    cell = CellModel.of(one)
    assert cell.axes == ("x",) and cell.id == one.id == one.content_id()
    assert CellModel.of(xy_model) is xy_model
    save_model(one, tmp_path / "one.json")
    save_cell_model(cell, tmp_path / "cell.json")
    assert (tmp_path / "cell.json").read_bytes() == (tmp_path / "one.json").read_bytes()  # the one-axis file
    loaded = load_any_model(tmp_path / "cell.json")
    assert isinstance(loaded, Model) and loaded.id == one.id
    assert cell.position_ranges == {"x": one.training.x_range}
    with pytest.raises(ValueError, match="one axis: x"):
        CellModel(("y",), {"y": one})
