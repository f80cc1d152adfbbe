"""An analog output channel of a Modbus module as the stage's actuator (e.g. an ADAM-6224 0-10 V output
wired to the PZT amplifier's analog input).

One holding register (function 6), or a pair for 32-bit types (function 16), in the sensors' data
types and byte/word orders; ``register = round((voltage_v - offset) / scale)``, except that a voltage
within half a count of ``[v_min, v_max]`` (``limits_v``) takes the count on the inside, so the output
never exceeds a limit. The output shares its hub (one connection, one lock) with any sensors on the
same module or bus. With ``verify`` every write is read back (function 3): a device that clamps,
ignores or mangles the value is an actuator fault, named with what was written and what came back;
``verify`` also means the register can be read, so :meth:`read_back` tells where the output is.
"""

from __future__ import annotations

from typing import Literal

from nanodrift.drivers.base import Actuator, DeviceError
from nanodrift.drivers.modbus.codec import decode, encode, raw_for
from nanodrift.drivers.modbus.config import ModbusActuatorConfig
from nanodrift.drivers.modbus.hub import HubLease, ModbusExceptionError, ModbusHub


class ModbusActuator(Actuator):
    def __init__(self, config: ModbusActuatorConfig, hub: ModbusHub) -> None:
        self.config = config
        self.hub = hub
        self.description = (f"modbus output (hub {hub.name!r} at {hub.endpoint}, device {config.device_id}, "
                            f"holding register {config.address})")
        self._lease = HubLease(hub)

    def __repr__(self) -> str:
        return f"ModbusActuator({self.description})"

    async def open(self) -> None:
        await self._lease.open()

    async def close(self) -> None:
        self._lease.close()

    def volts(self, registers: list[int]) -> tuple[int | float, float]:
        """What ``registers`` hold: the raw value and the voltage it means."""
        c = self.config
        raw = decode(registers, c.data_type, c.swap)
        return raw, raw * c.scale + c.offset

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        """The voltage the output register holds (None without ``verify``: the register may not be readable)."""
        c = self.config
        if not c.verify:
            return None
        try:
            registers = await self.hub.read_registers("holding", c.device_id, c.address, c.register_count)
        except (ModbusExceptionError, DeviceError) as error:
            raise DeviceError(f"{self.description}: reading the output failed: {error}") from error
        return "voltage_v", self.volts(registers)[1]

    def sent_voltage(self, voltage_v: float) -> float:
        """The voltage of the count that ``voltage_v`` is written as (ValueError: none can represent it)."""
        c = self.config
        raw = raw_for(voltage_v, c.scale, c.offset, c.data_type, within=self.limits_v)
        return raw * c.scale + c.offset

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        c = self.config
        try:
            raw = raw_for(voltage_v, c.scale, c.offset, c.data_type, within=self.limits_v)
        except ValueError as error:
            raise ValueError(f"{self.description}: cannot write {voltage_v:.4f} V: {error}") from None
        registers = encode(raw, c.data_type, c.swap)
        try:
            await self.hub.write_registers(c.device_id, c.address, registers)
        except (ModbusExceptionError, DeviceError) as error:
            raise DeviceError(f"{self.description}: writing {voltage_v:.4f} V (raw {raw}) failed: {error}") from error
        if c.verify:
            try:
                back = await self.hub.read_registers("holding", c.device_id, c.address, len(registers))
            except (ModbusExceptionError, DeviceError) as error:
                raise DeviceError(f"{self.description}: reading back {voltage_v:.4f} V failed: {error}") from error
            if back != registers:
                read_raw, read_v = self.volts(back)
                raise DeviceError(f"{self.description}: wrote raw {raw} ({voltage_v:.4f} V), read back raw "
                                  f"{read_raw} ({read_v:.4f} V)")
