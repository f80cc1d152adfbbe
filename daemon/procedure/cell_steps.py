"""A multi-axis procedure step by step: ramp every axis together, hold, average each axis' window.

The one-axis :mod:`nanodrift.procedure.steps` for an XY/XYZ cell, on its building blocks: the
:class:`~nanodrift.procedure.sampler.Sampler` polls every group on its own schedule and judges a window
(a faulted or stale sample in any channel, any axis' position sensor included, makes the window
dirty: it is measured again up to ``max_retries`` times, then kept with ``valid = 0``); each axis'
``[axes.actuator]`` limits hold as in a one-axis run (slew, ``[v_min, v_max]`` checked on every
sub-command, and every axis' sub-command of one instant checked before any is written); the
:class:`~nanodrift.procedure.follow.FollowCheck` watches each axis' first moves on its own sensor; the
stage starts where each output reads back and ends at each finite ``safe_voltage_v``.

Every axis of a move ramps over the same time (the slowest axis' slew sets it), so the stage moves
along the straight line between two points of the plan.
"""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field

from nanodrift.calibration.plans import (
    PAPER_TIMING,
    PlannedCellStep,
    PlannedStep,
    StepResult,
    StepTiming,
    ramp_commands,
)
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator
from nanodrift.drivers_set import DriverSet
from nanodrift.outputs import bind_limits, checked_sent_voltage
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.sampler import Sampler
from nanodrift.procedure.steps import ramp_s, stage_q_um

#: (the step's targets per axis, the cell clock's now) -> the command per axis
CellCommandFor = Callable[[dict[str, float], float], dict[str, float]]


@dataclass
class CellStepResult:
    """What one step of a multi-axis plan measured (window means; a fallback when ``valid`` is False)."""

    step: PlannedCellStep
    t_s: float
    q_um: dict[str, float]
    positions_um: dict[str, float]
    temperatures: dict[str, float]
    valid: bool
    retries: int = 0
    problem: str = ""
    #: each axis' true attained position over the window, when the cell knows it (simulated); nan on hardware
    true_um: dict[str, float] = field(default_factory=dict)

    def axis_result(self, axis: str) -> StepResult:
        """This step as one axis' :class:`StepResult` (what the one-axis follow check and progress read)."""
        return StepResult(PlannedStep(self.step.index, self.step.cycle, self.step.target(axis)), self.t_s,
                          self.q_um[axis], self.positions_um[axis], self.temperatures, self.valid, self.retries,
                          self.problem, x_true_um=self.true_um.get(axis, math.nan))


@dataclass
class CellDrive:
    """The outputs and position sensors of a multi-axis cell, with each axis' limits."""

    drivers: DriverSet
    limits: Mapping[str, ActuatorConfig]

    @property
    def axes(self) -> tuple[str, ...]:
        return tuple(self.limits)

    @property
    def actuators(self) -> dict[str, Actuator]:
        return {a: self.drivers.actuators[a] for a in self.axes}

    @property
    def position_channels(self) -> dict[str, str]:
        return {a: self.drivers.position_axes[a] for a in self.axes}


def move_s(q_from: Mapping[str, float | None], q_to: Mapping[str, float], timing: StepTiming,
           limits: Mapping[str, ActuatorConfig]) -> float:
    """How long a move of every axis takes: the rise time, stretched by the slowest axis' slew limit."""
    return max(ramp_s(q_from[a], q_to[a], timing, limits[a]) for a in q_to)


async def ramp_axes(drive: CellDrive, q_from: Mapping[str, float | None], q_to: Mapping[str, float],
                    timing: StepTiming) -> None:
    """Sub-commands every ``ramp_interval_s``, every axis along the same fraction of its move; at each instant
    every axis' voltage is checked before any is written. An axis whose start is unknown is written at once."""
    clock, limits = drive.drivers.clock, drive.limits
    actuators = drive.actuators
    unknown = [a for a in drive.axes if q_from[a] is None]
    if unknown:
        await _write(actuators, limits, {a: q_to[a] for a in unknown})
    known = [a for a in drive.axes if q_from[a] is not None]
    if not known:
        await clock.sleep(timing.ramp_s)
        return
    duration = move_s({a: q_from[a] for a in known}, {a: q_to[a] for a in known}, timing, limits)
    tracks = {}
    for a in known:
        start = q_from[a]
        assert start is not None
        tracks[a] = ramp_commands(start, q_to[a], duration, timing.ramp_interval_s)[1].tolist()
    n = len(tracks[known[0]])
    for k in range(n):
        await clock.sleep(duration / n)
        await _write(actuators, limits, {a: tracks[a][k] for a in known})


async def _write(actuators: Mapping[str, Actuator], limits: Mapping[str, ActuatorConfig],
                 q_um: Mapping[str, float]) -> None:
    sent = {a: checked_sent_voltage(actuators[a], limits[a], limits[a].checked_voltage(q)) for a, q in q_um.items()}
    for a, q in q_um.items():
        await actuators[a].command(q, sent[a])


async def measure_cell_step(sampler: Sampler, drive: CellDrive, step: PlannedCellStep,
                            q_from: Mapping[str, float | None], q_to: dict[str, float],
                            timing: StepTiming) -> CellStepResult:
    """Ramp every axis, hold, average the last window; re-measure a dirty window up to ``max_retries`` times."""
    drivers = drive.drivers
    clock = drivers.clock
    positions = drive.position_channels
    await ramp_axes(drive, q_from, q_to, timing)
    sampler.clear()
    channels = (*positions.values(), *drivers.temperature_channels)
    thermal_groups = [g for g in drivers.groups if not set(positions.values()) & set(g.names)]
    await sampler.sample_for(timing.hold_s - timing.window_s, thermal_groups)
    await sampler.sample_for(timing.window_s)
    retries = 0
    while True:
        end = clock.now()
        start = end - timing.window_s
        means, problem = sampler.window(channels, start, end)
        truth = {a: sampler.true_mean(c, start, end) for a, c in positions.items()}
        valid = not problem
        if not valid and retries < timing.max_retries:
            retries += 1
            sampler.clear()
            await sampler.sample_for(timing.window_s)
            continue
        if not valid:
            means = sampler.fallback(channels, start, end)
        return CellStepResult(step, end, dict(q_to), {a: means[c] for a, c in positions.items()},
                              {c: means[c] for c in drivers.temperature_channels}, valid, retries, problem, truth)


async def run_cell_steps(
    drive: CellDrive,
    plan: Sequence[PlannedCellStep],
    *,
    timing: StepTiming = PAPER_TIMING,
    command_for: CellCommandFor | None = None,
    on_step: Callable[[CellStepResult], Awaitable[None] | None] | None = None,
    on_temperatures: Callable[[float, dict[str, float]], None] | None = None,
    progress: Progress | None = None,
    follow: Mapping[str, FollowCheck] | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
) -> list[CellStepResult]:
    """Drive ``plan`` step by step on every axis; ``command_for(targets, t)`` gives the commands (default: the
    targets). ``follow``: one check per axis, shown each step on its own axis. See
    :func:`nanodrift.procedure.steps.run_steps` for the rest (the same rules, per axis)."""
    drivers = drive.drivers
    sampler = Sampler(drivers, on_temperatures=on_temperatures)
    results: list[CellStepResult] = []
    q_prev: dict[str, float | None] = dict.fromkeys(drive.axes)
    commanded = False
    for axis, actuator in drive.actuators.items():
        bind_limits(actuator, drive.limits[axis])
    await sampler.open()
    opened: list[Actuator] = []
    try:
        for actuator in drive.actuators.values():
            await actuator.open()
            opened.append(actuator)
        if ready is not None:
            await ready()
        for axis, actuator in drive.actuators.items():
            q_prev[axis] = await stage_q_um(_one_axis(drivers, actuator), drive.limits[axis], progress)
        if progress is not None:
            progress.begin(_planned_seconds(plan, q_prev, timing, drive.limits))
        await sampler.poll_all()  # know the temperatures before the first command
        for step in plan:
            targets = dict(step.targets_um)
            q = command_for(targets, drivers.clock.now()) if command_for else targets
            commanded = True
            result = await measure_cell_step(sampler, drive, step, q_prev, q, timing)
            q_prev = dict(q)
            results.append(result)
            if on_step is not None:
                maybe = on_step(result)
                if asyncio.iscoroutine(maybe):
                    await maybe
            if progress is not None:
                progress.advance(result.axis_result(drive.axes[0]))
            for axis, check in (follow or {}).items():
                check.observe(result.axis_result(axis))
    except BaseException:
        if commanded:
            await leave_cell_safe(drive, q_prev, timing, quiet=True)
        raise
    else:
        if commanded:
            await leave_cell_safe(drive, q_prev, timing)
    finally:
        for actuator in opened:
            try:
                await actuator.close()
            except Exception:  # closing must not hide the error that brought us here
                pass
        await sampler.close()
        if progress is not None:
            progress.finish()
    return results


def _one_axis(drivers: DriverSet, actuator: Actuator) -> DriverSet:
    """``drivers`` seen as a one-axis cell with ``actuator`` (what :func:`stage_q_um` reads)."""
    return DriverSet(context=drivers.context, groups=drivers.groups, actuator=actuator, roles=drivers.roles,
                     max_age_s=drivers.max_age_s, description=drivers.description)


def _planned_seconds(plan: Sequence[PlannedCellStep], q_from: Mapping[str, float | None], timing: StepTiming,
                     limits: Mapping[str, ActuatorConfig]) -> list[float]:
    out = []
    for step in plan:
        targets = dict(step.targets_um)
        out.append(move_s(q_from, targets, timing, limits) + timing.hold_s)
        q_from = targets
    return out


async def leave_cell_safe(drive: CellDrive, q_from: Mapping[str, float | None], timing: StepTiming, *,
                          quiet: bool = False) -> None:
    """Ramp every axis with a finite ``safe_voltage_v`` to it (the others stay where they are)."""
    safe = {a: drive.limits[a].safe_q_um for a in drive.axes}
    moving = {a: q for a, q in safe.items() if q is not None}
    if not moving:
        return
    try:
        target = {a: moving.get(a, q_from[a]) for a in drive.axes}
        if any(v is None for v in target.values()):
            await _write(drive.actuators, drive.limits, moving)
            return
        await ramp_axes(drive, q_from, {a: float(v) for a, v in target.items() if v is not None}, timing)
    except Exception:
        if not quiet:
            raise
