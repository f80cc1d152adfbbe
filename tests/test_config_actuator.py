"""``[actuator]`` and ``[procedure]``: the contract's examples, the default kind, two-pass validation
(core keys here, device keys by the kind's plugin), errors naming ``actuator.<key>``, and random
tables (hypothesis) that are either accepted as written or refused naming the key."""

from __future__ import annotations

import math
import re
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import pytest
from helpers.budget import examples
from helpers.daemon_harness import REPO
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.assembly import build_drivers
from nanodrift.calibration.plans import CALIBRATION_POINTS_UM, PAPER_TIMING
from nanodrift.config import ConfigError, load_config, parse_config
from nanodrift.drivers.modbus.actuator import ModbusActuator
from nanodrift.drivers.modbus.config import ModbusActuatorConfig
from nanodrift.drivers.serial_line.actuator import SerialLineActuator
from nanodrift.drivers.serial_line.config import SerialLineActuatorConfig
from nanodrift.drivers.simulated.config import SimulatedActuatorConfig

HARDWARE = """
[[hubs]]
name = "adam"
host = "127.0.0.1"
[[sensors]]
name = "T1"
kind = "modbus"
hub = "adam"
address = 0
input_type = "input"
[[sensors]]
name = "interferometer"
role = "position"
kind = "serial_line"
port = "/dev/ttyUSB0"
query = "POS?\\r"
"""

MODBUS = """
[actuator]
kind = "modbus"
max_slew_um_per_s = 0.0
safe_voltage_v = nan
hub = "adam"
device_id = 1
address = 10
data_type = "int16"
swap = "none"
scale = 0.001
offset = 0.0
verify = true
"""

SERIAL = """
[actuator]
kind = "serial_line"
port = "/dev/ttyUSB1"
baudrate = 115200
command = "SVA 1 {voltage_v:.4f}\\n"
readback = "SVA? 1\\n"
readback_pattern = '=(?P<value>[-+0-9.eE]+)'
readback_tolerance = 0.001
"""


def parsed(text: str) -> Any:
    return parse_config(tomllib.loads(text), source="test.toml")


def problems(text: str) -> list[str]:
    with pytest.raises(ConfigError) as caught:
        parsed(text)
    return caught.value.problems


def test_the_contracts_examples_are_accepted() -> None:
    modbus = parsed(HARDWARE + MODBUS)
    assert modbus.actuator.kind == "modbus" and math.isnan(modbus.actuator.safe_voltage_v)
    assert modbus.actuator.options == ModbusActuatorConfig(hub="adam", address=10, scale=0.001)
    serial = parsed(HARDWARE + SERIAL)
    options = serial.actuator.options
    assert isinstance(options, SerialLineActuatorConfig)
    assert options.command == "SVA 1 {voltage_v:.4f}\n" and options.readback == "SVA? 1\n"
    assert options.expected_field == "voltage_v"


def test_the_default_kind_moves_a_simulated_stage_and_publishes_on_hardware() -> None:
    assert parsed("[simulation]\nseed = 1\n").actuator.kind == "simulated"
    assert isinstance(parsed("[simulation]\nseed = 1\n").actuator.options, SimulatedActuatorConfig)
    hardware = parsed(HARDWARE)
    assert hardware.actuator.kind == "zenoh" and hardware.actuator.options is None
    assert parsed("").actuator.kind == "zenoh"  # monitoring only: nothing to move, nothing simulated
    assert parsed("[actuator]\nvolts_per_um = 0.01\n").actuator.kind == "zenoh"



def test_a_simulated_cell_loads_no_hardware_plugin() -> None:
    """Its [actuator] defaults to the cell's own plugin without loading every installed one to find it: each
    hardware plugin cost a daemon start (the suite starts hundreds) its imports, 0.16 s of CPU together."""
    script = ("import sys; from nanodrift.config import load_config; from nanodrift.assembly import build_drivers\n"
              "config = load_config('config/sim.toml'); build_drivers(config)\n"
              "print(config.actuator.kind, *sorted(m for m in sys.modules if m.startswith('nanodrift.drivers.')))")
    shown = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=REPO, check=True).stdout
    kind, *modules = shown.split()
    assert kind == "simulated"
    assert not [m for m in modules if m.split(".")[2] in {"modbus", "pi_gcs", "serial_line", "dcon", "attocube_ids"}]

@pytest.mark.parametrize(
    ("text", "expected"),
    [
        (HARDWARE + MODBUS + "adress = 3\n", "actuator.adress: unknown key (typo?)"),
        (HARDWARE + SERIAL + "readbak = 'x'\n", "actuator.readbak: unknown key (typo?)"),
        (HARDWARE + '[actuator]\nhub = "adam"\n', "actuator.hub: unknown key (typo?); kind = 'zenoh' takes no device"),
        ("[simulation]\n[actuator]\nkind = 'simulated'\nport = 'x'\n", "actuator.port: unknown key (typo?)"),
        (HARDWARE + "[actuator]\nkind = 'dac9000'\n", "actuator.kind: unknown actuator kind 'dac9000'; kinds: zenoh, "
                                                     "modbus, pi_gcs, serial_line, simulated"),
        (HARDWARE + "[actuator]\nkind = 3\n", "actuator.kind: Input should be a valid string"),
        (HARDWARE + "[actuator]\nkind = 'simulated'\n", "actuator.kind: 'simulated' cannot drive this cell: its "
                                                       "sensors are real hardware"),
        ("[simulation]\n[actuator]\nkind = 'zenoh'\n", "actuator.kind: 'zenoh' would leave the simulated stage"),
        (HARDWARE + MODBUS.replace('hub = "adam"', 'hub = "adma"'), "actuator.hub: no [[hubs]] named 'adma'"),
        (HARDWARE + MODBUS.replace("address = 10", ""), "actuator.address: Field required"),
        (HARDWARE + MODBUS.replace("scale = 0.001", "scale = 0.0"), "scale (volts per count) must not be 0"),
        (HARDWARE + MODBUS.replace('"int16"', '"uint16"'),
         "actuator: v_min = -2 V cannot be written as uint16 with scale 0.001"),
        (HARDWARE + MODBUS.replace("scale = 0.001", "scale = 10.0"),  # 4.73 V was written as round(0.473) = 0
         "actuator: scale = 10 V per count with data_type int16 and offset 0: one output step is 10 V, coarser "
         "than 0.14 V (1% of [v_min, v_max] = [-2, 12] V) and 0.02 V (1 um of travel at volts_per_um = 0.02)"),
        (HARDWARE + MODBUS.replace("scale = 0.001", "scale = 0.05"),
         "actuator: scale = 0.05 V per count with data_type int16 and offset 0: one output step is 0.05 V, coarser "
         "than 0.02 V (1 um of travel at volts_per_um = 0.02)"),
        (HARDWARE + MODBUS.replace("scale = 0.001", "scale = 0.001\nvolts_per_um = 0.0005"),
         "one output step is 0.001 V, coarser than 0.0005 V (1 um of travel at volts_per_um = 0.0005)"),
        (HARDWARE + MODBUS.replace('"int16"', '"float32"').replace("offset = 0.0", "offset = 1e9"),
         "actuator: scale = 0.001 V per count with data_type float32 and offset 1e+09: one output step is 65.54 V"),
        (HARDWARE + MODBUS.replace("max_slew_um_per_s = 0.0", "max_slew_um_per_s = 1e-300"),
         "actuator.max_slew_um_per_s: Value error, must be 0 (off) or at least 0.01 um/s"),
        (HARDWARE + MODBUS.replace("nan", "inf"), "actuator.safe_voltage_v: Value error, must be a finite voltage"),
        (HARDWARE + MODBUS.replace("nan", "20.0"), "safe_voltage_v (20) must be inside [v_min, v_max] = [-2, 12]"),
        (HARDWARE + MODBUS + "position_proof_tolerance_um = 0.0\n",
         "actuator.position_proof_tolerance_um: Value error, must be a positive, finite distance in um, or nan"),
        (HARDWARE + MODBUS + "position_proof_tolerance_um = inf\n",
         "actuator.position_proof_tolerance_um: Value error, must be a positive, finite distance in um, or nan"),
        (HARDWARE + MODBUS + "v_max = nan\n", "actuator.v_max: Input should be a finite number"),
        (HARDWARE + MODBUS.replace("max_slew_um_per_s = 0.0", "max_slew_um_per_s = -1.0"),
         "actuator.max_slew_um_per_s: Input should be greater than or equal to 0"),
        (HARDWARE + SERIAL.replace("{voltage_v:.4f}", "{volts}"), "actuator.command: Value error, unknown field(s) "
                                                                  "{volts}; fields: voltage_v, q_um, x_um"),
        (HARDWARE + SERIAL.replace("'=(?P<value>[-+0-9.eE]+)'", "'=(\\d+)'"),
         "actuator.readback_pattern: Value error, needs a named group 'value'"),
        ("[actuator]\n" + "[procedure]\npoints = [0, 30, 600]\n", "procedure.points: 600 um outside the workspace"),
        ("[procedure]\npoints = [0, 30]\nstep_um = 10\n", "procedure: Value error, give points, or step_um and max_um"),
        ("[procedure]\nhold_s = 2.0\n", "procedure: Value error, average_s (5) must not exceed hold_s (2)"),
        ("[procedure]\nrise = 1\n", "procedure.rise: unknown key"),
        ("[procedure]\ncycles = 0\n", "procedure.cycles: Input should be greater than or equal to 1"),
    ],
)
def test_bad_actuator_and_procedure_tables_name_the_field(text: str, expected: str) -> None:
    found = problems(text)
    assert any(p.startswith(expected) or expected in p for p in found), found


def test_a_hub_only_the_actuator_uses_is_a_hub_in_use() -> None:
    text = ('[[hubs]]\nname = "ao"\nhost = "10.0.0.9"\nport = 5020\n'
            '[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "serial_line"\nport = "/dev/ttyUSB0"\n'
            '[actuator]\nkind = "modbus"\nhub = "ao"\naddress = 0\nscale = 0.001\n')
    config = parsed(text)
    assert [h.name for h in config.hubs] == ["ao"] and config.hubs[0].port == 5020
    assert any(p.startswith("hubs[0] (ao): no sensor uses this hub") for p in problems(text.split("[actuator]")[0]))
    bad_hub = text.replace("port = 5020", "port = 5020\nbaudrat = 9600")
    assert any(p.startswith("hubs[0] (ao).baudrat: unknown key") for p in problems(bad_hub))


def test_procedure_defaults_are_the_papers_and_a_faster_schedule_is_one_table() -> None:
    default = parsed("").procedure
    assert default.calibration_points == CALIBRATION_POINTS_UM and default.cycles == 24
    assert default.timing == PAPER_TIMING
    fast = parsed("[procedure]\nstep_um = 60\nmax_um = 480\ncycles = 4\nrise_s = 0.5\nhold_s = 3\naverage_s = 1\n"
                  "follow_tolerance = 0.2\n").procedure
    assert fast.calibration_points == (0, 60, 120, 180, 240, 300, 360, 420, 480)
    assert (fast.timing.ramp_s, fast.timing.hold_s, fast.timing.window_s, fast.timing.step_s) == (0.5, 3, 1, 3.5)
    assert parsed("[procedure]\npoints = [0, 100, 50]\n").procedure.calibration_points == (0, 100, 50)


def test_two_configs_that_say_nan_are_equal(tmp_path: Path) -> None:
    path = tmp_path / "a.toml"
    path.write_text(HARDWARE + MODBUS + "position_proof_tolerance_um = nan\n")
    assert load_config(path).actuator == load_config(path).actuator  # a reload sees no change


def test_a_position_sensor_proves_nothing_until_the_operator_states_its_tolerance() -> None:
    assert math.isnan(parsed(HARDWARE + MODBUS).actuator.position_proof_tolerance_um)
    stated = parsed(HARDWARE + MODBUS + "position_proof_tolerance_um = 5.0\n").actuator
    assert stated.position_proof_tolerance_um == 5.0


# --- random [actuator] tables --------------------------------------------------------------------

# volts_per_um from 0.01: one count of the modbus scales below (up to 10 mV) must be at most 1 um of travel;
# a slew limit is 0 (off) or at least 0.01 um/s (the rest is refused, see tests/test_config_bounds.py)
CORE = {"volts_per_um": st.floats(0.01, 0.1), "offset_v": st.floats(-1, 1),
        "max_slew_um_per_s": st.one_of(st.just(0.0), st.floats(0.01, 1e3)),
        "safe_voltage_v": st.sampled_from([math.nan, 0.0, 1.5])}
MODBUS_KEYS = {"device_id": st.integers(0, 255), "address": st.integers(0, 65534),
               "data_type": st.sampled_from(["int16", "int32", "float32"]), "scale": st.floats(5e-4, 1e-2),
               "offset": st.floats(-0.5, 0.5), "verify": st.booleans()}
SERIAL_KEYS = {"baudrate": st.sampled_from([9600, 115200]), "readback": st.sampled_from(["", "SVA? 1\n"]),
               "readback_tolerance": st.floats(0, 0.1), "timeout_s": st.floats(0.05, 5),
               "command": st.sampled_from(["SVA 1 {voltage_v:.4f}\n", "MOV 1 {q_um:.3f}\r\n", "V{voltage_v:+08.3f}\n"])}
TYPO = st.text("abcdefghijklmnopqrstuvwxyz_", min_size=3, max_size=12).filter(
    lambda k: k not in {*CORE, *MODBUS_KEYS, *SERIAL_KEYS} and k not in
    {*ModbusActuatorConfig.model_fields, *SerialLineActuatorConfig.model_fields, "kind", "v_min", "v_max",
     "x_min_um", "x_max_um"})


@st.composite
def actuator_tables(draw: st.DrawFn) -> tuple[dict[str, Any], list[str]]:
    kind = draw(st.sampled_from(["zenoh", "modbus", "serial_line"]))
    table: dict[str, Any] = {"kind": kind}
    for key, values in CORE.items():
        if draw(st.booleans()):
            table[key] = draw(values)
    device = {"modbus": MODBUS_KEYS, "serial_line": SERIAL_KEYS, "zenoh": {}}[kind]
    if kind == "modbus":
        table.update(hub="adam", address=draw(MODBUS_KEYS["address"]), scale=draw(MODBUS_KEYS["scale"]))
    if kind == "serial_line":
        table["port"] = draw(st.sampled_from(["/dev/ttyUSB1", "socket://10.0.0.5:4001"]))
    for key, values in device.items():
        if draw(st.booleans()):
            table[key] = draw(values)
    typos = draw(st.lists(TYPO, max_size=2, unique=True))
    for typo in typos:
        table[typo] = draw(st.one_of(st.integers(), st.text(max_size=5), st.floats(allow_nan=False)))
    return table, typos


@settings(max_examples=examples(150), deadline=None)
@given(actuator_tables())
def test_random_actuator_tables_are_taken_as_written_or_refused_naming_the_key(case: tuple[dict, list[str]]) -> None:
    table, typos = case
    document = tomllib.loads(HARDWARE)
    document["actuator"] = table
    try:
        config = parse_config(document, source="random.toml")
    except ConfigError as error:
        assert typos, error.problems  # nothing else in these tables is wrong
        for typo in typos:
            assert any(p.startswith(f"actuator.{typo}: unknown key") for p in error.problems), error.problems
        assert all(p.startswith("actuator.") for p in error.problems), error.problems
        return
    assert not typos
    actuator = config.actuator
    assert actuator.kind == table["kind"]
    for key, value in table.items():
        held = getattr(actuator, key) if key in type(actuator).model_fields else getattr(actuator.options, key)
        assert held == value or (isinstance(value, float) and math.isnan(value) and math.isnan(held)), key
    if table["kind"] == "modbus":
        assert config.hubs[0].name == "adam"


# --- the commented output paths of config/lab.toml are valid as written --------------------------

LAB = Path(__file__).resolve().parents[1] / "config" / "lab.toml"


def lab_with(path_name: str) -> str:
    """config/lab.toml with the output path ``path_name`` uncommented (and kind = "zenoh" removed)."""
    out: list[str] = []
    active = False
    for line in LAB.read_text().splitlines():
        if line.startswith("# --- Output path:") or line.startswith("# The analog output module of"):
            active = path_name in line
        elif active and (re.match(r"# [a-z_]+ = ", line) or line == "# [[hubs]]"):
            line = line[2:]
        elif not line.startswith("#"):
            active = False
        if line.startswith('kind = "zenoh"'):
            continue
        out.append(line)
    return "\n".join(out) + "\n"


def test_the_lab_examples_output_paths_are_valid_configs() -> None:
    modbus = parse_config(tomllib.loads(lab_with("modbus")), source="lab.toml (modbus)")
    assert modbus.actuator.kind == "modbus" and modbus.actuator.options.hub == "ao"
    assert [h.name for h in modbus.hubs] == ["adam", "ao"] and modbus.hubs[1].host == "192.168.1.21"
    assert isinstance(build_drivers(modbus).actuators["x"], ModbusActuator)
    serial = parse_config(tomllib.loads(lab_with("serial_line")), source="lab.toml (serial_line)")
    options = serial.actuator.options
    assert isinstance(options, SerialLineActuatorConfig)
    assert (options.command, options.readback, options.error_query) == ("SVA 1 {voltage_v:.4f}\n", "SVA? 1\n",
                                                                        "ERR?\n")
    assert isinstance(build_drivers(serial).actuators["x"], SerialLineActuator)
    shipped = parse_config(tomllib.loads(LAB.read_text()), source="lab.toml")
    assert shipped.actuator.kind == "zenoh" and shipped.procedure.timing == PAPER_TIMING
    assert shipped.procedure.calibration_points == CALIBRATION_POINTS_UM
