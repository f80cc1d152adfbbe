"""Polling every sensor group on its own schedule during a step's hold, and averaging its window."""

from __future__ import annotations

import asyncio
import contextlib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import numpy as np

from nanodrift.drivers.base import DeviceError, Reading, SensorGroup, State
from nanodrift.drivers_set import DriverSet


@dataclass(slots=True)
class _Sample:
    t: float  # when polled (backend clock)
    reading: Reading


@dataclass
class Sampler:
    """Polls every group on its own schedule during holds and keeps the samples of the current step."""

    drivers: DriverSet
    samples: dict[str, list[_Sample]] = field(default_factory=dict)
    latest: dict[str, Reading] = field(default_factory=dict)
    on_temperatures: Callable[[float, dict[str, float]], None] | None = None
    #: per channel, (when polled, true value) from groups that know the truth (a simulated cell); else empty
    truth: dict[str, list[tuple[float, float]]] = field(default_factory=dict)
    _broken: set[int] = field(default_factory=set)
    #: the drivers' temperature channels, asked once (a poll asks for each reading)
    _temperature_channels: frozenset[str] = field(init=False)

    def __post_init__(self) -> None:
        self._temperature_channels = frozenset(self.drivers.temperature_channels)

    async def open(self) -> None:
        for group in self.drivers.groups:
            await group.open()

    async def close(self) -> None:
        for group in self.drivers.groups:
            with contextlib.suppress(Exception):  # closing must not hide the error that brought us here
                await group.close()

    async def poll(self, group: SensorGroup) -> None:
        now = self.drivers.clock.now()
        key = id(group)
        try:
            if key in self._broken:
                await group.close()
                await group.open()
                self._broken.discard(key)
            async with asyncio.timeout(group.timeout_s):
                readings = await group.read()
        except (DeviceError, TimeoutError, OSError) as err:
            self._broken.add(key)
            reason = f"device error: {err}" if str(err) else f"device error: {type(err).__name__}"
            readings = {name: Reading.fault(now, reason) for name in group.names}
        else:
            truth = group.true_values()
            if truth:
                for name, value in truth.items():
                    self.truth.setdefault(name, []).append((now, value))
        temperature_channels = self._temperature_channels
        samples, latest = self.samples, self.latest
        temps: dict[str, float] = {}
        for name, reading in readings.items():
            samples.setdefault(name, []).append(_Sample(now, reading))
            if reading.state is State.OK and math.isfinite(reading.value):
                latest[name] = reading
                if name in temperature_channels:
                    temps[name] = reading.value
        if temps and self.on_temperatures is not None:
            self.on_temperatures(now, temps)

    async def sample_for(self, duration_s: float, groups: Sequence[SensorGroup] | None = None) -> None:
        """Poll ``groups`` (default: all) each at its interval for ``duration_s`` of backend time."""
        clock = self.drivers.clock
        start = clock.now()
        end = start + duration_s
        # each group once (a group named twice is still polled once a period), with its next poll's time
        polled = list({id(g): g for g in (self.drivers.groups if groups is None else groups)}.values())
        if not polled:
            await clock.sleep(duration_s)
            return
        due = [start] * len(polled)
        while True:
            t_next = min(due)
            if t_next > end + 1e-9:
                break
            wait = t_next - clock.now()
            if wait > 0:
                await clock.sleep(wait)
            for k, group in enumerate(polled):
                if due[k] <= t_next + 1e-9:
                    await self.poll(group)
                    due[k] += group.interval_s
        if end - clock.now() > 0:
            await clock.sleep(end - clock.now())

    def window(self, channels: Sequence[str], start: float, end: float) -> tuple[dict[str, float], str]:
        """Averages over [start, end] per channel, or a problem if any sample there is not clean."""
        means: dict[str, float] = {}
        for name in channels:
            inside = [s for s in self.samples.get(name, []) if start - 1e-9 <= s.t <= end + 1e-9]
            if not inside:
                return means, f"{name}: no sample in the averaging window"
            max_age = self.drivers.max_age_s.get(name, math.inf)
            for s in inside:
                if s.reading.state is not State.OK or not math.isfinite(s.reading.value):
                    return means, f"{name}: {s.reading.reason or s.reading.state.value} at t={s.t:.1f}"
                if s.t - s.reading.t > max_age:
                    return means, f"{name}: stale (reading {s.t - s.reading.t:.1f} s old > max_age_s {max_age:g})"
            means[name] = float(np.mean([s.reading.value for s in inside]))
        return means, ""

    def clear(self) -> None:
        """Forget the samples (and true values) of the step before: a new window starts."""
        self.samples.clear()
        self.truth.clear()

    def true_mean(self, channel: str, start: float, end: float) -> float:
        """The mean true value of ``channel`` over [start, end]; nan when its group does not know the truth."""
        inside = [v for t, v in self.truth.get(channel, []) if start - 1e-9 <= t <= end + 1e-9]
        return float(np.mean(inside)) if inside else math.nan

    def fallback(self, channels: Sequence[str], start: float, end: float) -> dict[str, float]:
        """For an invalid step: means of the clean samples, else the last clean value, else 0."""
        out: dict[str, float] = {}
        for name in channels:
            good = [s.reading.value for s in self.samples.get(name, [])
                    if start - 1e-9 <= s.t <= end + 1e-9 and s.reading.state is State.OK
                    and math.isfinite(s.reading.value)]
            last = self.latest.get(name)
            out[name] = float(np.mean(good)) if good else (last.value if last else 0.0)
        return out
