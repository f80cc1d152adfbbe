""":class:`CellActuation`'s rules per axis, on fake outputs: a fault on one axis, the goal over a reload,
the value a device would receive checked against that axis' limits."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Callable

from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator, DeviceError
from nanodrift.logs import get_logger
from nanodrift.service.cell_actuation import CellActuation


class FakeOutput(Actuator):
    """Records what it receives; ``fail_writes`` raises on the next N writes; ``sent_offset_v`` is what its
    quantization adds to each voltage (a DAC that cannot represent the value asked for)."""

    def __init__(self, name: str, journal: list[tuple[str, float]]) -> None:
        self.description = f"fake {name}"
        self.name = name
        self.journal = journal
        self.fail_writes = 0
        self.sent_offset_v = 0.0
        self.opens = 0

    async def open(self) -> None:
        self.opens += 1

    async def close(self) -> None:
        pass

    def sent_voltage(self, voltage_v: float) -> float:
        return voltage_v + self.sent_offset_v

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        if self.fail_writes > 0:
            self.fail_writes -= 1
            raise DeviceError(f"{self.description}: no answer")
        self.journal.append((self.name, voltage_v))


def configs() -> dict[str, ActuatorConfig]:
    return {"x": ActuatorConfig(v_min=-2.0, v_max=12.0), "y": ActuatorConfig(v_min=0.0, v_max=10.0)}


async def until(condition: Callable[[], bool], what: str, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        await asyncio.sleep(0.005)


def offer(actuation: CellActuation, x_v: float, y_v: float) -> None:
    if actuation.offer({"x": x_v / 0.02, "y": y_v / 0.02}, {"x": x_v, "y": y_v}):
        actuation.wake()


def test_a_failure_on_one_axis_is_the_cells_fault_named_by_axis_and_the_goal_is_written_whole_after() -> None:
    journal: list[tuple[str, float]] = []
    outputs = {"x": FakeOutput("x", journal), "y": FakeOutput("y", journal)}

    async def scenario() -> None:
        actuation = CellActuation(get_logger("test"))
        await actuation.start(outputs, configs())
        outputs["y"].fail_writes = 1
        offer(actuation, 3.0, 4.0)
        await until(lambda: actuation.fault_reason is not None, "the fault")
        assert actuation.fault_reason is not None and actuation.fault_reason.startswith("axis y:"), \
            actuation.fault_reason
        await until(lambda: journal[-2:] == [("x", 3.0), ("y", 4.0)], "the goal written again to both axes")
        await until(lambda: actuation.fault_reason is None, "recovered")
        assert outputs["x"].opens >= 2 and outputs["y"].opens >= 2  # every axis closed and reopened
        await actuation.stop()

    asyncio.run(scenario())


def test_the_goal_is_carried_over_a_reload_to_the_new_outputs() -> None:
    journal: list[tuple[str, float]] = []
    first = {"x": FakeOutput("x", journal), "y": FakeOutput("y", journal)}
    second = {"x": FakeOutput("x2", journal), "y": FakeOutput("y2", journal)}

    async def scenario() -> None:
        actuation = CellActuation(get_logger("test"))
        await actuation.start(first, configs())
        offer(actuation, 1.0, 2.0)
        await until(lambda: ("y", 2.0) in journal, "the first goal")
        await actuation.stop()  # a reload: the drivers are stopped ...
        offer(actuation, 5.0, 6.0)  # ... a target is served meanwhile ...
        await actuation.start(second, configs())  # ... and the new outputs get it
        await until(lambda: journal[-2:] == [("x2", 5.0), ("y2", 6.0)], "the goal on the new outputs")
        await actuation.stop()

    asyncio.run(scenario())


def test_a_value_a_device_would_receive_outside_its_axis_limits_is_never_sent() -> None:
    journal: list[tuple[str, float]] = []
    outputs = {"x": FakeOutput("x", journal), "y": FakeOutput("y", journal)}
    outputs["y"].sent_offset_v = 0.5  # 9.8 V asked would be sent as 10.3 V, above y's v_max = 10

    async def scenario() -> None:
        actuation = CellActuation(get_logger("test"))
        await actuation.start(outputs, configs())
        offer(actuation, 9.8, 9.8)
        await until(lambda: actuation.fault_reason is not None, "the fault")
        assert "axis y" in (actuation.fault_reason or "") and "10.3" in (actuation.fault_reason or "")
        assert ("y", 9.8) not in journal and ("x", 9.8) not in journal  # nothing of that command, on any axis
        await actuation.stop()

    asyncio.run(scenario())


def test_the_stop_ramps_every_axis_to_its_safe_voltage() -> None:
    journal: list[tuple[str, float]] = []
    outputs = {"x": FakeOutput("x", journal), "y": FakeOutput("y", journal)}
    safe = {"x": ActuatorConfig(v_min=-2.0, v_max=12.0, safe_voltage_v=0.0, max_slew_um_per_s=200.0),
            "y": ActuatorConfig(v_min=0.0, v_max=10.0, safe_voltage_v=1.0, max_slew_um_per_s=200.0)}

    async def scenario() -> None:
        actuation = CellActuation(get_logger("test"), safe_budget_s=5.0)
        await actuation.start(outputs, safe)
        offer(actuation, 2.0, 3.0)
        await until(lambda: ("x", 2.0) in journal and ("y", 3.0) in journal, "the goal")
        del journal[:]
        await actuation.stop(final=True)

    asyncio.run(scenario())
    x_steps = [v for name, v in journal if name == "x"]
    y_steps = [v for name, v in journal if name == "y"]
    assert x_steps[-1] == 0.0 and y_steps[-1] == 1.0
    assert len(x_steps) >= 3 and all(b < a for a, b in itertools.pairwise(x_steps))  # ramped down
