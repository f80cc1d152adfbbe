"""``nanodrift.service.supervision``: sensor state changes logged once per change (channels that change
together in one line), a wall-clock step logged once per step, and the supervisor's periodic work (the
watchdog pinged only while healthy, the status line, the summaries of what the rate-limited logs held back)."""

from __future__ import annotations

import asyncio
import os
import time
from collections.abc import Callable
from typing import Any

import pytest

from nanodrift.compensation import Compensator
from nanodrift.config import parse_config
from nanodrift.drivers.base import Reading, SensorConfig
from nanodrift.logs import RateLimitedLog, RateLimiter
from nanodrift.service import supervision
from nanodrift.service.state import CellState
from nanodrift.service.supervision import CLOCK_STEP_S, ClockStepWatch, SensorWatch, Supervisor
from nanodrift.service.table import SensorTable


class Events:
    def __init__(self) -> None:
        self.lines: list[tuple[str, str, dict[str, Any]]] = []

    def __getattr__(self, level: str) -> Callable[..., None]:
        return lambda event, **fields: self.lines.append((level, event, fields))

    def named(self, event: str) -> list[dict[str, Any]]:
        return [fields for _, name, fields in self.lines if name == event]

    def levels(self, event: str) -> list[str]:
        return [level for level, name, _ in self.lines if name == event]


class ManualClock:
    def __init__(self, t: float) -> None:
        self.t = t

    def now(self) -> float:
        return self.t

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(0)


class WallClock:
    """``time.time`` that a test steps; ``time.monotonic`` is left alone."""

    def __init__(self, monkeypatch: pytest.MonkeyPatch) -> None:
        self.offset_s = 0.0
        real = time.time
        monkeypatch.setattr(time, "time", lambda: real() + self.offset_s)


# --- SensorWatch ------------------------------------------------------------------------------------


def watched(names: tuple[str, ...] = ("T1", "T2", "T3")) -> tuple[CellState, SensorTable, ManualClock]:
    config = parse_config({"sensors": []})
    table = SensorTable([SensorConfig(name=name, kind="x", max_age_s=2.0) for name in names])
    clock = ManualClock(100.0)
    return CellState(config, Compensator(None, {"x": config.actuator}, table), clock), table, clock


def test_channels_that_change_together_are_one_line_and_an_unchanged_state_is_not_news() -> None:
    state, table, clock = watched()
    log = Events()
    telemetry: list[tuple[str, str, bytes]] = []
    watch = SensorWatch(state, lambda role, name, payload: telemetry.append((role, name, payload)), log)
    watch.check()
    assert log.lines == [] and telemetry == []  # starting up: nothing read yet is not news
    for name in ("T1", "T2", "T3"):
        table.update(name, Reading(21.0, t=100.0), now=100.0)
    watch.check()
    assert log.named("sensor_state") == [
        {"channels": ["T1", "T2", "T3"], "state": "ok", "was": "stale", "reason": ""}]
    watch.check()
    assert len(log.named("sensor_state")) == 1  # no change, no line

    table.mark_fault(["T1", "T2"], "hub 'adam': no response")  # one device, two channels
    watch.check()
    fault = log.named("sensor_state")[-1]
    assert fault == {"channels": ["T1", "T2"], "state": "fault", "was": "ok", "reason": "hub 'adam': no response"}
    assert log.levels("sensor_state")[-1] == "warning"

    clock.t = 103.0  # T3 (max_age_s 2) has gone quiet: a stale line and a stale telemetry sample
    telemetry.clear()
    watch.check()
    stale = log.named("sensor_state")[-1]
    assert stale["channels"] == ["T3"] and stale["channel"] == "T3" and stale["state"] == "stale"
    assert [(role, name) for role, name, _ in telemetry] == [("temperature", "T3")]
    assert b'"state":"stale"' in telemetry[0][2]

    count = len(log.named("sensor_state"))
    watch.forget()  # a reload: every channel's state is news again
    watch.check()
    assert len(log.named("sensor_state")) == count + 2  # the faulted pair, and T3


# --- ClockStepWatch ---------------------------------------------------------------------------------


def test_a_wall_clock_step_is_logged_once_per_step_and_a_slew_never(monkeypatch: pytest.MonkeyPatch) -> None:
    wall = WallClock(monkeypatch)
    log = Events()
    watch = ClockStepWatch(log)
    wall.offset_s = 0.5 * CLOCK_STEP_S  # NTP slewing: no step
    assert watch.check() is None
    wall.offset_s = 3600.0  # date -s an hour ahead
    step = watch.check()
    assert step == pytest.approx(3600.0, abs=0.1)
    for _ in range(5):
        assert watch.check() is None  # the same step is not news again
    wall.offset_s = 3600.0 - 30.0  # then back 30 s
    assert watch.check() == pytest.approx(-30.0, abs=0.1)
    steps = log.named("clock_step")
    assert [round(line["step_s"]) for line in steps] == [3600, -30]
    assert log.levels("clock_step") == ["warning", "warning"]


# --- Supervisor -------------------------------------------------------------------------------------


class Notifier:
    def __init__(self) -> None:
        self.pings: list[float] = []
        self.statuses: list[str] = []

    def watchdog(self) -> bool:
        self.pings.append(time.monotonic())
        return True

    def status(self, line: str) -> bool:
        self.statuses.append(line)
        return True


class Watch:
    def __init__(self) -> None:
        self.checks = 0

    def check(self) -> None:
        self.checks += 1


def test_the_supervisor_pings_only_while_healthy_and_writes_status_and_summaries(
        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(supervision, "SUPERVISE_INTERVAL_S", 0.01)
    monkeypatch.setattr(supervision, "STATUS_INTERVAL_S", 0.05)
    monkeypatch.setattr(supervision, "SUPPRESSED_SUMMARY_S", 0.05)
    monkeypatch.setenv("WATCHDOG_USEC", "40000")  # systemd's 40 ms: a ping every 20 ms
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    wall = WallClock(monkeypatch)
    log = Events()
    notifier = Notifier()
    watch = Watch()
    healthy = [True]
    suppressed = [7]
    failures = RateLimitedLog(log, "actuator_failed", RateLimiter(rate=1.0, burst=1), level="error")
    failures(error="a")
    failures(error="b")  # held back: the summary says so

    def take_suppressed() -> int:
        count, suppressed[0] = suppressed[0], 0
        return count

    supervisor = Supervisor(watch, notifier, log, healthy=lambda: healthy[0],  # type: ignore[arg-type]
                            status_line=lambda: "serving", refusals_suppressed=take_suppressed,
                            actuator_failures=failures)

    async def rounds(count: int) -> None:
        """Until the supervisor has run ``count`` more rounds (a loaded machine runs fewer per second)."""
        until = watch.checks + count
        while watch.checks < until:
            await asyncio.sleep(0.01)

    async def body() -> None:
        task = asyncio.create_task(supervisor.run())
        while len(notifier.pings) < 5:
            await asyncio.sleep(0.01)
        healthy[0] = False  # the pollers stalled: systemd must see the pings stop
        await rounds(2)  # a round under way when the flag changed may still ping
        stopped_at = len(notifier.pings)
        wall.offset_s = -120.0  # a step while running: one line, however many rounds follow
        await rounds(10)
        assert len(notifier.pings) == stopped_at
        healthy[0] = True
        await rounds(3)
        assert len(notifier.pings) > stopped_at  # healthy again: pinged again
        while len(notifier.statuses) < 5:  # STATUS_INTERVAL_S apart
            await asyncio.sleep(0.01)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(asyncio.wait_for(body(), 30))
    assert watch.checks >= 20
    assert len(notifier.statuses) >= 5 and set(notifier.statuses) == {"serving"}
    assert log.named("target_refused_suppressed") == [{"suppressed": 7}]  # once: then nothing was held back
    assert log.named("actuator_failed_suppressed") == [{"suppressed": 1}]
    [step] = log.named("clock_step")
    assert step["step_s"] == pytest.approx(-120.0, abs=0.5)


def test_without_systemds_watchdog_nothing_is_pinged(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(supervision, "SUPERVISE_INTERVAL_S", 0.01)
    monkeypatch.delenv("WATCHDOG_USEC", raising=False)
    notifier = Notifier()
    watch = Watch()
    supervisor = Supervisor(watch, notifier, Events(), healthy=lambda: True,  # type: ignore[arg-type]
                            status_line=lambda: "s", refusals_suppressed=lambda: 0,
                            actuator_failures=RateLimitedLog(Events(), "actuator_failed"))

    async def body() -> None:
        task = asyncio.create_task(supervisor.run())
        while watch.checks < 5:  # rounds, however long a loaded machine takes for them
            await asyncio.sleep(0.01)
        task.cancel()
        with pytest.raises(asyncio.CancelledError):
            await task

    asyncio.run(asyncio.wait_for(body(), 30))
    assert notifier.pings == [] and watch.checks >= 5 and notifier.statuses == ["s"]
