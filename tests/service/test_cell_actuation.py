"""A three-axis GCS controller on one pty: every axis of a command on the line before the next command's.

The config is read as an operator's (``[[axes]]`` with ``kind = "serial_line"`` on one port), the drivers
built by the assembly (one line for the three axes), and :class:`CellActuation` drives them as the daemon
does. The controller is the pty emulator answering ``SVA``/``SVA?`` for axes 1, 2 and 3.
"""

from __future__ import annotations

import asyncio
import re
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from nanodrift.assembly import build_drivers
from nanodrift.config import parse_config
from nanodrift.drivers.testing.pty_devices import FakeGcsController
from nanodrift.logs import get_logger
from nanodrift.service.cell_actuation import CellActuation

AXES = {"x": "1", "y": "2", "z": "3"}


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[FakeGcsController]:
    fake = FakeGcsController(tmp_path / "ttyPI", axes=tuple(AXES.values()))
    yield fake
    fake.close()


def three_axis_config(port: str, *, slew: float = 0.0) -> dict[str, object]:
    return {
        "cell": "xyz",
        "axes": [{"name": axis, "min_um": 0.0, "max_um": 500.0,
                  "actuator": {"kind": "serial_line", "port": port, "command": f"SVA {n} {{voltage_v:.4f}}\n",
                               "readback": f"SVA? {n}\n", "timeout_s": 0.5, "safe_voltage_v": 0.0,
                               "max_slew_um_per_s": slew}}
                 for axis, n in AXES.items()],
    }


def sva_lines(controller: FakeGcsController) -> list[tuple[str, float]]:
    return [(m[1], float(m[2])) for line in list(controller.lines) if (m := re.fullmatch(r"SVA (\d) (\S+)", line))]


async def until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.005)


def test_three_axes_share_one_line_and_each_command_is_written_whole_before_the_next(
        controller: FakeGcsController) -> None:
    config = parse_config(three_axis_config(controller.port))
    drivers = build_drivers(config)
    assert list(drivers.actuators) == ["x", "y", "z"]
    lines = {id(a.port) for a in drivers.actuators.values()}  # type: ignore[attr-defined]
    assert len(lines) == 1, "the three axes of one controller share one line (one lock)"

    goals = [{axis: round(0.5 + 0.37 * k + i, 4) for i, axis in enumerate(AXES)} for k in range(12)]

    async def scenario() -> None:
        actuation = CellActuation(get_logger("test"))
        await actuation.start(drivers.actuators, config.axis_actuators())
        try:
            for goal in goals:  # a burst: newer commands replace pending ones, never half of one
                actuation.offer({a: v / 0.02 for a, v in goal.items()}, goal)
                if actuation._active:
                    actuation.wake()
                await asyncio.sleep(0.004)
            last = goals[-1]
            await until(lambda: all(abs(controller.voltages[AXES[a]] - v) < 1e-9 for a, v in last.items()), 5,
                        "the last command on every axis")
            assert actuation.fault_reason is None
        finally:
            await actuation.stop(final=True)

    asyncio.run(scenario())
    written = sva_lines(controller)
    *served, safe = [written[i:i + 3] for i in range(0, len(written), 3)]
    assert len(written) % 3 == 0 and len(served) >= 2, written
    offered = [tuple((AXES[a], v) for a, v in goal.items()) for goal in goals]
    for group in served:  # axis 1, 2, 3 of one command, then the next command's
        assert tuple(group) in offered, (group, written)
    assert tuple(served[-1]) == offered[-1]
    assert [offered.index(tuple(g)) for g in served] == sorted(offered.index(tuple(g)) for g in served)
    assert safe == [("1", 0.0), ("2", 0.0), ("3", 0.0)]  # the safe stop: every axis at its safe_voltage_v


def test_a_slewed_three_axis_move_ramps_each_axis_at_its_own_rate_in_steps_of_whole_commands(
        controller: FakeGcsController) -> None:
    config = parse_config(three_axis_config(controller.port, slew=500.0))  # 10 V/s at 0.02 V/um
    drivers = build_drivers(config)

    async def scenario() -> float:
        actuation = CellActuation(get_logger("test"), safe_budget_s=5.0)
        await actuation.start(drivers.actuators, config.axis_actuators())
        began = time.monotonic()
        try:
            goal = {"x": 4.0, "y": 2.0, "z": 0.0}
            actuation.offer({a: v / 0.02 for a, v in goal.items()}, goal)
            actuation.wake()
            await until(lambda: abs(controller.voltages["1"] - 4.0) < 1e-9, 5, "x at 4 V")
            return time.monotonic() - began
        finally:
            await actuation.stop(final=False)

    asyncio.run(scenario())
    written = sva_lines(controller)
    x_steps = [v for n, v in written if n == "1"]
    assert len(x_steps) >= 4 and x_steps[-1] == 4.0, x_steps  # a ramp, not a jump
    # no step covers more than 10 V/s over the longest interval one step may cover (5 ramp periods)
    assert max(b - a for a, b in zip([0.0, *x_steps], x_steps, strict=False)) <= 10.0 * 0.1 + 1e-6, x_steps
    axes_in_order = [n for n, _ in written]
    assert axes_in_order[:3] == ["1", "2", "3"]  # each step writes the axes in the cell's order
    assert [v for n, v in written if n == "2"][-1] == 2.0 and all(v == 0.0 for n, v in written if n == "3")


def test_two_axes_of_one_modbus_module_share_one_connection_and_its_lock() -> None:
    axes = [{"name": axis, "min_um": 0.0, "max_um": 500.0,
             "actuator": {"kind": "modbus", "hub": "dac", "address": address, "scale": 0.001}}
            for axis, address in (("x", 10), ("y", 11))]
    config = parse_config({"cell": "xy", "axes": axes, "hubs": [{"name": "dac", "port": 5020}]})
    drivers = build_drivers(config)
    x, y = drivers.actuators["x"], drivers.actuators["y"]
    assert x.hub is y.hub  # type: ignore[attr-defined]  # one ModbusHub: one connection, one lock
    assert (x.config.address, y.config.address) == (10, 11)  # type: ignore[attr-defined]
