"""``[[axes]]``: a multi-axis cell's config, and every refusal with its file:line."""

from __future__ import annotations

from pathlib import Path

import pytest

from nanodrift.assembly import procedure_drivers
from nanodrift.config import ConfigError, load_config
from nanodrift.drivers.base import DriverSetupError

AXIS = '''[[axes]]
name = "{name}"
min_um = 0.0
max_um = {max_um}
[axes.actuator]
kind = "zenoh"
volts_per_um = {gain}
'''


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return path


def axes(*names: str) -> str:
    return "".join(AXIS.format(name=n, max_um=480.0 + 10 * i, gain=0.02 + 0.001 * i) for i, n in enumerate(names))


def problems(tmp_path: Path, text: str) -> list[str]:
    with pytest.raises(ConfigError) as caught:
        load_config(write(tmp_path, text))
    return str(caught.value).splitlines()


def test_an_xyz_cell_has_its_axes_in_order_each_with_its_workspace_and_actuator(tmp_path: Path) -> None:
    sensor = '[[sensors]]\nname = "ifm_y"\nkind = "modbus"\nhub = "h"\naddress = 0\nrole = "position"\naxis = "y"\n'
    config = load_config(write(tmp_path, 'cell = "xyz"\n' + axes("x", "y", "z") + '[[hubs]]\nname = "h"\n' + sensor))
    assert config.sensor_axis("ifm_y") == "y" and config.sensor_workspaces() == {"ifm_y": (0.0, 490.0)}
    assert config.multi_axis and config.axis_names == ("x", "y", "z")
    actuators = config.axis_actuators()
    assert actuators["y"].workspace_um == (0.0, 490.0) and actuators["z"].volts_per_um == pytest.approx(0.022)
    assert config.actuator is actuators["x"]


def test_refusals_name_the_axis_and_the_line(tmp_path: Path) -> None:
    text = 'cell = "c"\n[actuator]\nv_max = 10.0\n' + axes("x", "y", "y", "q") + (
        '[[axes]]\nname = "w"\nmin_um = 5.0\nmax_um = 1.0\n[axes.actuator]\nx_max_um = 3.0\nv_min = "a"\n')
    lines = problems(tmp_path, text)
    assert any(":2: actuator: a cell with [[axes]] has one actuator per axis: move the keys of [actuator] (v_max)"
               in line for line in lines), lines
    assert any(":19: axes[2] (y).name: axis 'y' is named twice" in line for line in lines), lines
    assert any(":26: axes[3] (q).name: String should match pattern" in line for line in lines), lines
    assert any(":37: axes[4] (w).actuator.x_max_um: the axis' workspace is its own max_um" in line
               for line in lines), lines
    assert any(":38: axes[4] (w).actuator.v_min: Input should be a valid number" in line for line in lines), lines
    assert any(":32: axes[4] (w): Value error, min_um (5) must be below max_um (1)" in line for line in lines), lines


def test_a_cell_without_an_x_axis_is_refused_saying_why(tmp_path: Path) -> None:
    lines = problems(tmp_path, 'cell = "c"\n' + axes("y", "z"))
    assert any("axes: no axis named x (axes: y, z)" in line and "x_um" in line for line in lines), lines


def test_a_sensor_on_an_unknown_axis_is_refused_naming_it(tmp_path: Path) -> None:
    sensor = '[[sensors]]\nname = "T1"\nkind = "modbus"\nhub = "h"\naddress = 0\nrole = "position"\naxis = "z"\n'
    hub = '[[hubs]]\nname = "h"\n'
    lines = problems(tmp_path, 'cell = "c"\n' + axes("x", "y") + hub + sensor)
    assert any(":24: sensors[0] (T1).axis: unknown axis 'z'; the cell's axes: x, y" in line for line in lines), lines


def test_a_procedure_refuses_a_multi_axis_cell_whose_outputs_it_cannot_drive(tmp_path: Path) -> None:
    """A multi-axis procedure drives each axis' own output (daemon/procedure/steps.py): kind = "zenoh"
    axes (the daemon's published command is their actuation) are refused, naming them."""
    config = load_config(write(tmp_path, 'cell = "c"\n' + axes("x", "y")))
    with pytest.raises(DriverSetupError, match=r'axis x, y: \[axes.actuator\] kind = "zenoh" has no output'):
        procedure_drivers(config)
