"""Channels merged into one Modbus request, and the sensor group that polls them.

Merging: channels on the same hub, device and register kind whose registers are contiguous (or
overlap) are read with one request: eight thermocouples at 0..7 cost one round trip instead of
eight. Gaps of up to :data:`MAX_GAP_REGISTERS` unused registers are bridged too (a few extra bytes
cost far less than a round trip), up to :data:`MAX_REGISTERS_PER_READ` registers per request (the
protocol's limit is 125). Some modules refuse to read registers they do not map (exception 2,
illegal data address): a bridged request that gets exception 2 is split into its contiguous runs
for good, and read again at once, so bridging never costs a working channel.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import structlog

from nanodrift.drivers.base import Clock, DeviceError, Reading, SensorGroup
from nanodrift.drivers.modbus.codec import decode
from nanodrift.drivers.modbus.config import ModbusSensorConfig
from nanodrift.drivers.modbus.hub import HubLease, ModbusExceptionError, ModbusHub

MAX_GAP_REGISTERS = 4
MAX_REGISTERS_PER_READ = 125
ILLEGAL_DATA_ADDRESS = 2

log = structlog.get_logger(__name__)


@dataclass(frozen=True, slots=True)
class Block:
    """One read request: ``count`` registers from ``start``, and the channels they carry."""

    hub: str
    device_id: int
    input_type: str
    start: int
    count: int
    channels: tuple[ModbusSensorConfig, ...]


def _block(channels: Sequence[ModbusSensorConfig]) -> Block:
    first = channels[0]
    start = min(c.address for c in channels)
    end = max(c.end for c in channels)
    return Block(first.hub, first.device_id, first.input_type, start, end - start, tuple(channels))


def plan_blocks(
    configs: Iterable[ModbusSensorConfig],
    *,
    max_gap: int = MAX_GAP_REGISTERS,
    max_count: int = MAX_REGISTERS_PER_READ,
) -> list[Block]:
    """Group channels into as few requests as the rules above allow (stable, deterministic order)."""
    by_device: dict[tuple[str, int, str], list[ModbusSensorConfig]] = {}
    for c in configs:
        by_device.setdefault((c.hub, c.device_id, c.input_type), []).append(c)
    blocks: list[Block] = []
    for members in by_device.values():
        members.sort(key=lambda c: (c.address, c.end, c.name))
        runs: list[list[ModbusSensorConfig]] = []
        start = end = 0
        for c in members:
            if runs and c.address - end <= max_gap and max(end, c.end) - start <= max_count:
                runs[-1].append(c)
                end = max(end, c.end)
            else:
                runs.append([c])
                start, end = c.address, c.end
        blocks.extend(_block(run) for run in runs)
    return blocks


class ModbusBlockGroup(SensorGroup):
    """The channels of one :class:`Block`, polled together.

    A device exception code faults every channel of the request (the reason names the code); a
    burnout raw value (``nan_value``) faults its channel only; no answer or a lost link raises
    :class:`DeviceError` (the daemon's poller reopens the group after its back-off; the hub reconnects then).
    """

    def __init__(self, block: Block, hub: ModbusHub, clock: Clock) -> None:
        self.block = block
        self.hub = hub
        self.clock = clock
        self._requests: list[Block] = [block]
        self._lease = HubLease(hub)
        self.set_channels(block.channels)  # a slow poll may wait behind others on the hub
        # the hub's own timeout (hub timeout_s x (retries + 1)) must fire before the caller's
        self.timeout_s = max(max(c.timeout_s for c in block.channels), hub.poll_timeout_s)

    def __repr__(self) -> str:
        b = self.block
        return (f"ModbusBlockGroup(hub={b.hub!r}, device={b.device_id}, {b.input_type} {b.start}"
                f"..{b.start + b.count - 1}, channels={list(self.names)})")

    @property
    def request_count(self) -> int:
        """Requests one poll sends (1 unless a bridged block had to be split)."""
        return len(self._requests)

    async def open(self) -> None:
        await self._lease.open()

    async def close(self) -> None:
        self._lease.close()

    async def read(self) -> dict[str, Reading]:
        readings: dict[str, Reading] = {}
        index = 0
        while index < len(self._requests):
            request = self._requests[index]
            try:
                registers = await self.hub.read_registers(
                    request.input_type, request.device_id, request.start, request.count
                )
            except ModbusExceptionError as error:
                runs = plan_blocks(request.channels, max_gap=0)  # split where unused registers separate them
                if error.code == ILLEGAL_DATA_ADDRESS and len(runs) > 1:
                    log.info("modbus request split: the device refuses unmapped registers",
                             hub=request.hub, device_id=request.device_id, start=request.start,
                             count=request.count, requests=len(runs))
                    self._requests[index : index + 1] = runs
                    continue
                t = self.clock.now()
                for c in request.channels:
                    readings[c.name] = Reading.fault(t, str(error), c.value_unit)
            else:
                t = self.clock.now()
                for c in request.channels:
                    readings[c.name] = channel_reading(c, registers[c.address - request.start :], t)
            index += 1
        return readings


def channel_reading(config: ModbusSensorConfig, registers: Sequence[int], t: float) -> Reading:
    """One channel's reading from the registers starting at its address."""
    unit = config.value_unit
    try:
        raw = decode(registers[: config.register_count], config.data_type, config.swap)
    except ValueError as error:  # cannot happen with a well-formed answer; never crash a poll
        raise DeviceError(f"{config.name}: {error}") from error
    if config.nan_value is not None and raw == config.nan_value:
        what = "open thermocouple" if config.role == "temperature" else "no valid value"
        return Reading.fault(t, f"{what} (raw {raw:g})" if isinstance(raw, float) else f"{what} (raw {raw})",
                             unit)
    if isinstance(raw, float) and not math.isfinite(raw):
        return Reading.fault(t, f"device sent {raw} (raw float32 not finite)", unit)
    return Reading(value=raw * config.scale + config.offset, t=t, unit=unit)
