"""Sensor ingestion: what the pollers read goes into the table and the model's filters, and out as telemetry.

Runs on the asyncio loop (the pollers' callbacks). The table is updated under the state lock; the
telemetry is published after the lock is released, so a slow publish never holds up a target.
The ``role = "position"`` sensor's readings, each with whether it is ok and fresh, the good
temperatures, and every temperature reading (ok or not: a recorded row carries every polled channel)
go to the health unit (``nanodrift.service.health_unit``) under the same lock; its log lines and
``health`` sample after it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from nanodrift.bus.protocol import encode_telemetry
from nanodrift.drivers.base import Reading, SensorGroup, State
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.state import CellState

#: how the health advice names a position sensor's state
_STATE_WORDS = {State.FAULT: "faulted", State.STALE: "stale", State.OK: "ok"}

#: publishes one telemetry payload: (role, channel, payload)
PublishTelemetry = Callable[[str, str, bytes], None]


class SensorIngest:
    """The pollers' callbacks: readings, a group that failed, a group that recovered."""

    def __init__(self, state: CellState, publish_telemetry: PublishTelemetry, log: Any,
                 health: HealthUnit | None = None) -> None:
        self.state = state
        self.publish_telemetry = publish_telemetry
        self.log = log
        self.health = health

    def on_readings(self, group: SensorGroup, readings: Mapping[str, Reading]) -> None:
        state = self.state
        temps: dict[str, float] = {}
        t_obs = None
        telemetry = []
        health = self.health
        with state.lock:
            table = state.table
            now = state.clock.now()  # the table judges every reading on the daemon's clock
            for name, reading in readings.items():
                entry = table.update(name, reading, now)
                if entry is None:
                    continue
                if entry.role == "temperature" and health is not None:
                    health.on_channel(name, reading.t, reading.value, entry.device_state == State.OK)
                if entry.role == "temperature" and entry.device_state == State.OK:
                    temps[name] = reading.value
                    t_obs = reading.t if t_obs is None else max(t_obs, reading.t)
                elif entry.role == "position" and health is not None:
                    # only what the table believes (in range, not frozen, not in the future) and fresh
                    channel_state, reason = table.state(name, now)
                    ok = channel_state == State.OK
                    health.on_position(now, reading.t, reading.value, ok,
                                       problem="" if ok else f"{_STATE_WORDS[channel_state]}: {reason}", channel=name)
                telemetry.append((entry.role, name, reading.value, entry.unit, reading.t, entry.device_state.value,
                                  entry.reason))
            if temps and t_obs is not None:
                state.compensator.observe(t_obs, temps)
                if health is not None:
                    health.on_temperatures(t_obs, temps)
        if health is not None:
            health.flush()
        try:
            for role, name, value, unit, t, device_state, reason in telemetry:
                self.publish_telemetry(role, name, encode_telemetry(value, unit, t, device_state, reason))
        except zenoh.ZError as error:  # a bus problem is not the device's fault
            self.log.warning("telemetry_failed", error=str(error))

    def on_group_failure(self, group: SensorGroup, reason: str, retry_in_s: float, failures: int) -> None:
        """One ``sensor_group_failed`` line per episode (its first failure); the retries are debug lines."""
        health = self.health
        with self.state.lock:
            self.state.table.mark_fault(group.names, f"device error: {reason}")
            if health is not None:
                now = self.state.clock.now()
                for name in group.names:  # a device that fails voids its position sensor's window
                    health.on_position(now, now, math.nan, False, problem=f"faulted: device error: {reason}",
                                       channel=name)
                for name in group.names:
                    if group.roles.get(name) == "temperature":
                        health.on_channel(name, now, math.nan, False)  # ... and a recorded row's validity
        if failures == 1:
            self.log.warning("sensor_group_failed", channels=list(group.names), reason=reason,
                             retry_in_s=round(retry_in_s, 2))
        else:
            self.log.debug("sensor_group_retry_failed", channels=list(group.names), reason=reason,
                           failures=failures, retry_in_s=round(retry_in_s, 2))

    def on_group_recovered(self, group: SensorGroup, failures: int, down_s: float) -> None:
        """The episode's summary: how many attempts failed and for how long."""
        self.log.info("sensor_group_recovered", channels=list(group.names), failures=failures,
                      down_s=round(down_s, 2))
