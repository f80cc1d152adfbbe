"""The poller's back-off is the only one between the daemon and a device, and a failure episode is one log line.

A Modbus group on a real TCP port nobody listens on (connection refused at once), then a pymodbus
server started on that port. The poller's waits between reopen attempts go through a virtual clock
that records them and takes no wall time, so the back-off's growth is read exactly.
"""

from __future__ import annotations

import asyncio
import math
import time
from types import MappingProxyType

from helpers.log_capture import captured_logging, json_lines
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer, free_port, tcp_context

from nanodrift.compensation import Compensator
from nanodrift.config import ActuatorConfig, Config
from nanodrift.drivers.base import DeviceError, MonotonicClock, Reading, SensorGroup, State
from nanodrift.drivers.modbus.config import ModbusSensorConfig
from nanodrift.drivers.modbus.group import ModbusBlockGroup
from nanodrift.drivers.modbus.plugin import PLUGIN
from nanodrift.logs import get_logger
from nanodrift.service.polling import GroupPoller, first_attempts
from nanodrift.service.sensors import SensorIngest
from nanodrift.service.state import CellState
from nanodrift.service.table import SensorTable

DEAD_WAITS = 8  # reopen attempts that fail before the module comes back


class RetryClock:
    """A virtual clock for the poller's waits between attempts: each wait is recorded with the hub's
    connection attempts so far, advances virtual time and returns at once; from ``hold_at`` waits on,
    it holds the poller until :meth:`release` (the test changes the world meanwhile)."""

    def __init__(self, group: ModbusBlockGroup, hold_at: int) -> None:
        self.group = group
        self.hold_at = hold_at
        self.t = 1000.0
        self.waits: list[tuple[float, int]] = []  # (seconds asked, hub connection attempts when asked)
        self.holding = asyncio.Event()
        self._released = asyncio.Event()

    def now(self) -> float:
        return self.t

    async def sleep(self, seconds: float) -> None:
        self.waits.append((seconds, self.group.hub.connect_attempts))
        self.t += seconds
        if len(self.waits) % self.hold_at == 0:
            self.holding.set()
            await self._released.wait()
            self._released.clear()
        await asyncio.sleep(0)

    def release(self) -> None:
        self.holding.clear()
        self._released.set()


def modbus_group(port: int) -> ModbusBlockGroup:
    configs = [ModbusSensorConfig(name=f"T{i + 1}", hub="adam", address=i, input_type="input", scale=0.1,
                                  interval_s=0.05, timeout_s=0.5) for i in range(2)]
    [group] = PLUGIN.create(configs, tcp_context(port, timeout_s=0.3))
    assert isinstance(group, ModbusBlockGroup)
    return group


def expected_backoff_s(k: int) -> float:
    return min(GroupPoller.INITIAL_BACKOFF_S * 2.0**k, GroupPoller.MAX_BACKOFF_S)


def test_a_dead_device_is_retried_at_growing_intervals_by_exactly_one_back_off() -> None:
    port = free_port()  # nobody listens: every attempt is refused at once
    group = modbus_group(port)
    failures: list[tuple[str, float, int]] = []
    recovered: list[tuple[int, float]] = []
    back = asyncio.Event()

    def on_recovered(g: SensorGroup, n: int, down_s: float) -> None:
        recovered.append((n, down_s))
        back.set()

    async def body() -> None:
        clock = RetryClock(group, hold_at=DEAD_WAITS)
        poller = GroupPoller(group, MonotonicClock(), lambda g, r: None,
                             lambda g, reason, delay, n: failures.append((reason, delay, n)), on_recovered,
                             retry_clock=clock)
        poller.start()
        server = ModbusTestServer([ModbusTestDevice(1)], port=port)
        try:
            await asyncio.wait_for(clock.holding.wait(), 20)
            waits = list(clock.waits)
            await server.start()
            await server.set_registers(1, 0, [215, 216])
            clock.release()
            await asyncio.wait_for(back.wait(), 20)
        finally:
            await poller.stop()
            await server.stop()
        assert len(waits) == DEAD_WAITS
        # the waits double from 0.2 s, each within the jitter band: one exponential back-off ...
        for k, (seconds, _) in enumerate(waits):
            assert (1 - GroupPoller.JITTER) * expected_backoff_s(k) <= seconds <= (
                (1 + GroupPoller.JITTER) * expected_backoff_s(k)), (k, seconds)
        assert waits[-1][0] > 20 * waits[0][0]
        # ... and exactly one connection attempt per wait: no driver-side wait refusing a poll without
        # trying (the attempts would stall), no driver-side retry loop (they would jump)
        assert [attempts for _, attempts in waits] == list(range(1, DEAD_WAITS + 1))
        assert [n for _, _, n in failures] == list(range(1, DEAD_WAITS + 1))
        assert {reason for reason, _, _ in failures} == {f"modbus hub 'adam': cannot connect to 127.0.0.1:{port}"}
        assert [delay for _, delay, _ in failures] == [seconds for seconds, _ in waits]  # what is logged is waited
        # back: the next attempt connects, and the episode's summary covers it all
        assert group.hub.connect_attempts == DEAD_WAITS + 1
        [(n, down_s)] = recovered
        assert n == DEAD_WAITS
        assert math.isclose(down_s, sum(seconds for seconds, _ in waits))

    asyncio.run(asyncio.wait_for(body(), 60))


def test_a_failure_episode_is_one_log_line_and_a_summary_at_recovery() -> None:
    port = free_port()
    group = modbus_group(port)
    device = ModbusTestDevice(1)
    server = ModbusTestServer([device], port=port)
    names = list(group.names)

    async def body() -> None:
        table = SensorTable(list(group.block.channels))
        state = CellState(Config(), Compensator(None, {"x": ActuatorConfig()}, table), MonotonicClock())
        ingest = SensorIngest(state, lambda role, channel, payload: None, get_logger())
        clock = RetryClock(group, hold_at=DEAD_WAITS)
        back = asyncio.Event()

        def on_recovered(g: SensorGroup, n: int, down_s: float) -> None:
            ingest.on_group_recovered(g, n, down_s)
            back.set()

        poller = GroupPoller(group, MonotonicClock(), ingest.on_readings, ingest.on_group_failure, on_recovered,
                             retry_clock=clock)
        poller.start()
        try:
            for _episode in range(2):  # dead from the start, then the module goes away once more
                await asyncio.wait_for(clock.holding.wait(), 20)
                await server.start()
                await server.set_registers(1, 0, [215, 216])
                back.clear()
                clock.release()
                await asyncio.wait_for(back.wait(), 20)
                await server.stop()  # the next read finds the link gone: a new episode
        finally:
            await poller.stop()
            await server.stop()

    with captured_logging("info") as stream:
        asyncio.run(asyncio.wait_for(body(), 60))
        docs = json_lines(stream)
    failed = [d for d in docs if d["event"] == "sensor_group_failed"]
    summaries = [d for d in docs if d["event"] == "sensor_group_recovered"]
    assert len(failed) == 2 and len(summaries) == 2, [d["event"] for d in docs]  # 16 failed attempts in all
    assert all(d["channels"] == names and d["level"] == "warning" for d in failed)
    assert failed[0]["reason"] == f"modbus hub 'adam': cannot connect to 127.0.0.1:{port}"
    assert not any(word in failed[0]["reason"] for word in ("next", " in ", "0.0 s"))  # timing is retry_in_s's
    first_s, jitter = GroupPoller.INITIAL_BACKOFF_S, GroupPoller.JITTER
    low, high = (1 - jitter) * first_s, (1 + jitter) * first_s
    assert low - 0.005 <= failed[0]["retry_in_s"] <= high + 0.005  # the log rounds to 0.01 s
    assert [d["failures"] for d in summaries] == [DEAD_WAITS, DEAD_WAITS]
    assert all(d["channels"] == names and d["down_s"] > 0 for d in summaries)
    assert not [d for d in docs if d["event"] == "sensor_group_retry_failed"]  # debug lines, not at info
    assert not [d for d in docs if str(d.get("logger", "")).startswith("pymodbus")]  # no per-attempt chatter
    order = [d["event"] for d in docs if d["event"] in ("sensor_group_failed", "sensor_group_recovered")]
    assert order == ["sensor_group_failed", "sensor_group_recovered"] * 2


def test_only_the_first_failure_of_an_episode_is_a_warning() -> None:
    """The ingest's rule on its own: the poller's count decides the level; every failure faults the channels."""
    group = modbus_group(free_port())
    state = CellState(Config(), Compensator(None, {"x": ActuatorConfig()}, SensorTable(list(group.block.channels))),
                      MonotonicClock())
    with captured_logging("info") as stream:
        ingest = SensorIngest(state, lambda role, channel, payload: None, get_logger())
        for n in range(1, 6):
            ingest.on_group_failure(group, f"link down ({n})", 0.2 * n, n)
        docs = json_lines(stream)
    assert [(d["event"], d["reason"]) for d in docs] == [("sensor_group_failed", "link down (1)")]
    assert state.table.state("T1", 0.0)[1] == "device error: link down (5)"


class SlowFirstRead(SensorGroup):
    """A device whose first read takes ``first_read_s`` (a module waking up), or whose open fails."""

    names = ("T1",)
    roles = MappingProxyType({"T1": "temperature"})
    interval_s = 0.05
    timeout_s = 2.0

    def __init__(self, first_read_s: float, *, dead: bool = False) -> None:
        self.first_read_s = first_read_s
        self.dead = dead
        self.reads = 0

    async def open(self) -> None:
        if self.dead:
            raise DeviceError("no such module")

    async def read(self) -> dict[str, Reading]:
        if self.reads == 0:
            await asyncio.sleep(self.first_read_s)
        self.reads += 1
        return {"T1": Reading(value=21.5, t=time.monotonic(), state=State.OK)}

    async def close(self) -> None:
        return None


def test_the_daemon_waits_for_each_devices_first_attempt_read_or_failed_before_it_serves() -> None:
    """What ``Service.run`` awaits before it logs ``serving`` and tells systemd READY: every group has
    been read once (its readings delivered) or has failed once, within a limit for a hung device."""
    delivered: list[int] = []
    failed: list[str] = []

    async def main() -> tuple[float, float]:
        slow, dead = SlowFirstRead(0.4), SlowFirstRead(0.0, dead=True)
        pollers = [GroupPoller(g, MonotonicClock(), lambda g, r: delivered.append(g.reads),
                               lambda g, reason, delay, n: failed.append(reason)) for g in (slow, dead)]
        for poller in pollers:
            poller.start()
        started = time.monotonic()
        await first_attempts(pollers, limit_s=5.0)
        waited = time.monotonic() - started
        # the slow device's first readings are in (the dead one may have been retried meanwhile)
        assert delivered == [1] and failed and set(failed) == {"no such module"}
        hung = GroupPoller(SlowFirstRead(60.0), MonotonicClock(), lambda g, r: None, lambda *a: None)
        hung.start()
        started = time.monotonic()
        await first_attempts([hung], limit_s=0.3)  # a device that hangs does not hold the daemon for ever
        bounded = time.monotonic() - started
        for poller in [*pollers, hung]:
            await poller.stop()
        return waited, bounded

    waited, bounded = asyncio.run(main())
    assert waited >= 0.4 and bounded < 5.0
