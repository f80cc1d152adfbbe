"""Registers -> number, with Home Assistant's modbus semantics (pure; no I/O).

A value occupies 1 (16-bit types) or 2 (32-bit types) registers, each register big-endian on the
wire. ``swap`` undoes a device's byte/word order before the big-endian struct decode, exactly as
Home Assistant does it:

- ``byte``: swap the two bytes inside every register ([12][34] -> [21][43]);
- ``word``: reverse the register order ([12][34] -> [34][12]);
- ``word_byte``: both.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np

DataTypeName = Literal["int16", "uint16", "int32", "uint32", "float32"]
SwapName = Literal["none", "byte", "word", "word_byte"]


@dataclass(frozen=True, slots=True)
class DataTypeSpec:
    registers: int
    struct_format: str  # big-endian struct code
    is_float: bool
    minimum: int | float
    maximum: int | float


DATA_TYPES: dict[str, DataTypeSpec] = {
    "int16": DataTypeSpec(1, ">h", False, -(2**15), 2**15 - 1),
    "uint16": DataTypeSpec(1, ">H", False, 0, 2**16 - 1),
    "int32": DataTypeSpec(2, ">i", False, -(2**31), 2**31 - 1),
    "uint32": DataTypeSpec(2, ">I", False, 0, 2**32 - 1),
    "float32": DataTypeSpec(2, ">f", True, -3.4028234663852886e38, 3.4028234663852886e38),
}


def register_count(data_type: str) -> int:
    """How many 16-bit registers one value of ``data_type`` occupies."""
    return DATA_TYPES[data_type].registers


def _swapped(registers: Sequence[int], swap: str) -> list[int]:
    regs = [int(r) & 0xFFFF for r in registers]
    if swap in ("byte", "word_byte"):
        regs = [((r & 0xFF) << 8) | (r >> 8) for r in regs]
    if swap in ("word", "word_byte"):
        regs.reverse()
    return regs


def decode(registers: Sequence[int], data_type: str, swap: str = "none") -> int | float:
    """The raw value (before scale/offset) that ``registers`` hold."""
    spec = DATA_TYPES[data_type]
    if len(registers) != spec.registers:
        raise ValueError(f"{data_type} needs {spec.registers} register(s), got {len(registers)}")
    raw = b"".join(r.to_bytes(2, "big") for r in _swapped(registers, swap))
    value: int | float = struct.unpack(spec.struct_format, raw)[0]
    return value


def encode(value: int | float, data_type: str, swap: str = "none") -> list[int]:
    """The registers a device sends for ``value``: the inverse of :func:`decode` (tests, emulators)."""
    spec = DATA_TYPES[data_type]
    raw = struct.pack(spec.struct_format, value)
    regs = [int.from_bytes(raw[i : i + 2], "big") for i in range(0, len(raw), 2)]
    # every swap is its own inverse, so the same transformation maps back
    return _swapped(regs, swap)


def raw_for(value: float, scale: float, offset: float, data_type: str,
            within: tuple[float, float] | None = None) -> int | float:
    """The raw register value that scales back to ``value`` (``raw * scale + offset``), the inverse of a
    sensor's scaling: the nearest count for integer types, the nearest float32 for float32.

    ``within`` (the operator's ``[v_min, v_max]``): when the nearest raw value would scale back to a
    voltage outside it (``value`` within half a count of a limit), the neighbour on the inside is
    taken instead, so the output never exceeds a limit by a fraction of a count. ``ValueError`` when
    the value does not fit ``data_type``, or no raw value lies within the limits (nothing must then
    be written)."""
    spec = DATA_TYPES[data_type]
    exact = (value - offset) / scale
    if not math.isfinite(exact):
        raise ValueError(f"{value!r} has no raw value")
    raw: int | float = _float32(exact) if spec.is_float else round(exact)
    if within is not None:
        low, high = within
        slack = 0.0 if spec.is_float else _SLACK * abs(scale)
        if raw * scale + offset > high + slack:
            raw = _inward(raw, scale, spec.is_float, lower=True)
        elif raw * scale + offset < low - slack:
            raw = _inward(raw, scale, spec.is_float, lower=False)
        if not low - slack <= raw * scale + offset <= high + slack:
            raise ValueError(f"{value:g} has no raw value within [{low:g}, {high:g}] (one count is {abs(scale):g} V)")
    if not spec.minimum <= raw <= spec.maximum:
        raise ValueError(f"{value:g} needs raw {exact:g}, outside {data_type}'s range "
                         f"{spec.minimum:g}..{spec.maximum:g}")
    return raw


def step_v(scale: float, offset: float, data_type: str, v_min: float, v_max: float) -> float:
    """The largest step between neighbouring voltages ``data_type`` can hold in ``[v_min, v_max]``.

    One count (``|scale|``) for the integer types; for float32 the spacing of float32 values at the
    largest raw value of the range (a float's steps grow with its size: a large ``offset`` makes them
    coarse), times ``|scale|``. Call it for a range whose raw values fit the type (see :func:`raw_for`).
    """
    spec = DATA_TYPES[data_type]
    if not spec.is_float:
        return abs(scale)
    largest = max(abs((v_min - offset) / scale), abs((v_max - offset) / scale))
    return float(np.spacing(np.float32(largest))) * abs(scale)


#: an integer raw value scaling back to within this fraction of a count beyond a limit is at the limit
#: (``4095 * (10 / 4095)`` is 10.000000000000002 in floating point, and 10 V is the module's top)
_SLACK = 1e-6


def _float32(x: float) -> float:
    """The float32 nearest ``x`` (what the register pair will hold); overflow keeps ``x`` for the range check."""
    if abs(x) > DATA_TYPES["float32"].maximum:
        return x
    return float(np.float32(x))


def _inward(raw: int | float, scale: float, is_float: bool, *, lower: bool) -> int | float:
    """The neighbouring raw value whose voltage is lower (``lower``) or higher than ``raw``'s."""
    towards_lower_raw = lower == (scale > 0)
    if is_float:
        step = np.float32(-np.inf if towards_lower_raw else np.inf)
        return float(np.nextafter(np.float32(raw), step))
    return int(raw) - 1 if towards_lower_raw else int(raw) + 1
