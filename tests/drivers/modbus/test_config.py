"""The Modbus channel keys: defaults, strictness, and messages that name the problem."""

from __future__ import annotations

import pytest
from pydantic import ValidationError

from drivers.base import DriverContext
from drivers.modbus.config import ModbusHubConfig, ModbusSensorConfig
from drivers.modbus.group import ModbusBlockGroup, plan_blocks
from drivers.modbus.plugin import PLUGIN


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
