"""The ``[[sensors]]`` keys of a Modbus channel (Home Assistant modbus naming)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, FiniteFloat, field_validator, model_validator

from drivers.base import SensorConfig
from drivers.modbus.codec import DATA_TYPES, DataTypeName, SwapName, register_count


class ModbusSensorConfig(SensorConfig):
    """One channel read from a Modbus register (or register pair) of a device on a hub."""

    kind: Literal["modbus"] = "modbus"
    hub: str = Field(description="name of a [[hubs]] entry: the TCP connection or RS-485 bus")
    device_id: int = Field(default=1, ge=0, le=255, description="Modbus unit / slave id")
    address: int = Field(ge=0, le=65535, description="0-based protocol address (40001 -> 0)")
    input_type: Literal["input", "holding"] = Field(
        default="holding", description="input registers (function 4) or holding registers (function 3)"
    )
    data_type: DataTypeName = "int16"
    swap: SwapName = "none"
    scale: FiniteFloat = 1.0
    offset: FiniteFloat = 0.0
    nan_value: int | float | None = Field(
        default=None, description="raw value (before scale/offset) meaning burnout/open circuit -> fault"
    )
    unit: str | None = Field(default=None, description="unit of the scaled value; default degC / um by role")

    @field_validator("nan_value", mode="before")
    @classmethod
    def _parse_hex(cls, value: object) -> object:
        # Home Assistant accepts nan_value as a string such as "0x8000"; TOML has native hex ints.
        if isinstance(value, str):
            try:
                return int(value, 0)
            except ValueError:
                raise ValueError(f"expected an integer such as -32768 or 0x7FFF, got {value!r}") from None
        return value

    @model_validator(mode="after")
    def _consistent(self) -> ModbusSensorConfig:
        spec = DATA_TYPES[self.data_type]
        if self.swap in ("word", "word_byte") and spec.registers < 2:
            raise ValueError(
                f"swap = {self.swap!r} reorders registers and needs a 32-bit data_type, not {self.data_type}"
            )
        if self.address + spec.registers - 1 > 65535:
            raise ValueError(f"address {self.address} + {spec.registers} register(s) runs past 65535")
        if self.nan_value is not None:
            if not spec.is_float and isinstance(self.nan_value, float) and not self.nan_value.is_integer():
                raise ValueError(f"nan_value {self.nan_value} must be an integer for {self.data_type}")
            if not spec.minimum <= self.nan_value <= spec.maximum:
                raise ValueError(
                    f"nan_value {self.nan_value} is outside {self.data_type}'s range "
                    f"{spec.minimum}..{spec.maximum} (for the bit pattern 0x8000 of an int16 write -32768)"
                )
        return self

    @property
    def register_count(self) -> int:
        return register_count(self.data_type)

    @property
    def end(self) -> int:
        """One past the last register this channel occupies."""
        return self.address + self.register_count

    @property
    def value_unit(self) -> str:
        if self.unit is not None:
            return self.unit
        return "um" if self.role == "position" else "degC"
