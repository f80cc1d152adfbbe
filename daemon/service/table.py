"""The latest reading of every configured channel and its state: ok, stale or fault (with the reason).

Staleness is judged here, with the drivers' clock, not by the drivers: a driver says what the device
said, the daemon says whether that is recent enough to compute a command from.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

from drivers.base import Reading, SensorConfig, State

UNITS = {"temperature": "degC", "position": "um"}


@dataclass(slots=True)
class ChannelEntry:
    name: str
    role: str
    unit: str
    max_age_s: float
    value: float | None = None
    t: float | None = None
    device_state: State = State.STALE  # STALE here means: nothing read yet
    reason: str = "no reading yet"


class SensorTable:
    """The latest reading of each configured channel."""

    def __init__(self, sensors: Sequence[SensorConfig]) -> None:
        self.entries: dict[str, ChannelEntry] = {
            s.name: ChannelEntry(s.name, s.role, UNITS.get(s.role, ""), s.max_age_s) for s in sensors
        }
        #: bumped by every change, so readers can cache what they derive from the entries
        self.version = 0

    def update(self, name: str, reading: Reading) -> ChannelEntry | None:
        entry = self.entries.get(name)
        if entry is None:
            return None
        self.version += 1
        entry.t = reading.t
        if reading.state == State.OK and math.isfinite(reading.value):
            entry.value = float(reading.value)
            entry.device_state = State.OK
            entry.reason = ""
        else:
            entry.device_state = State.FAULT
            entry.reason = reading.reason or ("non-finite value" if reading.state == State.OK else "fault")
        if reading.unit:
            entry.unit = reading.unit
        return entry

    def mark_fault(self, names: Iterable[str], reason: str) -> None:
        """The device behind these channels failed; they are faulted until a reading arrives."""
        self.version += 1
        for name in names:
            entry = self.entries.get(name)
            if entry is not None:
                entry.device_state = State.FAULT
                entry.reason = reason

    def state(self, name: str, now: float) -> tuple[State, str]:
        entry = self.entries.get(name)
        if entry is None:
            return State.FAULT, "no sensor configured for this channel"
        if entry.device_state == State.FAULT:
            return State.FAULT, entry.reason
        if entry.t is None or entry.device_state != State.OK:
            return State.STALE, entry.reason or "no reading yet"
        age = now - entry.t
        if age > entry.max_age_s:
            return State.STALE, f"last reading {age:.1f} s old (max_age_s {entry.max_age_s:g})"
        return State.OK, ""

    def snapshot(self, now: float) -> dict[str, dict[str, Any]]:
        out = {}
        for name, entry in self.entries.items():
            state, reason = self.state(name, now)
            out[name] = {
                "role": entry.role,
                "value": entry.value,
                "unit": entry.unit,
                "t": entry.t,
                "age_s": None if entry.t is None else round(now - entry.t, 6),
                "max_age_s": entry.max_age_s,
                "state": state.value,
                "reason": reason,
            }
        return out

    def position_channel(self) -> str | None:
        return next((e.name for e in self.entries.values() if e.role == "position"), None)


# --- targets ----------------------------------------------------------------------------------



    def carry_over(self, previous: SensorTable) -> None:
        """Keep the last reading of every channel ``previous`` had with the same role (a reload)."""
        for name, entry in self.entries.items():
            old = previous.entries.get(name)
            if old is not None and old.role == entry.role:
                entry.value, entry.t = old.value, old.t
                entry.device_state, entry.reason = old.device_state, old.reason

    def latest_temperatures(self) -> tuple[float, dict[str, float]] | None:
        """The good temperature readings and the time of the newest, or None if there are none."""
        temps = {n: e.value for n, e in self.entries.items()
                 if e.role == "temperature" and e.device_state == State.OK and e.value is not None}
        times = [e.t for n, e in self.entries.items() if n in temps and e.t is not None]
        return (max(times), temps) if temps and times else None
