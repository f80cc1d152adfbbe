"""config/lab.toml (the operator's hardware example) is accepted and builds the intended groups."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

import pytest
from helpers.daemon_harness import write_test_model

from nanodrift.assembly import build_drivers
from nanodrift.config import ConfigError, load_config, parse_config
from nanodrift.drivers.modbus.config import ModbusSensorConfig
from nanodrift.drivers.modbus.group import ModbusBlockGroup
from nanodrift.drivers.serial_line.config import SerialLineSensorConfig
from nanodrift.drivers.serial_line.line import SerialLineGroup

LAB = Path(__file__).resolve().parents[3] / "config" / "lab.toml"


def test_lab_config_is_accepted_by_the_loader() -> None:
    config = load_config(LAB)
    thermocouples = [s for s in config.sensors if isinstance(s, ModbusSensorConfig)]
    assert [s.name for s in thermocouples] == [f"T{i}" for i in range(1, 9)]
    assert [s.address for s in thermocouples] == list(range(8))
    assert all((s.input_type, s.data_type, s.scale, s.nan_value) == ("input", "int16", 0.1, -32768)
               for s in thermocouples)
    [interferometer] = [s for s in config.sensors if isinstance(s, SerialLineSensorConfig)]
    assert (interferometer.role, interferometer.query, interferometer.scale) == ("position", "POS?\r", 0.001)
    assert interferometer.pattern == "P (?P<value>[-+0-9.]+) nm"


def test_lab_config_builds_one_request_for_eight_thermocouples() -> None:
    drivers = build_drivers(load_config(LAB))
    modbus = [g for g in drivers.groups if isinstance(g, ModbusBlockGroup)]
    serial = [g for g in drivers.groups if isinstance(g, SerialLineGroup)]
    assert len(modbus) == 1 and modbus[0].names == tuple(f"T{i}" for i in range(1, 9))
    assert (modbus[0].block.start, modbus[0].block.count) == (0, 8)
    assert len(serial) == 1 and serial[0].names == ("interferometer",)


def test_check_config_accepts_it_once_calibrated(tmp_path: Path) -> None:
    def check(path: Path) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(path)],
                              capture_output=True, text=True, timeout=60)

    # as shipped, before `nanodrift calibrate` wrote /var/lib/nanodrift/model.json: a reload would be refused
    if not Path("/var/lib/nanodrift/model.json").exists():
        result = check(LAB)
        assert result.returncode == 2 and f"{LAB}:28: model.path: /var/lib/nanodrift/model.json" in result.stderr
    write_test_model(tmp_path / "model.json")
    calibrated = tmp_path / "nanodrift.toml"
    calibrated.write_text(LAB.read_text().replace('"/var/lib/nanodrift/model.json"', f'"{tmp_path / "model.json"}"'))
    result = check(calibrated)
    assert result.returncode == 0, result.stderr
    assert "9 sensor(s)" in result.stdout


def test_a_typo_in_a_modbus_key_is_named() -> None:
    data = tomllib.loads(LAB.read_text())
    data["sensors"][2]["nan_valeu"] = -32768
    with pytest.raises(ConfigError, match=r"sensors\[2\] \(\w+\)\.nan_valeu: unknown key"):
        parse_config(data, source=str(LAB))
