"""A one-axis cell after multi-axis cells arrived: its model ids and command bytes are today's.

The expected values were produced by main at 98babf5 (before the daemon learnt ``[[axes]]``), through the
path the daemon takes now (the model read by ``load_served_model``, the command by the
compensator of one axis and ``encode_command``).
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.cell_helpers import write_cell_model
from helpers.daemon_harness import write_test_model
from helpers.floats import assert_same

from nanodrift.bus.protocol import encode_command
from nanodrift.compensation import Compensator, Target, load_served_model
from nanodrift.config import ActuatorConfig, parse_config
from nanodrift.drivers.base import Reading, SensorConfig
from nanodrift.model.model import Model, ModelFileError
from nanodrift.service.table import SensorTable
from nanodrift.settings import DEFAULT_MODEL_PATH


def test_one_axis_model_ids_are_unchanged(tmp_path: Path) -> None:
    # the shipped model (refitted when the default selection became coherent) and the one shipped before it
    assert load_served_model(DEFAULT_MODEL_PATH, ("x",)).id == "m-5f3cfa7690f2"
    before = Path(__file__).parents[1] / "model" / "data" / "default_model_before_hac.json"
    assert load_served_model(before, ("x",)).id == "m-37a14bbc1429"
    write_test_model(tmp_path / "m.json")
    model = load_served_model(tmp_path / "m.json", ("x",))
    assert isinstance(model, Model) and model.id == "m-735e979167ac"


def test_one_axis_command_payloads_are_byte_for_byte_unchanged(tmp_path: Path) -> None:
    write_test_model(tmp_path / "m.json")
    model = load_served_model(tmp_path / "m.json", ("x",))
    assert isinstance(model, Model)
    config = parse_config({})
    assert config.axes == [] and config.axis_names == ("x",) and not config.multi_axis
    table = SensorTable([SensorConfig(name=n, kind="x", max_age_s=5.0) for n in ("T1", "T2")])
    for name, value in {"T1": 21.8, "T2": 22.3}.items():
        table.update(name, Reading(value, t=10.0))
    comp = Compensator(model, {"x": ActuatorConfig()}, table)
    comp.observe(10.0, {"T1": 21.8, "T2": 22.3})
    assert_same(encode_command(comp.compensate(Target(7, {"x": 240.0}), now=11.0, unix_now=1700000000.25)), (
        b'{"id":7,"x_um":240.0,"q_um":216.45048000000003,"voltage_v":4.329009600000001,"temperatures_c":'
        b'{"T1":21.8,"T2":22.3},"model":"m-735e979167ac","t":1700000000.25,"extrapolating":["T2"],'
        b'"q_sigma_um":null}'))
    assert_same(encode_command(comp.compensate(Target("a", {"x": 490.0}), now=11.5, unix_now=1700000000.5)), (
        b'{"id":"a","x_um":490.0,"q_um":467.20198,"voltage_v":9.3440396,"temperatures_c":{"T1":21.8,"T2":22.3},'
        b'"model":"m-735e979167ac","t":1700000000.5,"extrapolating":["x","T2"],"q_sigma_um":null}'))


def test_a_multi_axis_model_is_refused_by_a_one_axis_cell_and_the_reverse(tmp_path: Path) -> None:
    write_cell_model(tmp_path / "xy.json", ("x", "y"))
    write_test_model(tmp_path / "x.json")
    with pytest.raises(ModelFileError, match=r"a multi-axis model \(axes x, y\), but this cell has one axis"):
        load_served_model(tmp_path / "xy.json", ("x",))
    with pytest.raises(ModelFileError, match=r"serves axes x \(one axis\), the cell has axes x, y, z"):
        load_served_model(tmp_path / "x.json", ("x", "y", "z"))
    with pytest.raises(ModelFileError, match=r"serves axes x, y, the cell has axes x, z"):
        load_served_model(tmp_path / "xy.json", ("x", "z"))
