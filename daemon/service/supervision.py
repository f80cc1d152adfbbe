"""Supervision on the asyncio loop: sensor state changes, systemd's watchdog and status line, log summaries.

- :class:`SensorWatch` logs each change of state (ok / stale / fault), one line for the channels
  that changed together with the same reason (a hub failure is one line, not one per channel), and publishes a
  ``stale`` telemetry sample when a channel goes quiet (a silent device sends nothing else).
- :class:`Supervisor` runs every ``SUPERVISE_INTERVAL_S``: the watchdog ping (only while healthy,
  so systemd restarts a daemon whose pollers died or stalled), the status line, and the summaries
  of refused targets and actuator failures that the rate-limited logs suppressed.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass, field
from typing import Any

from nanodrift.bus.protocol import encode_telemetry
from nanodrift.drivers.base import State
from nanodrift.logs import RateLimitedLog
from nanodrift.sdnotify import Notifier, watchdog_interval_s
from nanodrift.service.sensors import PublishTelemetry
from nanodrift.service.state import CellState

SUPERVISE_INTERVAL_S = 0.25
STATUS_INTERVAL_S = 5.0
SUPPRESSED_SUMMARY_S = 2.0  # how often "N refused targets not logged" is written during a flood


@dataclass(eq=False)
class SensorWatch:
    """Remembers each channel's last state and reports the changes."""

    state: CellState
    publish_telemetry: PublishTelemetry
    log: Any
    _states: dict[str, str] = field(default_factory=dict, init=False)

    def forget(self) -> None:
        """The table was replaced (a reload): every channel's state is news again."""
        self._states = {}

    def check(self) -> None:
        state = self.state
        with state.lock:
            now = state.clock.now()
            table = state.table
            states = [(name, entry, *table.state(name, now)) for name, entry in table.entries.items()]
        # channels that changed together (one device failing takes all of its channels) make one line
        changed: dict[tuple[str, str | None, str], list[str]] = {}
        for name, entry, channel_state, reason in states:
            previous = self._states.get(name)
            if previous == channel_state.value:
                continue
            self._states[name] = channel_state.value
            if previous is None and channel_state == State.STALE and entry.t is None:
                continue  # starting up: nothing read yet is not news
            changed.setdefault((channel_state.value, previous, reason), []).append(name)
            if channel_state == State.STALE:
                self.publish_telemetry(entry.role, name, encode_telemetry(entry.value, entry.unit, entry.t,
                                                                          "stale", reason))
        for (new_state, previous, reason), names in changed.items():
            log = self.log.info if new_state == State.OK.value else self.log.warning
            log("sensor_state", channels=names, state=new_state, was=previous, reason=reason,
                **({"channel": names[0]} if len(names) == 1 else {}))


#: a change of the wall clock against the monotonic clock larger than this is a step (NTP slews by far less)
CLOCK_STEP_S = 1.0


class ClockStepWatch:
    """Notices a step of the wall clock (NTP, ``date -s``) and logs it once (``clock_step``).

    The daemon decides on its monotonic clock, so a step changes nothing it computes; this only tells
    the operator why the labels (payload ``t``, record dates) jumped.
    """

    def __init__(self, log: Any) -> None:
        self.log = log
        self._offset_s = time.time() - time.monotonic()

    def check(self) -> float | None:
        """The step since the last check, in seconds (None: no step)."""
        offset_s = time.time() - time.monotonic()
        step_s = offset_s - self._offset_s
        if abs(step_s) <= CLOCK_STEP_S:
            return None
        self._offset_s = offset_s
        self.log.warning("clock_step", step_s=round(step_s, 3), wall_t=round(time.time(), 3),
                         note="the wall clock only labels (payload t, record dates): no command, reading age, "
                         "ramp or retention depends on it")
        return step_s


@dataclass(eq=False)
class Supervisor:
    """The periodic task; ``healthy`` says whether the pollers make progress."""

    watch: SensorWatch
    notifier: Notifier
    log: Any
    _: KW_ONLY
    healthy: Callable[[], bool]
    status_line: Callable[[], str]
    refusals_suppressed: Callable[[], int]
    actuator_failures: RateLimitedLog

    def __post_init__(self) -> None:
        self.clock_watch = ClockStepWatch(self.log)

    async def run(self) -> None:
        watchdog = watchdog_interval_s()
        last_ping = last_status = last_summary = 0.0
        while True:
            now_mono = time.monotonic()
            self.clock_watch.check()
            self.watch.check()
            if watchdog is not None and now_mono - last_ping >= watchdog and self.healthy():
                self.notifier.watchdog()
                last_ping = now_mono
            if now_mono - last_summary >= SUPPRESSED_SUMMARY_S:
                suppressed = self.refusals_suppressed()
                if suppressed:
                    self.log.warning("target_refused_suppressed", suppressed=suppressed)
                self.actuator_failures.flush()
                last_summary = now_mono
            if now_mono - last_status >= STATUS_INTERVAL_S:
                self.notifier.status(self.status_line())
                last_status = now_mono
            await asyncio.sleep(SUPERVISE_INTERVAL_S if watchdog is None else min(SUPERVISE_INTERVAL_S, watchdog))
