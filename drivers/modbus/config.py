"""The ``[[sensors]]`` keys of a Modbus channel (Home Assistant modbus naming)."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import AllowInfNan, Field, FiniteFloat, field_validator, model_validator

from nanodrift.drivers.base import ActuatorOptions, OutputClaim, SensorConfig, StrictModel, output_step_problem
from nanodrift.drivers.modbus.codec import DATA_TYPES, DataTypeName, SwapName, raw_for, register_count, step_v


def _check_layout(data_type: str, swap: str, address: int) -> None:
    """A ``ValueError`` when ``swap`` or ``address`` cannot take ``data_type``."""
    spec = DATA_TYPES[data_type]
    if swap in ("word", "word_byte") and spec.registers < 2:
        raise ValueError(f"swap = {swap!r} reorders registers and needs a 32-bit data_type, not {data_type}")
    if address + spec.registers - 1 > 65535:
        raise ValueError(f"address {address} + {spec.registers} register(s) runs past 65535")


class ModbusHubConfig(StrictModel):
    """A ``[[hubs]]`` entry: a connection shared by several channels (Home Assistant modbus naming); strict: no
    ``"502"`` for 502."""

    name: str
    type: Literal["tcp", "serial"] = "tcp"
    host: str = "127.0.0.1"
    port: int | str = 502  # TCP port, or serial device for type = "serial"
    timeout_s: float = Field(default=1.0, gt=0)
    baudrate: int = 9600
    bytesize: Literal[7, 8] = 8
    parity: Literal["N", "E", "O"] = "N"
    stopbits: Literal[1, 2] = 1
    retries: int = Field(default=0, ge=0)


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
    nan_value: int | Annotated[float, AllowInfNan(True)] | None = Field(
        default=None,
        description="raw value (before scale/offset) meaning burnout/open circuit -> fault",
    )
    unit: str | None = Field(default=None, description="unit of the scaled value; default degC / um by role")

    def hub_name(self) -> str:
        return self.hub

    @field_validator("scale")
    @classmethod
    def _scale_not_zero(cls, value: float) -> float:
        if value == 0:
            raise ValueError("must not be 0: every reading would be the offset, whatever the register holds")
        return value

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
        _check_layout(self.data_type, self.swap, self.address)
        spec = DATA_TYPES[self.data_type]
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


class ModbusActuatorConfig(ActuatorOptions):
    """``[actuator] kind = "modbus"``: one analog output channel in a holding register (or pair).

    ``register = round((voltage_v - offset) / scale)``: ``scale`` is the module's volts per count
    (no default: it is in the module's manual). ``verify`` reads the register back after each write.
    """

    kind: Literal["modbus"] = "modbus"
    hub: str = Field(description="name of a [[hubs]] entry; shared with the sensors on it")
    device_id: int = Field(default=1, ge=0, le=255, description="Modbus unit / slave id")
    address: int = Field(ge=0, le=65535, description="0-based protocol address of the output's holding register")
    data_type: DataTypeName = "int16"
    swap: SwapName = "none"
    scale: FiniteFloat = Field(description="volts per count")
    offset: FiniteFloat = Field(default=0.0, description="volts at count 0")
    verify: bool = Field(default=True, description="read the register back after each write; a mismatch faults")

    def hub_name(self) -> str:
        return self.hub

    def claims(self) -> list[OutputClaim]:
        """Every holding register the value occupies (an int32 its pair) on this unit of this hub."""
        registers = range(self.address, self.address + self.register_count)
        return [OutputClaim(f"Modbus hub {self.hub!r}, unit id {self.device_id}",
                            frozenset(f"holding register {r}" for r in registers))]

    @model_validator(mode="after")
    def _consistent(self) -> ModbusActuatorConfig:
        if self.scale == 0:
            raise ValueError("scale (volts per count) must not be 0")
        _check_layout(self.data_type, self.swap, self.address)
        return self

    @property
    def register_count(self) -> int:
        return register_count(self.data_type)

    def voltage_range_problem(self, v_min: float, v_max: float, volts_per_um: float) -> str | None:
        """Every voltage of ``[v_min, v_max]`` must fit ``data_type`` (checked at both ends: the raw value is
        monotonic in the voltage) and one step of the register must be fine enough
        (:func:`nanodrift.drivers.base.output_step_problem`): ``scale = 10.0`` wrote a 4.73 V command as 0 V."""
        for name, volts in (("v_min", v_min), ("v_max", v_max)):
            try:
                raw_for(volts, self.scale, self.offset, self.data_type)
                raw_for(volts, self.scale, self.offset, self.data_type, within=(v_min, v_max))
            except ValueError as error:
                return (f"{name} = {volts:g} V cannot be written as {self.data_type} with scale {self.scale:g} and "
                        f"offset {self.offset:g} ({error}); narrow [v_min, v_max] to what the output can do")
        coarse = output_step_problem(step_v(self.scale, self.offset, self.data_type, v_min, v_max),
                                     v_min, v_max, volts_per_um)
        if coarse:
            return (f"scale = {self.scale:g} V per count with data_type {self.data_type} and offset {self.offset:g}: "
                    f"{coarse}; scale is the module's volts per count (e.g. 10 / 4095 for a 12-bit 0-10 V output)")
        return None
