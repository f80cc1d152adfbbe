"""One DCON module as a sensor group: its channels read by one ``#AA`` exchange per poll.

At ``open`` the module is asked its name (``$AAM``) and configuration (``$AA2``): a module that sends
hexadecimal or percent-of-span data, or whose checksum setting differs from the config, is refused
there with both sides named, never read as temperatures. A channel whose value is the over/under-range
code is a fault for that channel alone; with ``open_detection`` a channel the module's own ``$AAB``
diagnosis flags is a fault too. Silence, a bad checksum, a line that is not the module's answer: a
:class:`DeviceError` naming the hub, the module and what was expected.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Sequence

from nanodrift.drivers.base import Clock, DeviceError, Reading, SensorGroup
from nanodrift.drivers.dcon.bus import DconBus
from nanodrift.drivers.dcon.config import DconSensorConfig
from nanodrift.drivers.dcon.protocol import (
    ChannelValue,
    DconFormatError,
    frame,
    parse_all_channels,
    parse_configuration,
    parse_diagnosis,
    parse_module_name,
    unframe,
)

log = logging.getLogger(__name__)


class DconModuleGroup(SensorGroup):
    def __init__(self, channels: Sequence[DconSensorConfig], bus: DconBus, clock: Clock, *,
                 modules_on_bus: int = 1) -> None:
        first = channels[0]
        self.channels = list(channels)
        self.bus = bus
        self.clock = clock
        self.address = first.address
        self.with_checksum = first.checksum
        self.open_detection = first.open_detection
        self.set_channels(channels)
        # one poll: #AA, and $AAB when asked, each bounded by the hub's timeout, possibly after as much for
        # every other module of the bus (one request at a time): the poll's bound covers the queue
        exchanges = 2 if self.open_detection else 1
        self.timeout_s = max(max(c.timeout_s for c in channels),
                             exchanges * bus.config.timeout_s * modules_on_bus + 0.5)
        self.module_name = ""
        self._opened = False

    @property
    def description(self) -> str:
        name = f" ({self.module_name})" if self.module_name else ""
        return f"{self.bus.description} module {self.address:02X}{name}"

    def __repr__(self) -> str:
        return f"DconModuleGroup({self.description}, channels {[c.channel for c in self.channels]})"

    async def _ask(self, command: str, expected: str) -> str:
        answer = await self.bus.request(frame(command, with_checksum=self.with_checksum), expected)
        try:
            return unframe(answer, with_checksum=self.with_checksum)
        except DconFormatError as error:
            raise DeviceError(f"{self.description}: answer to {command!r}: {error}") from None

    async def open(self) -> None:
        if not self._opened:
            await self.bus.open()
            self._opened = True
        aa = f"{self.address:02X}"
        try:
            self.module_name = parse_module_name(await self._ask(f"${aa}M", f"!{aa} and the module name"),
                                                 self.address)
            configuration = parse_configuration(await self._ask(f"${aa}2", f"!{aa}TTCCFF"), self.address)
        except DconFormatError as error:
            raise DeviceError(f"{self.description}: {error}") from None
        if not configuration.engineering_units:
            raise DeviceError(f"{self.description}: configured for data format {configuration.format_byte & 3} "
                              "($AA2 FF bits 0-1); nanodrift reads engineering units (format 0): reconfigure the "
                              "module (%AANNTTCCFF) or its utility")
        if configuration.checksum != self.with_checksum:
            state = "on" if configuration.checksum else "off"
            raise DeviceError(f"{self.description}: the module's checksum is {state} ($AA2), the config says "
                              f"checksum = {str(self.with_checksum).lower()}")
        log.info("%s: opened, input range code %02X", self.description, configuration.type_code)

    async def close(self) -> None:
        if self._opened:
            self._opened = False
            await self.bus.release()

    async def read(self) -> dict[str, Reading]:
        aa = f"{self.address:02X}"
        body = await self._ask(f"#{aa}", "'>' and every channel's value")
        try:
            values = parse_all_channels(body)
            flagged = parse_diagnosis(await self._ask(f"${aa}B", f"!{aa}NN"), self.address) \
                if self.open_detection else 0
        except DconFormatError as error:
            raise DeviceError(f"{self.description}: {error}") from None
        t = self.clock.now()
        return {config.name: self._reading(config, values, flagged, t) for config in self.channels}

    def _reading(self, config: DconSensorConfig, values: list[ChannelValue], flagged: int, t: float) -> Reading:
        """One channel's reading from the poll's values and ``$AAB`` mask (0 without open detection)."""
        where = f"{self.description} channel {config.channel}"
        if config.channel >= len(values):
            return Reading.fault(t, f"{where}: the module answered {len(values)} channel(s)", config.unit)
        value = values[config.channel]
        if value.problem:
            return Reading.fault(t, f"{where}: {value.problem}", config.unit)
        if flagged >> config.channel & 1:
            return Reading.fault(t, f"{where}: the module diagnoses it open or out of range ($AAB)", config.unit)
        assert math.isfinite(value.value)
        return Reading(value=value.value, t=t, unit=config.unit)
