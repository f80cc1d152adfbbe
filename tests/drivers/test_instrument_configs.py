"""The worked instrument config (config/lab-ids-dcon.toml) passes ``nanodrift check-config`` and builds one
group for the thermocouple module and one for the interferometer."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from helpers.daemon_harness import run_cli, write_test_model

from nanodrift.assembly import build_drivers
from nanodrift.config import load_config
from nanodrift.drivers.attocube_ids.group import IdsGroup
from nanodrift.drivers.dcon.group import DconModuleGroup

CONFIG = Path(__file__).resolve().parents[2] / "config" / "lab-ids-dcon.toml"


def test_check_config_accepts_it_once_calibrated(tmp_path: Path) -> None:
    write_test_model(tmp_path / "model.json")
    calibrated = tmp_path / "nanodrift.toml"
    calibrated.write_text(CONFIG.read_text().replace('"/var/lib/nanodrift/model.json"', f'"{tmp_path / "model.json"}"'))
    result = run_cli("check-config", str(calibrated))
    assert result.returncode == 0, result.stderr
    assert "5 sensor(s)" in result.stdout


def test_it_builds_one_exchange_per_module_and_one_connection_per_interferometer() -> None:
    drivers = build_drivers(load_config(CONFIG))
    [module] = [g for g in drivers.groups if isinstance(g, DconModuleGroup)]
    [ids] = [g for g in drivers.groups if isinstance(g, IdsGroup)]
    assert module.names == ("T1", "T2", "T3", "T4") and module.address == 1 and module.open_detection
    assert ids.names == ("interferometer",) and ids.rpc.endpoint == "192.168.1.30:9090"


def test_a_misspelt_key_is_refused_naming_the_sensor_and_key(tmp_path: Path) -> None:
    broken = tmp_path / "nanodrift.toml"
    broken.write_text(CONFIG.read_text().replace("ids_axis = 0", "ids_axis = 4"))
    result = run_cli("check-config", str(broken))
    assert result.returncode == 2
    assert "sensors[4] (interferometer).ids_axis" in result.stderr


XY = '''cell = "xy0"
[[hubs]]
name = "dac"
type = "tcp"
host = "192.168.1.21"
[[hubs]]
name = "rs485"
port = "/dev/ttyUSB0"
[[axes]]
name = "x"
[axes.actuator]
kind = "modbus"
hub = "dac"
address = 10
scale = 0.001
[[axes]]
name = "y"
[axes.actuator]
kind = "modbus"
hub = "dac"
address = 11
scale = 0.001
[[sensors]]
name = "T1"
kind = "dcon"
hub = "rs485"
address = 1
channel = 0
[[sensors]]
name = "ifm_x"
role = "position"
axis = "x"
kind = "attocube_ids"
host = "192.168.1.30"
ids_axis = 0
[[sensors]]
name = "ifm_y"
role = "position"
axis = "y"
kind = "attocube_ids"
host = "192.168.1.30"
ids_axis = 1
'''


def test_an_xy_cell_reads_an_ids_axis_per_stage_axis_over_one_connection(tmp_path: Path) -> None:
    path = tmp_path / "xy.toml"
    path.write_text(XY)
    drivers = build_drivers(load_config(path))
    [ids] = [g for g in drivers.groups if isinstance(g, IdsGroup)]
    assert ids.names == ("ifm_x", "ifm_y") and [c.ids_axis for c in ids.channels] == [0, 1]
    path.write_text(XY.replace("ids_axis = 1", "ids_axis = 0"))
    result = subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(path)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 2
    assert "sensors[2] (ifm_y).ids_axis: axis 0 of the IDS at 192.168.1.30:9090 is already read by sensors[1] " \
           "(ifm_x)" in result.stderr
