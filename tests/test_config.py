"""The operator config: the TOML contract, errors that name file and field, check-config."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest
from helpers.daemon_harness import run_cli as harness_run_cli

from nanodrift.bus.protocol import Keys
from nanodrift.config import DEFAULT_MODEL_PATH, ConfigError, default_config, load_config, missing_model_channels
from nanodrift.drivers.base import POSITION_FROZEN_AFTER_S
from nanodrift.drivers.simulated.config import SimulatedSensorConfig
from nanodrift.model.model import load_model

REPO = Path(__file__).resolve().parent.parent

LAB_LIKE = """
cell = "lab1"
[zenoh]
mode = "client"
connect = ["tcp/10.0.0.2:7447"]
[model]
path = "models/model.json"
[actuator]
volts_per_um = 0.025
v_max = 10.0
[simulation]
scenario = "steady"
speed = 30.0
[[sensors]]
name = "T1"
kind = "simulated"
[[sensors]]
name = "T2"
kind = "simulated"
max_age_s = 3.0
[[sensors]]
name = "interferometer"
role = "position"
kind = "simulated"
interval_s = 0.1
"""


def write(tmp_path: Path, text: str, name: str = "nanodrift.toml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def problems_of(path: Path) -> list[str]:
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    pattern = re.compile(rf"^{re.escape(str(path))}(:\d+)?: ")  # file:line: problem, or file: problem
    assert all(pattern.match(line) for line in str(caught.value).splitlines()), str(caught.value)
    return caught.value.problems


def test_full_config_is_read_with_relative_paths_resolved(tmp_path: Path) -> None:
    path = write(tmp_path, LAB_LIKE)
    config = load_config(path)
    assert config.cell == "lab1" and Keys(config.cell).prefix == "nanodrift/lab1"
    assert config.zenoh.mode == "client" and config.zenoh.connect == ["tcp/10.0.0.2:7447"]
    assert config.model.path == (tmp_path / "models" / "model.json").resolve()
    assert config.actuator.volts_per_um == 0.025 and config.actuator.v_min == -2.0  # default kept
    assert config.actuator.voltage(100.0) == pytest.approx(2.5)
    simulation = config.section("simulation")
    assert simulation.scenario == "steady" and simulation.speed == 30.0 and config.virtual_cell
    assert [s.name for s in config.sensors] == ["T1", "T2", "interferometer"]
    assert all(isinstance(s, SimulatedSensorConfig) for s in config.sensors)  # the plugin's own model
    assert next(s for s in config.sensors if s.name == "T2").max_age_s == 3.0
    assert config.source == str(path)


def test_no_file_means_the_simulated_cell_but_a_sensorless_file_never_does(tmp_path: Path) -> None:
    builtin = default_config()
    assert builtin.model.path == DEFAULT_MODEL_PATH and DEFAULT_MODEL_PATH.exists()
    assert [s.name for s in builtin.sensors] == ["T1", "T2", "T3", "T4", "interferometer"]
    assert {s.kind for s in builtin.sensors} == {"simulated"} and builtin.virtual_cell
    # a file runs the simulator only when it says so (issue 10: an emptied file swapped hardware for it)
    for text in ("", 'cell = "c2"\n[actuator]\nvolts_per_um = 0.01\n'):
        monitoring = load_config(write(tmp_path, text))
        assert monitoring.sensors == [] and not monitoring.virtual_cell and monitoring.sections == {}
    minimal = load_config(write(tmp_path, 'cell = "c2"\n[simulation]\nseed = 3\n'))
    assert [s.name for s in minimal.sensors] == [s.name for s in builtin.sensors] and minimal.virtual_cell


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ('cel = "x"', "cel: unknown key"),
        ("[actuator]\nvolts_per_umm = 1", "actuator.volts_per_umm: unknown key"),
        ('[actuator]\nv_min = "low"', "actuator.v_min:"),
        ("[actuator]\nv_min = 5.0\nv_max = 1.0", "v_min (5.0) must be below v_max (1.0)"),
        ("[actuator]\nx_min_um = nan", "actuator.x_min_um: Input should be a finite number"),
        ('[[sensors]]\nname = "T1"\nkind = "simulated"\nmax_age_s = inf', "sensors[0] (T1).max_age_s: Input should"),
        ('[[sensors]]\nname = "T1"\nkind = "simulated"\ninterval_s = inf', "sensors[0] (T1).interval_s: Input should"),
        ("[simulation]\nspeed = inf", "simulation.speed: Input should be a finite number"),
        ('[[hubs]]\nname = "adam"\n', "hubs[0] (adam): no sensor uses this hub"),
        ('[zenoh]\nmode = "server"', "zenoh.mode:"),
        ('cell = "a/b"', "cell:"),
        ("[simulation]\nspeeed = 2", "simulation.speeed: unknown key"),
        ('[simulation]\nscenario = "tset5"', "simulation.scenario:"),
        ('[[sensors]]\nname = "T1"\nkind = "simulated"\nscale = 2', "sensors[0] (T1).scale: unknown key"),
        ('[[sensors]]\nname = "T1"', "sensors[0] (T1).kind: required"),
        ('[[sensors]]\nname = "T1"\nkind = "thermobox"', "sensors[0] (T1).kind: unknown sensor kind 'thermobox'"),
        ('[[sensors]]\nname = "T1"\nkind = "simulated"\ninterval_s = -1', "sensors[0] (T1).interval_s:"),
        ('[[sensors]]\nname = "T 1"\nkind = "simulated"', "sensors[0] (T 1).name:"),
        ("sensors = 3", "sensors: expected an array of tables"),
    ],
)
def test_bad_configs_name_the_field(tmp_path: Path, text: str, expected: str) -> None:
    problems = problems_of(write(tmp_path, text))
    assert any(expected in p for p in problems), problems


def test_every_problem_is_reported_at_once_with_its_index(tmp_path: Path) -> None:
    text = (
        '[actuator]\nvolts_per_um = "x"\n'
        '[[sensors]]\nname = "T1"\nkind = "simulated"\n'
        '[[sensors]]\nname = "T1"\nkind = "simulated"\n'
        '[[sensors]]\nname = "T3"\nkind = "simulated"\nmax_age = 1\n'
    )
    problems = problems_of(write(tmp_path, text))
    assert any(p.startswith("actuator.volts_per_um:") for p in problems)
    assert any(p.startswith("sensors[1] (T1).name:") and "used twice" in p for p in problems)
    assert any(p.startswith("sensors[2] (T3).max_age: unknown key") for p in problems)


def test_hub_references_must_exist(tmp_path: Path) -> None:
    text = (
        '[[hubs]]\nname = "adam"\nhost = "127.0.0.1"\n'
        '[[hubs]]\nname = "adam"\n'
        '[[sensors]]\nname = "T1"\nkind = "modbus"\nhub = "adma"\naddress = 0\n'
    )
    problems = problems_of(write(tmp_path, text))
    assert any("hubs: name 'adam' is used twice" in p for p in problems)
    assert any(p.startswith("sensors[0] (T1).hub: no [[hubs]] named 'adma'") for p in problems), problems


def test_unreadable_files_are_refused_with_the_file_name(tmp_path: Path) -> None:
    assert problems_of(tmp_path / "absent.toml") == ["file not found"]
    assert "not valid TOML" in problems_of(write(tmp_path, "cell = [unclosed"))[0]
    binary = tmp_path / "binary.toml"
    binary.write_bytes(b"\xff\xfe\x00")
    assert "cannot read" in problems_of(binary)[0]


def test_missing_model_channels() -> None:
    config = default_config()
    assert missing_model_channels(config, ("T1", "T4")) == []
    assert missing_model_channels(config, ("T1", "T9")) == ["T9"]


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift ARGS`` in this process (the console script's ``main``; a process each costs half a second)."""
    return harness_run_cli(*args, cwd=REPO)


def test_check_config_accepts_the_shipped_example_and_warns_about_missing_channels(tmp_path: Path) -> None:
    shipped = run_cli("check-config", str(REPO / "config" / "sim.toml"))
    assert shipped.returncode == 0, shipped.stderr
    assert "ok" in shipped.stdout
    only_t1 = write(tmp_path, '[[sensors]]\nname = "T1"\nkind = "simulated"\n')
    result = run_cli("check-config", str(only_t1))
    assert result.returncode == 0, result.stderr
    needed = set(load_model(DEFAULT_MODEL_PATH).channels) - {"T1"}  # the shipped model's other channels
    assert needed and "warning" in result.stderr and all(c in result.stderr for c in needed), (needed, result.stderr)


def test_check_config_fails_naming_file_and_field(tmp_path: Path) -> None:
    bad = write(tmp_path, '[[sensors]]\nname = "T1"\nkind = "simulated"\n[[sensors]]\nname = "T2"\nkind = "simulated"\n'
                          "interval_s = \"fast\"\n")
    result = run_cli("check-config", str(bad))
    assert result.returncode != 0
    assert f"{bad}:7: sensors[1] (T2).interval_s:" in result.stderr


LOCATED = """\
cell = "lab1"
[[hubs]]
name = "adam"
timeout_s = "1.0"
[[sensors]]
name = "T1"
kind = "modbus"
hub = "adam"
address = 0
[[sensors]]
name = "T2"
kind = "modbus"
hub = "adam"
address = 1
swap = "word"
[[sensors]]
name = "T3"
kind = "modbus"
hub = "adam"
address = 2
scale = "0.1"
[actuator]
v_min = 5.0
v_max = 1.0
"""


def test_problems_name_the_sensor_and_the_line(tmp_path: Path) -> None:
    path = write(tmp_path, LOCATED)
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    lines = str(caught.value).splitlines()
    assert f"{path}:21: sensors[2] (T3).scale: Input should be a valid number" in "\n".join(lines)  # the key's line
    assert any(line.startswith(f"{path}:10: sensors[1] (T2): ") and "swap" in line for line in lines)  # the table's
    assert any(line.startswith(f"{path}:4: hubs[0] (adam).timeout_s: ") for line in lines)
    assert any(line.startswith(f"{path}:22: actuator: ") and "v_min (5.0)" in line for line in lines)
    assert len(lines) == 4, lines


@pytest.mark.parametrize(
    ("text", "field"),
    [
        ('[actuator]\nv_max = "10"', "actuator.v_max"),
        ('[[sensors]]\nname = "T1"\nkind = "simulated"\ninterval_s = "0.5"', "sensors[0] (T1).interval_s"),
        ('[[sensors]]\nname = "T1"\nkind = "modbus"\nhub = "a"\naddress = 0\nscale = "0.1"\n[[hubs]]\nname = "a"',
         "sensors[0] (T1).scale"),
        ('[[sensors]]\nname = "T1"\nkind = "modbus"\nhub = "a"\naddress = "0"\n[[hubs]]\nname = "a"',
         "sensors[0] (T1).address"),
        ('[[sensors]]\nname = "T1"\nkind = "modbus"\nhub = "a"\naddress = 0\n[[hubs]]\nname = "a"\nretries = "2"',
         "hubs[0] (a).retries"),
        ('[[sensors]]\nname = "x"\nrole = "position"\nkind = "serial_line"\nport = "loop://"\nbaudrate = "9600"',
         "sensors[0] (x).baudrate"),
        ('[[sensors]]\nname = "x"\nrole = "position"\nkind = "serial_line"\nport = "loop://"\noffset = "1"',
         "sensors[0] (x).offset"),
        ('[simulation]\nspeed = "2"', "simulation.speed"),
        ('[simulation]\nseed = "3"', "simulation.seed"),
        ('[[sensors]]\nname = "T1"\nkind = "simulated"\nmax_age_s = true', "sensors[0] (T1).max_age_s"),
    ],
)
def test_strings_are_refused_for_numbers(tmp_path: Path, text: str, field: str) -> None:
    problems = problems_of(write(tmp_path, text))
    assert any(p.startswith(f"{field}: Input should be a valid") for p in problems), problems


def test_numbers_may_be_written_as_ints_and_paths_as_strings(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, '[actuator]\nv_max = 10\n[model]\npath = "m.json"\n'
                                         '[zenoh]\nconfig_file = "z.json5"\n'))
    assert config.actuator.v_max == 10.0 and isinstance(config.actuator.v_max, float)
    assert config.model.path == tmp_path / "m.json" and config.zenoh.config_file == tmp_path / "z.json5"


IFM = '[[sensors]]\nname = "ifm"\nrole = "position"\nkind = "serial_line"\nport = "loop://"\n'


@pytest.mark.parametrize(
    ("keys", "expected"),
    [
        ("valid_min = 10.0\nvalid_max = 10.0", "sensors[0] (ifm).valid_max: Value error, valid_max = 10 is not above "
                                               "valid_min = 10"),
        ("valid_min = 20.0\nvalid_max = -5.0", "sensors[0] (ifm).valid_max: Value error, valid_max = -5 is not above"),
        ("valid_min = nan", "sensors[0] (ifm).valid_min: Input should be a finite number"),
        ("valid_max = inf", "sensors[0] (ifm).valid_max: Input should be a finite number"),
        ('valid_max = "500"', "sensors[0] (ifm).valid_max: Input should be a valid number"),
        # the default valid_max of the workspace [0, 500] is 550: a valid_min above it believes nothing
        ("valid_min = 600.0", "sensors[0] (ifm).valid_min: the valid range would be [600, 550]"),
        ("frozen_after_s = -1.0", "sensors[0] (ifm).frozen_after_s: Input should be greater than or equal to 0"),
        ("frozen_after_s = inf", "sensors[0] (ifm).frozen_after_s: Input should be a finite number"),
        ("interval_s = 0.5\nfrozen_after_s = 0.2", "sensors[0] (ifm).frozen_after_s: Value error, frozen_after_s = "
                                                    "0.2 s is below interval_s = 0.5 s"),
    ],
    ids=["min=max", "min>max", "min=nan", "max=inf", "max-string", "min-above-default-max", "frozen<0",
         "frozen=inf", "frozen<interval"],
)
def test_a_sensors_valid_range_and_frozen_after_s_are_checked_naming_the_key(tmp_path: Path, keys: str,
                                                                            expected: str) -> None:
    problems = problems_of(write(tmp_path, IFM + keys + "\n"))
    assert any(p.startswith(expected) for p in problems), problems


def test_a_sensors_valid_range_and_frozen_after_s_are_read_with_their_defaults(tmp_path: Path) -> None:
    config = load_config(write(tmp_path, IFM + "valid_min = -5\nvalid_max = 505.5\nfrozen_after_s = 0\n"
                                          '[[sensors]]\nname = "T1"\nkind = "modbus"\nhub = "a"\naddress = 0\n'
                                          '[[hubs]]\nname = "a"\nhost = "127.0.0.1"\n'))
    ifm, t1 = config.sensors
    assert (ifm.valid_min, ifm.valid_max, ifm.frozen_after_s) == (-5.0, 505.5, 0.0)  # 0: off, as the operator says
    assert (t1.valid_min, t1.valid_max, t1.frozen_after_s) == (None, None, 0.0)  # temperatures: not frozen by default
    default = load_config(write(tmp_path, IFM))
    assert default.sensors[0].frozen_after_s == POSITION_FROZEN_AFTER_S
