"""``nanodrift.procedure.sampler``: every group polled on its own schedule during a hold (on a virtual clock:
no wall time), a failing device recorded as fault samples and reopened, and the window's averages
refused when a sample in it is not clean."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable
from typing import Any

import pytest

from nanodrift.drivers.base import Actuator, Clock, DeviceError, DriverContext, Reading, SensorGroup, State
from nanodrift.drivers.simulated.clock import VirtualClock
from nanodrift.procedure import sampler as sampler_module
from nanodrift.procedure.sampler import Sampler

#: the sampler's own name for the drivers it polls (wherever that class lives)
DriverSet = sampler_module.DriverSet


class Group(SensorGroup):
    """Channels whose value is ``value(t)``; ``fail`` makes reads raise, ``hang`` makes them never return."""

    def __init__(self, clock: Clock, names: tuple[str, ...], interval_s: float,
                 value: Callable[[float], float] = lambda t: 21.0, roles: dict[str, str] | None = None) -> None:
        self.clock = clock
        self.names = names
        self.roles = roles or dict.fromkeys(names, "temperature")
        self.interval_s = interval_s
        self.timeout_s = 1.0
        self.value = value
        self.reads: list[float] = []
        self.calls: list[str] = []
        self.fail: Exception | None = None
        self.hang = False
        self.faulted: set[str] = set()

    async def open(self) -> None:
        self.calls.append("open")

    async def close(self) -> None:
        self.calls.append("close")

    async def read(self) -> dict[str, Reading]:
        now = self.clock.now()
        self.reads.append(now)
        if self.fail is not None:
            raise self.fail
        if self.hang:
            await asyncio.Event().wait()
        return {name: Reading.fault(now, "burnout") if name in self.faulted else Reading(self.value(now), t=now)
                for name in self.names}


class Output(Actuator):
    def __init__(self) -> None:
        self.calls: list[str] = []

    async def open(self) -> None:
        self.calls.append("open")

    async def close(self) -> None:
        self.calls.append("close")
        raise DeviceError("already gone")

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None: ...


def drivers(clock: VirtualClock, *groups: Group, actuator: Actuator | None = None,
            max_age_s: dict[str, float] | None = None) -> Any:
    roles = {name: role for group in groups for name, role in group.roles.items()}
    return DriverSet(context=DriverContext(clock=clock), groups=list(groups), roles=roles,
                     max_age_s=max_age_s or {}, actuators={"x": actuator} if actuator else {})


def run(body: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(body(), 10))


def test_each_group_is_polled_at_its_own_interval_for_the_hold_on_the_backend_clock() -> None:
    async def body() -> None:
        clock = VirtualClock(1000.0)
        fast = Group(clock, ("T1", "T2"), 1.0, value=lambda t: t - 1000.0)
        slow = Group(clock, ("ifm",), 2.5, roles={"ifm": "position"})
        sampler = Sampler(drivers(clock, fast, slow))
        seen: list[tuple[float, dict[str, float]]] = []
        sampler.on_temperatures = lambda t, temps: seen.append((t, temps))
        await sampler.sample_for(10.0)
        assert clock.now() == pytest.approx(1010.0)  # the hold lasts its duration, no more
        assert fast.reads == pytest.approx([1000.0 + k for k in range(11)])
        assert slow.reads == pytest.approx([1000.0, 1002.5, 1005.0, 1007.5, 1010.0])
        assert [s.t for s in sampler.samples["T1"]] == pytest.approx(fast.reads)
        assert len(seen) == 11 and all(set(temps) == {"T1", "T2"} for _, temps in seen)  # no position in it
        means, problem = sampler.window(["T1", "ifm"], 1002.0, 1006.0)
        assert problem == "" and means == {"T1": pytest.approx(4.0), "ifm": pytest.approx(21.0)}

    run(body)


def test_a_device_error_is_a_fault_sample_and_the_group_is_reopened_on_the_next_poll() -> None:
    async def body() -> None:
        clock = VirtualClock(0.0)
        group = Group(clock, ("T1",), 1.0)
        sampler = Sampler(drivers(clock, group))
        await sampler.poll(group)
        group.fail = DeviceError("port vanished")
        await sampler.poll(group)
        [_, bad] = sampler.samples["T1"]
        assert bad.reading.state is State.FAULT and bad.reading.reason == "device error: port vanished"
        assert group.calls == []  # not reopened yet
        group.fail = None
        await sampler.poll(group)
        assert group.calls == ["close", "open"]  # reopened before the next read
        assert sampler.samples["T1"][-1].reading.state is State.OK
        assert sampler.latest["T1"].value == 21.0
        group.hang = True  # a read that never returns is cut at timeout_s
        await sampler.poll(group)
        assert sampler.samples["T1"][-1].reading.reason == "device error: TimeoutError"

    run(body)


def test_a_window_with_a_faulted_stale_or_missing_sample_is_refused_and_the_fallback_keeps_the_clean() -> None:
    async def body() -> None:
        clock = VirtualClock(0.0)
        group = Group(clock, ("T1",), 1.0, value=lambda t: 20.0 + t)
        sampler = Sampler(drivers(clock, group, max_age_s={"T1": 5.0}))
        for _ in range(3):
            await sampler.poll(group)  # 20, 21, 22 at t = 0, 1, 2
            await clock.sleep(1.0)
        group.faulted = {"T1"}
        await sampler.poll(group)  # t = 3: a fault
        assert sampler.window(["T1"], 0.0, 2.0) == ({"T1": pytest.approx(21.0)}, "")
        _, problem = sampler.window(["T1"], 0.0, 3.0)
        assert problem == "T1: burnout at t=3.0"
        assert sampler.window(["T1"], 10.0, 12.0)[1] == "T1: no sample in the averaging window"
        assert sampler.fallback(["T1"], 0.0, 3.0) == {"T1": pytest.approx(21.0)}  # the clean ones
        assert sampler.fallback(["T1"], 3.0, 3.0) == {"T1": 22.0}  # none clean: the last clean value
        assert sampler.fallback(["T9"], 0.0, 3.0) == {"T9": 0.0}

        old = Group(clock, ("T2",), 1.0)
        stale = Sampler(drivers(clock, old, max_age_s={"T2": 5.0}))
        stale.samples["T2"] = [sampler_module._Sample(20.0, Reading(21.0, t=10.0))]  # read 10 s before polled
        assert stale.window(["T2"], 19.0, 21.0)[1] == "T2: stale (reading 10.0 s old > max_age_s 5)"

    run(body)


def test_open_opens_every_group_and_close_closes_every_group_whatever_fails() -> None:
    """The sampler owns the sensor groups; the outputs are the procedure's (``run_steps`` opens each axis')."""
    async def body() -> None:
        clock = VirtualClock(0.0)
        a, b = Group(clock, ("T1",), 1.0), Group(clock, ("T2",), 1.0)
        output = Output()
        sampler = Sampler(drivers(clock, a, b, actuator=output))
        await sampler.open()
        assert a.calls == b.calls == ["open"] and output.calls == []

        async def broken_close() -> None:
            raise OSError("gone")

        a.close = broken_close  # type: ignore[method-assign]
        await sampler.close()  # a group's failure does not escape, nor keep the others open
        assert b.calls == ["open", "close"]

    run(body)


def test_a_hold_without_groups_just_waits() -> None:
    async def body() -> None:
        clock = VirtualClock(50.0)
        sampler = Sampler(drivers(clock))
        await sampler.sample_for(7.5)
        assert clock.now() == 57.5 and sampler.samples == {}
        assert math.isfinite(clock.now())

    run(body)
