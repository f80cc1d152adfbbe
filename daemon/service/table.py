"""The latest reading of every configured channel and the daemon's judgement of it: ok, stale or fault.

The one place a reading is judged: a driver says what the device said, the daemon says whether it
believes it enough to compute a command (or a health residual) from it. Judged when it arrives
(:meth:`SensorTable.update`, on the loop), never per target, with the daemon's cell clock:

- ``fault``: the device said so; or the value is non-finite or outside the sensor's valid range
  (``valid_min``/``valid_max``, defaults in :func:`nanodrift.config.valid_range`); or the reading is
  stamped more than :data:`FUTURE_TOLERANCE_S` ahead of the daemon's clock. The last believed
  value is kept (shown in ``status``), never the rejected one.
- ``stale``: nothing read yet; the last reading older than ``max_age_s`` (judged in :meth:`state`, as
  time passes); or the value bit-identical across readings spanning more than ``frozen_after_s``
  (a dead instrument repeating its last value).

So the table's ``value`` of an ``ok`` channel is always finite and inside its valid range.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from nanodrift.config import valid_range
from nanodrift.drivers.base import Reading, SensorConfig, State

UNITS = {"temperature": "degC", "position": "um"}
#: a reading stamped further ahead of the daemon's clock than this is a fault (its clock is wrong): more
#: than any poll's latency, less than anything that would keep a dead value "fresh" for long
FUTURE_TOLERANCE_S = 1.0


@dataclass(slots=True)
class ChannelEntry:
    name: str
    role: str
    unit: str
    max_age_s: float
    valid_min: float = -math.inf
    valid_max: float = math.inf
    frozen_after_s: float = 0.0  # 0: off
    value: float | None = None  # the last believed value (finite, inside the valid range)
    t: float | None = None
    #: the daemon's judgement of the last reading (STALE here means: nothing read yet, or frozen)
    device_state: State = State.STALE
    reason: str = "no reading yet"
    value_since_t: float | None = None  # stamp of the first reading of the current value (frozen check)

    def judge(self, value: float) -> str:
        """Why ``value`` is not believed ("" when it is)."""
        if not math.isfinite(value):
            return f"non-finite value {value}"
        if not self.valid_min <= value <= self.valid_max:
            return (f"reading {value:g} {self.unit} outside the valid range [{self.valid_min:g}, {self.valid_max:g}] "
                    f"{self.unit} (valid_min/valid_max)")
        return ""


class SensorTable:
    """The latest reading of each configured channel.

    ``workspace_um`` (the actuator's ``[x_min_um, x_max_um]``) gives a position sensor that declares no
    valid range its default one; without it such a sensor is judged on finiteness only.
    """

    def __init__(self, sensors: Sequence[SensorConfig], workspace_um: tuple[float, float] | None = None,
                 sensor_workspaces: Mapping[str, tuple[float, float]] | None = None) -> None:
        """``sensor_workspaces``: a multi-axis cell's position sensors, each judged on its own axis' workspace."""
        own = sensor_workspaces or {}
        self.entries: dict[str, ChannelEntry] = {
            s.name: ChannelEntry(s.name, s.role, UNITS.get(s.role, ""), s.max_age_s,
                                 *valid_range(s, own.get(s.name, workspace_um)), s.frozen_after_s)
            for s in sensors
        }
        #: bumped by every change, so readers can cache what they derive from the entries
        self.version = 0

    def update(self, name: str, reading: Reading, now: float | None = None) -> ChannelEntry | None:
        """Judge ``reading`` at ``now`` (the daemon's clock; None: at the reading's own stamp, so it is
        never in the future) and keep it; None when no sensor has that name."""
        entry = self.entries.get(name)
        if entry is None:
            return None
        self.version += 1
        entry.t = reading.t
        if reading.unit:
            entry.unit = reading.unit
        if reading.state != State.OK:
            entry.device_state = State.FAULT
            entry.reason = reading.reason or "fault"
            return entry
        value = float(reading.value)
        ahead_s = reading.t - (reading.t if now is None else now)
        problem = entry.judge(value)
        if not problem and ahead_s > FUTURE_TOLERANCE_S:
            problem = f"reading stamped {ahead_s:.1f} s in the future (tolerance {FUTURE_TOLERANCE_S:g} s)"
        if problem:
            entry.device_state, entry.reason = State.FAULT, problem
            return entry
        if value != entry.value or entry.value_since_t is None:
            entry.value_since_t = reading.t
        entry.value = value
        frozen_s = reading.t - entry.value_since_t
        if entry.frozen_after_s > 0 and frozen_s > entry.frozen_after_s:
            entry.device_state = State.STALE
            entry.reason = (f"value frozen at {value:g} {entry.unit} for {frozen_s:.0f} s "
                            f"(frozen_after_s {entry.frozen_after_s:g})")
        else:
            entry.device_state, entry.reason = State.OK, ""
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

    def has(self, name: str) -> bool:
        return name in self.entries

    def problem(self, name: str, now: float) -> tuple[str, str] | None:
        """Why ``name`` is not ok at ``now`` (``("stale", reason)``, ``("fault", reason)``), None when it is."""
        state, reason = self.state(name, now)
        return None if state is State.OK else (state.value, reason)

    def fresh_temperatures(self, channels: Sequence[str]) -> tuple[float, dict[str, float]]:
        """The cell-clock time until which every one of ``channels`` is fresh, and their values; ``(-inf,
        {})`` when one is not ok (or has no sensor). Derived once per table change, never per target."""
        fresh_until = math.inf
        temps: dict[str, float] = {}
        for name in channels:
            entry = self.entries.get(name)
            if entry is None or entry.device_state is not State.OK or entry.t is None or entry.value is None:
                return -math.inf, {}
            fresh_until = min(fresh_until, entry.t + entry.max_age_s)
            temps[name] = entry.value
        return fresh_until, temps

    def values(self, channels: Sequence[str]) -> dict[str, float]:
        """The last believed value of each of ``channels`` that has one, whatever its state."""
        return {name: entry.value for name in channels
                if (entry := self.entries.get(name)) is not None and entry.value is not None}

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

    def carry_over(self, previous: SensorTable) -> None:
        """Keep the last reading of every channel ``previous`` had with the same role (a reload), judged
        against this table's valid range (a narrowed range faults a value it no longer believes)."""
        for name, entry in self.entries.items():
            old = previous.entries.get(name)
            if old is not None and old.role == entry.role:
                entry.value, entry.t, entry.value_since_t = old.value, old.t, old.value_since_t
                entry.device_state, entry.reason = old.device_state, old.reason
                problem = entry.judge(entry.value) if entry.value is not None else ""
                if problem and entry.device_state != State.FAULT:
                    entry.device_state, entry.reason = State.FAULT, problem

    def latest_temperatures(self) -> tuple[float, dict[str, float]] | None:
        """The good temperature readings and the time of the newest, or None if there are none."""
        temps = {n: e.value for n, e in self.entries.items()
                 if e.role == "temperature" and e.device_state == State.OK and e.value is not None}
        times = [e.t for n, e in self.entries.items() if n in temps and e.t is not None]
        return (max(times), temps) if temps and times else None
