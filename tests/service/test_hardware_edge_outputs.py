"""Issue 26 item 1: one output drives one axis, for every driver kind, refused when the config is read.

Through the public interfaces: ``nanodrift check-config`` on the file, and ``nanodrift run`` against a
real Modbus module (pymodbus' TCP server on 127.0.0.1) that must receive nothing. The one mechanism:
each ``[axes.actuator]`` declares the outputs it writes (:meth:`ActuatorOptions.claims`), and a
generic check refuses an output claimed twice, naming both axes.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.cell_helpers import ThreadedModbus, write_cell_model
from helpers.daemon_harness import REPO, TEMPS, TESTS, SensorFile, install_file_plugin, run_cli

HUB = '[[hubs]]\nname = "dac"\nhost = "127.0.0.1"\nport = {port}\ntimeout_s = 0.5\n'


def modbus(address: int, data_type: str = "int16") -> str:
    return f'kind = "modbus"\nhub = "dac"\naddress = {address}\ndata_type = "{data_type}"\nscale = 0.001\n'


def xy_config(root: Path, x_actuator: str, y_actuator: str, hub_port: int = 502) -> Path:
    model = root / "model.json"
    write_cell_model(model, ("x", "y"))
    axes = "".join(f'[[axes]]\nname = "{axis}"\nmin_um = 0.0\nmax_um = 480.0\n[axes.actuator]\n{keys}\n'
                   for axis, keys in (("x", x_actuator), ("y", y_actuator)))
    hubs = HUB.format(port=hub_port) if "modbus" in x_actuator + y_actuator else ""
    readings = SensorFile(root / "sensors.json", dict(TEMPS)).path
    sensors = "".join(f'[[sensors]]\nname = "{ch}"\nkind = "file"\npath = "{readings}"\ninterval_s = 0.05\n'
                      "max_age_s = 2.0\ntimeout_s = 0.5\n\n" for ch in TEMPS)
    config = root / "xy.toml"
    config.write_text(f'cell = "xy"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:0"]\n'
                      f'multicast_scouting = false\n[model]\npath = "{model}"\n\n{axes}{hubs}{sensors}')
    return config


def cli(root: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift <args>`` with the harness' ``file`` sensor plugin installed."""
    path = os.pathsep.join([str(install_file_plugin(root / "plugins")), str(TESTS), str(REPO)])
    return subprocess.run([sys.executable, "-m", "nanodrift.cli", *args], capture_output=True, text=True,
                          timeout=30, env={**os.environ, "PYTHONPATH": path})


def check_config(config: Path) -> subprocess.CompletedProcess[str]:
    """``nanodrift check-config`` run by the console script's own ``main`` in this process (it reads a file and
    opens nothing: a process of its own would only add half a second of CPU start-up)."""
    return run_cli("check-config", str(config), pythonpath=[install_file_plugin(config.parent / "plugins")])


SERIAL = 'kind = "serial_line"\nport = "/dev/ttyUSB7"\n'
SHARED = {
    "one_register": (modbus(10), modbus(10), "holding register 10 of Modbus hub 'dac', unit id 1 is"),
    "int32_pair_over_the_next_register": (modbus(10, "int32"), modbus(11),
                                          "holding register 11 of Modbus hub 'dac', unit id 1 is"),
    "one_gcs_command_on_one_port": (SERIAL + 'command = "SVA 1 {voltage_v:.4f}\\n"\n',
                                    SERIAL + 'command = "SVA  1 {voltage_v:.3f}\\n"\n',
                                    "command 'SVA 1 {}' of the controller on port '/dev/ttyUSB7' is"),
    "one_pi_gcs_axis": ('kind = "pi_gcs"\nhost = "10.0.0.2"\naxis = "1"\n',
                        'kind = "pi_gcs"\nhost = "10.0.0.2"\naxis = "1"\n',
                        "axis '1' of the PI controller at 10.0.0.2:50000 is"),
}


@pytest.mark.parametrize("case", list(SHARED))
def test_check_config_refuses_two_axes_on_one_output_naming_both(tmp_path: Path, case: str) -> None:
    x_keys, y_keys, output = SHARED[case]
    result = check_config(xy_config(tmp_path, x_keys, y_keys))
    assert result.returncode != 0, result.stdout
    assert f"axes[1] (y).actuator: {output} already the output of axes[0] (x): one output drives one axis" \
        in result.stderr, result.stderr


@pytest.mark.parametrize(("x_keys", "y_keys"), [
    (modbus(10, "int32"), modbus(12)),  # the pair 10-11, then 12
    (SERIAL + 'command = "SVA 1 {voltage_v:.4f}\\n"\n', SERIAL + 'command = "SVA 2 {voltage_v:.4f}\\n"\n'),
    ('kind = "pi_gcs"\nhost = "10.0.0.2"\naxis = "1"\n', 'kind = "pi_gcs"\nhost = "10.0.0.2"\naxis = "2"\n'),
], ids=["modbus", "serial_line", "pi_gcs"])
def test_check_config_accepts_axes_on_outputs_of_their_own(tmp_path: Path, x_keys: str, y_keys: str) -> None:
    result = check_config(xy_config(tmp_path, x_keys, y_keys))
    assert result.returncode == 0, result.stderr


def test_the_daemon_refuses_to_start_on_a_shared_register_and_the_module_receives_nothing(tmp_path: Path) -> None:
    module = ThreadedModbus().start()
    try:
        config = xy_config(tmp_path, modbus(10), modbus(10), hub_port=module.port)
        result = cli(tmp_path, "run", "--config", str(config))
        assert result.returncode != 0
        assert "axes[1] (y).actuator: holding register 10 of Modbus hub 'dac', unit id 1 is already the output of " \
               "axes[0] (x)" in result.stderr + result.stdout, result.stderr
        assert list(module.device.writes) == []
    finally:
        module.stop()
