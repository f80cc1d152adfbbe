"""How fast a slewed ramp runs on a slow output device, against the configured rate, same run (issue 26.9).

``Actuation`` (the daemon's own) ramps one output from 0 to 6 V (300 um at 0.02 V/um) at
``--rate`` um/s; the device is an in-process actuator whose ``command`` takes ``L`` ms (0, 10, 60 and
200 ms: a local DAC, a Modbus module, a slow module or gateway). Each row gives the achieved rate as a
share of the configured one, the number of writes and the largest step, for the daemon's rule (a ramp
pauses ``LATENCY_PAUSES`` times the device's write time between steps) and for the rule it replaced (a
pause of one ramp period whatever the device: ``LATENCY_PAUSES = 0``), which is what today's main ran.
The 0 ms device is the baseline of each rule. A safe stop's duration is distance / (share x rate).

    .venv/bin/python benchmarks/slow_device_ramp.py [--rate 100]
"""

from __future__ import annotations

import argparse
import asyncio
import itertools
import time
from typing import Literal

import structlog

import nanodrift.motion as motion
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator
from nanodrift.service.actuation import Actuation

GOAL_V = 6.0
LATENCIES_S = (0.0, 0.010, 0.060, 0.200)


class SlowOutput(Actuator):
    """Takes ``latency_s`` per write; reads back what it holds (0 V at power-up)."""

    def __init__(self, latency_s: float) -> None:
        self.latency_s = latency_s
        self.description = f"output answering in {latency_s * 1000:g} ms"
        self.held_v = 0.0
        self.writes: list[tuple[float, float]] = []

    async def open(self) -> None:
        return None

    async def close(self) -> None:
        return None

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        return "voltage_v", self.held_v

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        await asyncio.sleep(self.latency_s)
        self.held_v = voltage_v
        self.writes.append((time.monotonic(), voltage_v))


async def ramp(latency_s: float, rate_um_per_s: float) -> tuple[float, int, float]:
    """(achieved rate as a share of the configured one, writes, largest step in um)."""
    config = ActuatorConfig(max_slew_um_per_s=rate_um_per_s)
    device = SlowOutput(latency_s)
    actuation = Actuation(structlog.get_logger("bench"))
    await actuation.start({"x": device}, {"x": config})
    began = time.monotonic()
    if actuation.offer({"x": GOAL_V / config.volts_per_um}, {"x": GOAL_V}):
        actuation.wake()
    while device.held_v != GOAL_V:
        await asyncio.sleep(0.005)
    took_s = device.writes[-1][0] - began
    await actuation.stop()
    steps_um = [abs(b - a) / config.volts_per_um for (_, a), (_, b) in itertools.pairwise(device.writes)]
    distance_um = GOAL_V / config.volts_per_um
    return distance_um / took_s / rate_um_per_s, len(device.writes), max(steps_um, default=0.0)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rate", type=float, default=100.0, help="max_slew_um_per_s")
    args = parser.parse_args()
    structlog.configure(wrapper_class=structlog.make_filtering_bound_logger(40))
    pauses = motion.LATENCY_PAUSES
    print(f"ramp 0 -> {GOAL_V:g} V ({GOAL_V / 0.02:g} um) at {args.rate:g} um/s")
    print(f"{'rule':<28}{'device':>10}{'rate share':>12}{'vs 0 ms':>10}{'writes':>8}{'largest step':>15}")
    for rule, factor in (("pause 9x the write (now)", pauses), ("pause 20 ms (before)", 0.0)):
        motion.LATENCY_PAUSES = factor
        baseline = None
        for latency_s in LATENCIES_S:
            share, writes, step_um = asyncio.run(ramp(latency_s, args.rate))
            baseline = baseline or share
            print(f"{rule:<28}{latency_s * 1000:>8g}ms{share:>11.0%}{share / baseline:>10.2f}{writes:>8}"
                  f"{step_um:>12.2f} um")
    motion.LATENCY_PAUSES = pauses


if __name__ == "__main__":
    main()
