"""A move's sub-commands are computed in one place (``nanodrift.calibration.plans.ramp_commands``): the
procedure sends them on the cell's clock and the simulated run uses the same numbers."""

from __future__ import annotations

import asyncio

import numpy as np
import pytest

from nanodrift.calibration.plans import PAPER_TIMING, StepTiming, ramp_commands
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator, DriverContext
from nanodrift.drivers.simulated.clock import VirtualClock
from nanodrift.drivers_set import DriverSet
from nanodrift.procedure.steps import ramp


def test_the_paper_ramp_is_sixteen_equal_steps_ending_at_the_target() -> None:
    offsets, commands = ramp_commands(30.0, 60.0, PAPER_TIMING.ramp_s, PAPER_TIMING.ramp_interval_s)
    assert offsets.tolist() == [0.25 * k for k in range(1, 17)]
    assert commands == pytest.approx(np.linspace(30.0, 60.0, 17)[1:], abs=1e-12)
    assert commands[-1] == 60.0
    assert ramp_commands(0.0, 5.0, 0.1, 0.25)[1].tolist() == [5.0]  # shorter than one interval: one command


class Recording(Actuator):
    def __init__(self, clock: VirtualClock) -> None:
        self.clock = clock
        self.sent: list[tuple[float, float]] = []  # (clock time, q_um)

    async def open(self) -> None: ...

    async def close(self) -> None: ...

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        self.sent.append((self.clock.now(), q_um))


@pytest.mark.parametrize("slew_um_per_s", [0.0, 2.5])
def test_the_procedure_sends_exactly_the_planned_sub_commands(slew_um_per_s: float) -> None:
    timing = StepTiming(ramp_s=4.0, ramp_interval_s=0.25)
    limits = ActuatorConfig(max_slew_um_per_s=slew_um_per_s)

    async def body() -> list[tuple[float, float]]:
        clock = VirtualClock(start=100.0)
        actuator = Recording(clock)
        drivers = DriverSet(context=DriverContext(clock=clock), groups=[], roles={},
                            max_age_s={}, actuators={"x": actuator})
        await ramp(drivers, {"x": limits}, {"x": 10.0}, {"x": 40.0}, timing)
        return actuator.sent

    sent = asyncio.run(body())
    duration = 12.0 if slew_um_per_s else 4.0  # 30 um at 2.5 um/s stretches the 4 s ramp
    offsets, commands = ramp_commands(10.0, 40.0, duration, timing.ramp_interval_s)
    assert [q for _, q in sent] == commands.tolist()
    assert [t - 100.0 for t, _ in sent] == pytest.approx(offsets.tolist(), abs=1e-9)
