"""A cell's drivers once assembled (by ``nanodrift.assembly``): what the daemon polls and a procedure drives.

Not part of the plugin contract (a plugin never builds one), so it lives with the daemon; the service
and the procedures import it from here, never from the assembly.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from nanodrift.drivers.base import Actuator, Clock, DriverContext, SensorGroup
from nanodrift.output_record import OutputRecords


@dataclass
class DriverSet:
    """The sensor groups and the outputs of one config, with the context they share."""

    context: DriverContext
    groups: list[SensorGroup]
    roles: dict[str, str]
    max_age_s: dict[str, float]
    description: str = ""
    #: the cell's output per axis (a one-axis cell's: ``{"x": actuator}``; an axis with ``kind = "zenoh"`` has
    #: none): what the daemon's actuation and the procedures drive
    actuators: dict[str, Actuator] = field(default_factory=dict)
    #: each axis' position sensor (a one-axis cell's: ``{"x": name}``)
    position_axes: dict[str, str] = field(default_factory=dict)
    #: where a procedure records what it writes to each output (the daemon's start believes only that)
    records: OutputRecords | None = None

    @property
    def clock(self) -> Clock:
        return self.context.clock

    @property
    def temperature_channels(self) -> tuple[str, ...]:
        return tuple(name for name, role in self.roles.items() if role == "temperature")
