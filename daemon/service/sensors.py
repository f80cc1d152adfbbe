"""Sensor ingestion: what the pollers read goes into the table and the model's filters, and out as telemetry.

Runs on the asyncio loop (the pollers' callbacks). The table is updated under the state lock; the
telemetry is published after the lock is released, so a slow publish never holds up a target.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from daemon.bus.protocol import encode_telemetry
from daemon.service.state import CellState
from drivers.base import Reading, SensorGroup, State

#: publishes one telemetry payload: (role, channel, payload)
PublishTelemetry = Callable[[str, str, bytes], None]


class SensorIngest:
    """The pollers' callbacks: readings, a group that failed, a group that recovered."""

    def __init__(self, state: CellState, publish_telemetry: PublishTelemetry, log: Any) -> None:
        self.state = state
        self.publish_telemetry = publish_telemetry
        self.log = log

    def on_readings(self, group: SensorGroup, readings: Mapping[str, Reading]) -> None:
        state = self.state
        temps: dict[str, float] = {}
        t_obs = None
        telemetry = []
        with state.lock:
            table = state.table
            for name, reading in readings.items():
                entry = table.update(name, reading)
                if entry is None:
                    continue
                if entry.role == "temperature" and entry.device_state == State.OK:
                    temps[name] = reading.value
                    t_obs = reading.t if t_obs is None else max(t_obs, reading.t)
                telemetry.append((entry.role, name, reading.value, entry.unit, reading.t, entry.device_state.value,
                                  entry.reason))
            if temps and t_obs is not None:
                state.compensator.observe(t_obs, temps)
        try:
            for role, name, *doc in telemetry:
                self.publish_telemetry(role, name, encode_telemetry(*doc))
        except zenoh.ZError as error:  # a bus problem is not the device's fault
            self.log.warning("telemetry_failed", error=str(error))

    def on_group_failure(self, group: SensorGroup, reason: str, retry_in_s: float) -> None:
        with self.state.lock:
            self.state.table.mark_fault(group.names, f"device error: {reason}")
        self.log.warning("sensor_group_failed", channels=list(group.names), reason=reason,
                         retry_in_s=round(retry_in_s, 2))

    def on_group_recovered(self, group: SensorGroup) -> None:
        self.log.info("sensor_group_recovered", channels=list(group.names))

