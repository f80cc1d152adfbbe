"""Registers -> value for every data type and swap (Home Assistant semantics), cross-checked
against pymodbus' own converter and against hand-written wire bytes."""

from __future__ import annotations

import math

import pytest
from pydantic import ValidationError
from pymodbus.client.mixin import ModbusClientMixin

from nanodrift.drivers.modbus.codec import decode, encode, register_count
from nanodrift.drivers.modbus.config import ModbusSensorConfig

DT = ModbusClientMixin.DATATYPE
PYMODBUS_TYPES = {"int16": DT.INT16, "uint16": DT.UINT16, "int32": DT.INT32, "uint32": DT.UINT32,
                  "float32": DT.FLOAT32}
SAMPLES = {"int16": [-32768, -215, 0, 1, 32767], "uint16": [0, 215, 0x8000, 65535],
           "int32": [-(2**31), -123456, 0, 2**31 - 1], "uint32": [0, 123456, 2**32 - 1],
           "float32": [-273.15, 0.0, 21.5, 3.0e38]}


def test_known_wire_layouts() -> None:
    # float32 21.5 is 0x41AC0000: registers [0x41AC, 0x0000] big-endian
    assert decode([0x41AC, 0x0000], "float32") == 21.5
    assert decode([0x0000, 0x41AC], "float32", "word") == 21.5  # word-swapped device
    assert decode([0xAC41, 0x0000], "float32", "byte") == 21.5  # bytes swapped inside registers
    assert decode([0x0000, 0xAC41], "float32", "word_byte") == 21.5  # little-endian device
    assert decode([0x8000], "int16") == -32768
    assert decode([0x0080], "int16", "byte") == -32768
    assert decode([0x0001, 0x0002], "uint32") == 0x00010002
    assert decode([0x0001, 0x0002], "uint32", "word") == 0x00020001
    assert decode([0x0102, 0x0304], "uint32", "byte") == 0x02010403
    assert decode([0x0102, 0x0304], "uint32", "word_byte") == 0x04030201


@pytest.mark.parametrize("data_type", list(SAMPLES))
def test_matches_pymodbus_converter(data_type: str) -> None:
    for value in SAMPLES[data_type]:
        regs = ModbusClientMixin.convert_to_registers(value, PYMODBUS_TYPES[data_type])
        assert decode(regs, data_type) == pytest.approx(value, rel=1e-7)
        assert decode(regs, data_type) == ModbusClientMixin.convert_from_registers(regs, PYMODBUS_TYPES[data_type])
        if register_count(data_type) == 2:
            little = ModbusClientMixin.convert_to_registers(value, PYMODBUS_TYPES[data_type], word_order="little")
            assert decode(little, data_type, "word") == pytest.approx(value, rel=1e-7)


@pytest.mark.parametrize("data_type", list(SAMPLES))
@pytest.mark.parametrize("swap", ["none", "byte", "word", "word_byte"])
def test_encode_decode_round_trip(data_type: str, swap: str) -> None:
    if swap in ("word", "word_byte") and register_count(data_type) == 1:
        with pytest.raises(ValidationError, match="needs a 32-bit data_type"):
            ModbusSensorConfig(name="T1", hub="h", address=0, data_type=data_type, swap=swap)
        return
    for value in SAMPLES[data_type]:
        regs = encode(value, data_type, swap)
        assert len(regs) == register_count(data_type)
        assert all(0 <= r <= 0xFFFF for r in regs)
        assert decode(regs, data_type, swap) == pytest.approx(value, rel=1e-7)


def test_nan_float_is_decoded_not_hidden() -> None:
    assert math.isnan(decode([0x7FC0, 0x0000], "float32"))


def test_wrong_register_count_is_an_error() -> None:
    with pytest.raises(ValueError, match="float32 needs 2 register"):
        decode([1], "float32")
