"""VirtualClock scheduling and the ``simulated`` driver plugin (groups, actuator, faults)."""

from __future__ import annotations

import asyncio
import os
import signal
import time

import pytest

from nanodrift.drivers.base import DeviceError, DriverContext, State
from nanodrift.drivers.registry import load_plugin
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.clock import VirtualClock
from nanodrift.drivers.simulated.config import SimulatedActuatorConfig, SimulatedSensorConfig, SimulationConfig
from nanodrift.drivers.simulated.plugin import PLUGIN, RESOURCE_KEY, default_sensor_configs


def test_virtual_clock_interleaves_sleepers_like_real_time():
    clock = VirtualClock(start=100.0)
    log: list[tuple[str, float]] = []

    async def ticker(name: str, period: float, n: int) -> None:
        for _ in range(n):
            await clock.sleep(period)
            log.append((name, clock.now()))

    async def chatty() -> None:  # runnable work without sleeping must finish before time moves
        for _ in range(50):
            await asyncio.sleep(0)
        log.append(("chatty", clock.now()))

    async def main() -> None:
        await asyncio.gather(ticker("a", 3.0, 4), ticker("b", 5.0, 2), chatty(), ticker("c", 3600.0 * 24, 1))

    wall = time.perf_counter()
    asyncio.run(main())
    assert time.perf_counter() - wall < 1.0  # a simulated day in no time
    assert log == [("chatty", 100.0), ("a", 103.0), ("b", 105.0), ("a", 106.0), ("a", 109.0), ("b", 110.0),
                   ("a", 112.0), ("c", 100.0 + 86400.0)]


def test_virtual_clock_survives_cancelled_sleepers():
    clock = VirtualClock()

    async def main() -> float:
        sleeper = asyncio.ensure_future(clock.sleep(10.0))
        await clock.sleep(1.0)
        sleeper.cancel()
        await clock.sleep(20.0)
        return clock.now()

    assert asyncio.run(main()) == 21.0


def test_a_lone_sleeper_jumps_at_once_but_what_is_ready_or_due_runs_first_and_signals_get_in():
    """A lone sleeper skips the advancer's rounds; a callback ready or a timer due still runs at the time it was
    scheduled in, and the loop still hears a signal (Ctrl-C) while one task sleeps on and on."""
    clock = VirtualClock()
    seen: list[tuple[str, float]] = []

    async def main() -> int:
        loop = asyncio.get_running_loop()
        for _ in range(100):
            await clock.sleep(0.5)
        assert clock.now() == 50.0
        assert clock._advancer is None  # the scheduler was never needed
        loop.call_soon(lambda: seen.append(("ready", clock.now())))
        await clock.sleep(1.0)
        loop.call_later(0.0, lambda: seen.append(("due", clock.now())))
        await clock.sleep(1.0)
        assert seen == [("ready", 50.0), ("due", 51.0)] and clock.now() == 52.0
        task = asyncio.current_task()
        assert task is not None
        loop.add_signal_handler(signal.SIGUSR1, task.cancel)
        os.kill(os.getpid(), signal.SIGUSR1)
        sleeps = 0
        try:
            while True:
                await clock.sleep(1.0)
                sleeps += 1
        except asyncio.CancelledError:
            return sleeps
        finally:
            loop.remove_signal_handler(signal.SIGUSR1)

    assert asyncio.run(main()) <= VirtualClock.YIELD_EVERY


def _context(**simulation) -> DriverContext:
    section = SimulationConfig.model_validate({"scenario": "train", "seed": 4, **simulation})
    return DriverContext(clock=VirtualClock(), sections={"simulation": section})


def test_plugin_found_by_entry_point_and_shares_one_cell():
    assert load_plugin("simulated") is PLUGIN and PLUGIN.name == "simulated"
    ctx = _context()
    groups = PLUGIN.create(default_sensor_configs(), ctx)
    actuator = PLUGIN.create_actuator(SimulatedActuatorConfig(), ctx)
    assert sorted(n for g in groups for n in g.names) == ["T1", "T2", "T3", "T4", "interferometer"]
    assert len(groups) == 2  # the four thermocouples answer together, the interferometer alone
    position = next(g for g in groups if "interferometer" in g.names)

    async def main() -> tuple[float, float]:
        await actuator.open()
        await actuator.command(240.0, 4.8)
        await ctx.clock.sleep(10.0)
        reading = (await position.read())["interferometer"]
        return reading.value, reading.t

    value, t = asyncio.run(main())
    assert value == pytest.approx(240.0, abs=0.5) and t == 10.0
    cell = ctx.resources.get(RESOURCE_KEY, SimulatedCell)
    assert cell is not None and cell.commands == 1


def test_sensor_channel_mapping_and_bad_channels():
    ctx = _context()
    configs = [SimulatedSensorConfig(name="stage_temp", channel="T1"), SimulatedSensorConfig(name="air", channel="air")]
    (group,) = PLUGIN.create(configs, ctx)
    readings = asyncio.run(group.read())
    assert set(readings) == {"stage_temp", "air"} and all(r.state is State.OK for r in readings.values())
    assert readings["stage_temp"].value == pytest.approx(22.04, abs=0.05)
    with pytest.raises(ValueError, match=r"no simulated channel 'T9'.*T1, T2, T3, T4"):
        PLUGIN.create([SimulatedSensorConfig(name="T9")], ctx)
    with pytest.raises(ValueError, match="role position"):
        PLUGIN.create([SimulatedSensorConfig(name="interferometer", role="temperature")], ctx)


def test_injected_faults_reach_the_readings():
    ctx = _context()
    groups = PLUGIN.create(default_sensor_configs(), ctx)
    cell = ctx.resources.get(RESOURCE_KEY, SimulatedCell)
    assert cell is not None
    temps = next(g for g in groups if "T2" in g.names)
    cell.inject_fault("T2", 5.0, 10.0, "fault")
    cell.inject_fault("T3", 5.0, 10.0, "stale")
    cell.inject_fault("T4", 20.0, 30.0, "device_error")

    async def main() -> None:
        first = await temps.read()
        await ctx.clock.sleep(6.0)
        during = await temps.read()
        assert during["T2"].state is State.FAULT and "injected" in during["T2"].reason
        assert during["T1"].state is State.OK and during["T1"].t == 6.0
        assert during["T3"].t == first["T3"].t == 0.0  # a stale device repeats its old sample
        await ctx.clock.sleep(15.0)
        with pytest.raises(DeviceError):
            await temps.read()
        await ctx.clock.sleep(10.0)
        assert all(r.state is State.OK for r in (await temps.read()).values())

    asyncio.run(main())
