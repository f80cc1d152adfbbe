"""The small interfaces every device kind implements, in the spirit of python-can's bus.

A *sensor group* is the unit the daemon polls: one device request that yields readings for one or
more channels (a Modbus module answering eight thermocouples in one request is one group; a serial
interferometer is a group of one). A *plugin* turns validated sensor configs into groups, and is
found by name through the entry-point group ``nanodrift.drivers``.

Drivers report what the device said (``ok`` or ``fault`` with a reason). Whether a reading is
``stale`` is the daemon's judgement (its age against ``max_age_s``), not the driver's.
Connection-level trouble (port gone, timeout, socket closed) is raised as :class:`DeviceError` so
the daemon can reopen the group with backoff; a channel-level problem on a healthy device
(thermocouple burnout) is a ``fault`` reading.
"""

from __future__ import annotations

import asyncio
import time
from abc import ABC, abstractmethod
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, ClassVar, Literal, Protocol

from pydantic import BaseModel, ConfigDict, Field


class State(StrEnum):
    OK = "ok"
    STALE = "stale"
    FAULT = "fault"


@dataclass(frozen=True, slots=True)
class Reading:
    """One timestamped value of one channel, with the device's verdict on it."""

    value: float  # NaN when state is FAULT
    t: float  # seconds on the group's clock (unix seconds on real hardware)
    state: State = State.OK
    reason: str = ""
    unit: str = ""

    @classmethod
    def fault(cls, t: float, reason: str, unit: str = "") -> Reading:
        return cls(value=float("nan"), t=t, state=State.FAULT, reason=reason, unit=unit)


class DeviceError(Exception):
    """The device or its connection failed; the daemon closes and reopens the group with backoff."""


class Clock(Protocol):
    """Where time comes from: the wall clock, or a simulated one that runs faster than real time."""

    def now(self) -> float: ...

    async def sleep(self, seconds: float) -> None: ...


class WallClock:
    """Real time: unix seconds and asyncio's sleep."""

    def now(self) -> float:
        return time.time()

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))


class ScaledClock:
    """Real sleeps, but simulated time runs ``speed`` times faster than the wall clock."""

    def __init__(self, speed: float = 1.0, start: float | None = None) -> None:
        if speed <= 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.speed = speed
        self._start = time.time() if start is None else start
        self._mono0 = time.monotonic()

    def now(self) -> float:
        return self._start + self.speed * (time.monotonic() - self._mono0)

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds) / self.speed)


class SensorConfig(BaseModel):
    """Keys common to every ``[[sensors]]`` entry. A plugin subclasses it with its own keys.

    ``extra="forbid"``: a typo in an operator's config must be an error, never silently ignored.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_.\-]*$", description="channel name the model uses")
    role: Literal["temperature", "position"] = "temperature"
    kind: str
    interval_s: float = Field(default=0.5, gt=0, description="poll period")
    max_age_s: float = Field(default=5.0, gt=0, description="older readings are stale")
    timeout_s: float = Field(default=1.0, gt=0, description="one poll may take this long")


class HubConfig(BaseModel):
    """A connection shared by several channels (Home Assistant modbus 'hub' naming)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

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


@dataclass
class DriverContext:
    """What a plugin may need besides its own configs: shared hubs, the clock, simulation settings."""

    clock: Clock = field(default_factory=WallClock)
    hubs: Mapping[str, HubConfig] = field(default_factory=dict)
    simulation: Mapping[str, Any] = field(default_factory=dict)
    shared: dict[str, Any] = field(default_factory=dict)  # plugin-private objects (e.g. one sim cell)


class SensorGroup(ABC):
    """Channels read together in one device transaction; polled by the daemon every ``interval_s``."""

    #: channel names this group yields, in a stable order
    names: tuple[str, ...]
    #: role of each channel ("temperature" | "position")
    roles: Mapping[str, str]
    interval_s: float
    timeout_s: float

    @abstractmethod
    async def open(self) -> None:
        """Connect. Raise :class:`DeviceError` when the device cannot be reached."""

    @abstractmethod
    async def read(self) -> dict[str, Reading]:
        """One poll: a reading per channel in ``names``. Raise :class:`DeviceError` on link failure."""

    @abstractmethod
    async def close(self) -> None:
        """Release the device; safe to call twice and after a failed ``open``."""


class Actuator(ABC):
    """Takes the compensated command. Real stages get the voltage from the published command."""

    @abstractmethod
    async def open(self) -> None: ...

    @abstractmethod
    async def command(self, q_um: float, voltage_v: float) -> None: ...

    @abstractmethod
    async def close(self) -> None: ...


class DriverPlugin(Protocol):
    """What an entry point in ``nanodrift.drivers`` names: a driver kind.

    ``config_model`` validates one ``[[sensors]]`` entry of this kind (including the common keys).
    ``create`` gets every validated entry of this kind at once so it can share connections and
    merge contiguous channels into one request.

    A plugin that can also move the stage defines ``create_actuator(context) -> Actuator`` (the
    simulated cell does); the daemon and the calibration procedure look for it with ``getattr``,
    since most sensor plugins have none.
    """

    name: str
    config_model: ClassVar[type[SensorConfig]] | type[SensorConfig]

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]: ...
