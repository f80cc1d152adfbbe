"""The Modbus channel keys: defaults, strictness, and messages that name the problem; the analog output's
data_type, scale and offset represent every voltage of [v_min, v_max] finely enough (issue 16)."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.budget import examples
from hypothesis import event, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from nanodrift.drivers.base import MAX_OUTPUT_STEP_FRACTION, MAX_OUTPUT_STEP_UM, DriverContext
from nanodrift.drivers.modbus.codec import DATA_TYPES, decode, encode, raw_for
from nanodrift.drivers.modbus.config import ModbusActuatorConfig, ModbusHubConfig, ModbusSensorConfig
from nanodrift.drivers.modbus.group import ModbusBlockGroup, plan_blocks
from nanodrift.drivers.modbus.plugin import PLUGIN


def channel(name: str, address: int, **kw: object) -> ModbusSensorConfig:
    return ModbusSensorConfig(name=name, hub=kw.pop("hub", "adam"), address=address, **kw)


def test_contract_example_is_accepted() -> None:
    c = ModbusSensorConfig.model_validate({
        "name": "T1", "role": "temperature", "kind": "modbus", "hub": "adam", "device_id": 1, "address": 0,
        "input_type": "input", "data_type": "int16", "swap": "none", "scale": 0.1, "offset": 0.0,
        "nan_value": -32768, "interval_s": 0.5, "max_age_s": 5.0})
    assert (c.register_count, c.end, c.value_unit) == (1, 1, "degC")


def test_unknown_key_is_refused() -> None:
    with pytest.raises(ValidationError, match="scael"):
        ModbusSensorConfig.model_validate({"name": "T1", "kind": "modbus", "hub": "a", "address": 0, "scael": 0.1})


def test_nan_value_outside_type_range_is_explained() -> None:
    with pytest.raises(ValidationError, match=r"nan_value 32768 is outside int16's range -32768\.\.32767"):
        channel("T1", 0, nan_value=0x8000)
    assert channel("T1", 0, data_type="uint16", nan_value="0x8000").nan_value == 0x8000


def test_word_swap_needs_two_registers() -> None:
    with pytest.raises(ValidationError, match="needs a 32-bit data_type"):
        channel("T1", 0, swap="word")


def test_contiguous_channels_merge_and_devices_do_not() -> None:
    configs = [channel(f"T{i}", i) for i in range(8)]
    configs += [channel("F0", 20, data_type="float32"), channel("F1", 22, data_type="float32")]
    configs += [channel("D2", 0, device_id=2), channel("H0", 0, input_type="input")]
    configs += [channel("FAR", 60)]
    blocks = {(b.device_id, b.input_type, b.start, b.count): [c.name for c in b.channels]
              for b in plan_blocks(configs)}
    assert blocks == {
        (1, "holding", 0, 8): [f"T{i}" for i in range(8)],
        (1, "holding", 20, 4): ["F0", "F1"],
        (1, "holding", 60, 1): ["FAR"],
        (2, "holding", 0, 1): ["D2"],
        (1, "input", 0, 1): ["H0"],
    }


def test_small_gaps_are_bridged_up_to_125_registers() -> None:
    blocks = plan_blocks([channel("A", 0), channel("B", 5), channel("C", 11)])
    assert [(b.start, b.count) for b in blocks] == [(0, 6), (11, 1)]  # gap 4 bridged, gap 5 not
    wide = plan_blocks([channel(f"C{i}", 4 * i) for i in range(40)])
    assert all(b.count <= 125 for b in wide) and len(wide) == 2


def test_plugin_needs_the_hub_and_shares_one_hub_per_name() -> None:
    context = DriverContext(hubs={"adam": ModbusHubConfig(name="adam", port=1502)})
    groups = PLUGIN.create([channel("T1", 0), channel("T2", 1), channel("T3", 40)], context)
    assert len(groups) == 2 and all(isinstance(g, ModbusBlockGroup) for g in groups)
    assert groups[0].hub is groups[1].hub
    assert groups[0].names == ("T1", "T2") and groups[0].roles == {"T1": "temperature", "T2": "temperature"}
    with pytest.raises(ValueError, match="sensor 'X': no \\[\\[hubs\\]\\] named 'moxa' \\(hubs: adam\\)"):
        PLUGIN.create([channel("X", 0, hub="moxa")], context)


def test_serial_hub_needs_a_device_name() -> None:
    context = DriverContext(hubs={"bus": ModbusHubConfig(name="bus", type="serial")})
    with pytest.raises(ValueError, match="hub 'bus': type = 'serial' needs port = the serial device"):
        PLUGIN.create([channel("T1", 0, hub="bus")], context)


# --- the analog output: every voltage of [v_min, v_max] written as itself, within one count (issue 16) ----

SWAPS_16 = ["none", "byte"]
SWAPS_32 = ["none", "byte", "word", "word_byte"]


@st.composite
def outputs(draw: st.DrawFn) -> tuple[ModbusActuatorConfig, float, float, float]:
    """An output channel and ``(v_min, v_max, volts_per_um)``: half drawn widely (mostly refused), half
    near what real modules are (a span of ~100 to ~10^7 counts, mostly accepted)."""
    data_type = draw(st.sampled_from(list(DATA_TYPES)))
    swap = draw(st.sampled_from(SWAPS_32 if DATA_TYPES[data_type].registers == 2 else SWAPS_16))
    v_min = draw(st.floats(-20, 20))
    v_max = v_min + draw(st.floats(0.05, 40))
    volts_per_um = draw(st.floats(1e-4, 1)) * draw(st.sampled_from([1, -1]))
    sign = draw(st.sampled_from([1, -1]))
    if draw(st.booleans()):
        scale = sign * 10 ** draw(st.floats(-9, 2))
        offset = draw(st.one_of(st.floats(-30, 30), st.floats(-1e10, 1e10)))
    else:
        scale = sign * (v_max - v_min) / 10 ** draw(st.floats(1.5, 7))
        offset = draw(st.floats(v_min - 1, v_max + 1))
    config = ModbusActuatorConfig(hub="ao", address=0, data_type=data_type, swap=swap, scale=scale, offset=offset)
    return config, v_min, v_max, volts_per_um


@settings(max_examples=examples(400), deadline=None)
@given(outputs(), st.lists(st.floats(0, 1), max_size=20))
def test_every_voltage_an_accepted_output_allows_is_written_within_one_count(
        case: tuple[ModbusActuatorConfig, float, float, float], fractions: list[float]) -> None:
    """For any data_type, scale and offset the config accepts, each voltage of ``[v_min, v_max]`` encodes
    to a register value inside the type's range and decodes to within one count of itself, and that
    count is as fine as the config promises (1 % of the range, 1 um of travel)."""
    config, v_min, v_max, volts_per_um = case
    problem = config.voltage_range_problem(v_min, v_max, volts_per_um)
    event("refused" if problem else "accepted")
    if problem is not None:
        assert problem.startswith(("v_min = ", "v_max = ", "scale = ")), problem  # names the key
        return
    spec = DATA_TYPES[config.data_type]
    promised_v = min(MAX_OUTPUT_STEP_FRACTION * (v_max - v_min), MAX_OUTPUT_STEP_UM * abs(volts_per_um))
    for voltage in [v_min, v_max, *(min(v_min + f * (v_max - v_min), v_max) for f in fractions)]:
        raw = raw_for(voltage, config.scale, config.offset, config.data_type, within=(v_min, v_max))
        assert spec.minimum <= raw <= spec.maximum, (voltage, raw)
        registers = encode(raw, config.data_type, config.swap)
        assert len(registers) == spec.registers and all(0 <= r <= 0xFFFF for r in registers)
        decoded = decode(registers, config.data_type, config.swap)
        back_v = decoded * config.scale + config.offset
        count_v = abs(config.scale) * (float(np.spacing(np.float32(abs(decoded)))) if spec.is_float else 1.0)
        rounding_v = 8 * np.finfo(float).eps * (abs(voltage) + abs(config.offset) + abs(decoded * config.scale))
        assert abs(back_v - voltage) <= count_v + rounding_v, (voltage, back_v, count_v)
        assert abs(back_v - voltage) <= promised_v + rounding_v, (voltage, back_v, promised_v)


@pytest.mark.parametrize(
    ("data_type", "scale", "offset", "v_min", "v_max"),
    [("uint16", 10 / 4095, 0.0, 0.0, 10.0),      # a 12-bit 0-10 V module
     ("int16", 10 / 32767, 0.0, -10.0, 10.0),    # a 16-bit +-10 V module
     ("int16", 0.001, 0.0, -2.0, 12.0),          # config/lab.toml's example: mV in an int16
     ("float32", 1.0, 0.0, -2.0, 12.0),          # volts as a float
     ("uint32", 1e-6, -5.0, -2.0, 12.0)],        # uV above an offset
    ids=["12bit-0-10V", "16bit-10V", "lab-mV", "float-V", "uV-offset"],
)
def test_real_output_modules_are_accepted(data_type: str, scale: float, offset: float, v_min: float,
                                          v_max: float) -> None:
    config = ModbusActuatorConfig(hub="ao", address=0, data_type=data_type, scale=scale, offset=offset)
    assert config.voltage_range_problem(v_min, v_max, 0.02) is None


def test_a_coarse_scale_is_refused_naming_scale_and_the_step() -> None:
    """``scale = 10.0``: a 4.73 V command was written as round(0.473) = 0 counts, 0 V, with the status ok."""
    config = ModbusActuatorConfig(hub="ao", address=0, scale=10.0)
    assert raw_for(4.73, 10.0, 0.0, "int16") == 0  # what the daemon would have written
    problem = config.voltage_range_problem(-2.0, 12.0, 0.02)
    assert problem is not None and problem.startswith("scale = 10 V per count"), problem
    assert "one output step is 10 V" in problem, problem
