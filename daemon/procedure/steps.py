"""A procedure step by step: ramp every axis together, hold, average the window, re-measure a dirty one.

One code path for a cell of any number of axes (a one-axis cell is a cell of one axis, ``x``). A
channel that faults or goes stale inside the window (any axis' position sensor included) is never
averaged: the window is measured again (up to ``max_retries`` times), then the step is kept with
``valid = 0`` (identification ignores it). The same code drives the simulated cell on a virtual
clock and real hardware.

Each axis' ``[actuator]`` / ``[axes.actuator]`` motion keys hold here too: no ramp is faster than
``max_slew_um_per_s`` (a move is stretched instead; every axis of a move ramps over the same time, the
slowest axis' slew sets it, so the stage moves along the straight line between two points), every
sub-command's voltage is checked against ``[v_min, v_max]`` (every axis' sub-command of one instant
before any is written), and a finite ``safe_voltage_v`` is where an axis is left at the end. The
first ramp starts where the stage is, by the daemon's rule (:func:`nanodrift.outputs.locate_stage`:
the output read back, else a finite ``safe_voltage_v``); an axis whose start is unknown is written at
once, and the progress stream says so.
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Awaitable, Callable, Mapping, Sequence

from nanodrift.calibration.plans import (
    PAPER_TIMING,
    PlannedStep,
    StepResult,
    StepTiming,
    ramp_commands,
)
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator
from nanodrift.drivers_set import DriverSet
from nanodrift.output_record import OutputRecords
from nanodrift.outputs import bind_limits, checked_sent_voltage, locate_stage
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.sampler import Sampler

#: (the step's targets per axis, the cell clock's now) -> the command per axis
CommandFor = Callable[[dict[str, float], float], dict[str, float]]
Limits = Mapping[str, ActuatorConfig]


def axis_limits(drivers: DriverSet, limits: Limits | None) -> Limits:
    """Each driven axis' limits: ``limits``, else the ``[actuator]`` defaults for every output of ``drivers``."""
    return limits if limits is not None else {axis: ActuatorConfig() for axis in drivers.actuators}


def ramp_s(q_from: float | None, q_to: float, timing: StepTiming, limits: ActuatorConfig) -> float:
    """How long one axis' move takes: ``timing.ramp_s``, stretched so it never exceeds ``max_slew_um_per_s``."""
    slew = limits.max_slew_um_per_s
    return max(timing.ramp_s, abs(q_to - q_from) / slew) if slew > 0 and q_from is not None else timing.ramp_s


def move_s(q_from: Mapping[str, float | None], q_to: Mapping[str, float], timing: StepTiming, limits: Limits) -> float:
    """How long a move of every axis takes: the rise time, stretched by the slowest axis' slew limit."""
    return max(ramp_s(q_from[a], q_to[a], timing, limits[a]) for a in q_to)


def planned_seconds(plan: Sequence[PlannedStep], q_from: Mapping[str, float | None], timing: StepTiming,
                    limits: Limits) -> list[float]:
    """Each step's planned duration on the cell's clock: its rise (stretched by the slew limits) and hold."""
    out = []
    for step in plan:
        targets = dict(step.targets_um)
        out.append(move_s(q_from, targets, timing, limits) + timing.hold_s)
        q_from = targets
    return out


async def _write(actuators: Mapping[str, Actuator], limits: Limits, q_um: Mapping[str, float],
                 records: OutputRecords | None) -> None:
    """One instant of a move: every axis' voltage checked before any is written, and recorded (when the config
    keeps a state directory) before it is written, so the daemon's next start can believe the read-back."""
    sent = {a: checked_sent_voltage(actuators[a], limits[a], limits[a].checked_voltage(q)) for a, q in q_um.items()}
    for a, q in q_um.items():
        if records is not None:
            records.note_written(a, actuators[a].description, sent[a])
        await actuators[a].command(q, sent[a])


async def ramp(drivers: DriverSet, limits: Limits, q_from: Mapping[str, float | None], q_to: Mapping[str, float],
               timing: StepTiming) -> None:
    """Sub-commands every ``ramp_interval_s``, every axis of ``q_to`` along the same fraction of its move.

    An axis whose start is unknown (None) is written at once; with none known, the rise time then passes."""
    clock, actuators = drivers.clock, drivers.actuators
    unknown = {a: q for a, q in q_to.items() if q_from[a] is None}
    if unknown:
        await _write(actuators, limits, unknown, drivers.records)
    known = {a: start for a in q_to if (start := q_from[a]) is not None}
    if not known:
        await clock.sleep(timing.ramp_s)
        return
    duration = move_s(known, {a: q_to[a] for a in known}, timing, limits)
    tracks = {a: ramp_commands(start, q_to[a], duration, timing.ramp_interval_s)[1].tolist()
              for a, start in known.items()}
    n = len(next(iter(tracks.values())))
    for k in range(n):
        await clock.sleep(duration / n)
        await _write(actuators, limits, {a: track[k] for a, track in tracks.items()}, drivers.records)


async def measure_step(sampler: Sampler, limits: Limits, step: PlannedStep, q_from: Mapping[str, float | None],
                       q_to: dict[str, float], timing: StepTiming) -> StepResult:
    """Ramp every axis, hold, average the last window; re-measure a dirty window up to ``max_retries`` times."""
    drivers = sampler.drivers
    clock = drivers.clock
    positions = {a: drivers.position_axes[a] for a in limits}
    await ramp(drivers, limits, q_from, q_to, timing)
    sampler.clear()
    channels = (*positions.values(), *drivers.temperature_channels)
    # temperatures all through the hold (stateful model terms see them); the positions where they are used
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
        return StepResult(step, end, dict(q_to), {a: means[c] for a, c in positions.items()},
                              {c: means[c] for c in drivers.temperature_channels}, valid, retries, problem, truth)


async def run_steps(
    drivers: DriverSet,
    plan: Sequence[PlannedStep],
    *,
    limits: Limits | None = None,
    timing: StepTiming = PAPER_TIMING,
    command_for: CommandFor | None = None,
    on_step: Callable[[StepResult], Awaitable[None] | None] | None = None,
    on_temperatures: Callable[[float, dict[str, float]], None] | None = None,
    progress: Progress | None = None,
    follow: Mapping[str, FollowCheck] | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
) -> list[StepResult]:
    """Drive ``plan`` step by step on every axis; ``command_for(targets, t)`` gives the commands (default: the
    targets).

    ``limits``: each axis' ``[actuator]`` section (default: its defaults for every output). ``ready``: a
    check that must pass once the drivers are open, before the first command (an output node is
    listening). ``follow``: one check per axis, shown each step on its own axis after it is recorded; it
    stops the run when the stage did not move as commanded. The first ramp starts where the stage is
    (a resumed run too)."""
    limits = axis_limits(drivers, limits)
    actuators = {a: drivers.actuators[a] for a in limits}
    sampler = Sampler(drivers, on_temperatures=on_temperatures)
    results: list[StepResult] = []
    q_prev: dict[str, float | None] = dict.fromkeys(limits)
    commanded = False  # a run refused before its first move (no output node) leaves the stage alone
    for axis, actuator in actuators.items():
        bind_limits(actuator, limits[axis])
    await sampler.open()
    opened: list[Actuator] = []
    try:
        for actuator in actuators.values():
            await actuator.open()
            opened.append(actuator)
        if ready is not None:
            await ready()
        for axis, actuator in actuators.items():
            q_prev[axis] = await stage_q_um(actuator, limits[axis], progress)
        if progress is not None:
            progress.begin(planned_seconds(plan, q_prev, timing, limits))
        for group in drivers.groups:  # know the temperatures before the first command
            await sampler.poll(group)
        for step in plan:
            targets = dict(step.targets_um)
            q = command_for(targets, drivers.clock.now()) if command_for else targets
            commanded = True
            result = await measure_step(sampler, limits, step, q_prev, q, timing)
            q_prev = dict(q)
            results.append(result)
            if on_step is not None:
                maybe = on_step(result)
                if asyncio.iscoroutine(maybe):
                    await maybe
            if progress is not None:
                progress.advance(result.valid)
            for axis, check in (follow or {}).items():
                check.observe(result, axis)
    except BaseException:
        if commanded:
            await leave_safe(drivers, limits, q_prev, timing, quiet=True)
        raise
    else:
        if commanded:
            await leave_safe(drivers, limits, q_prev, timing)
    finally:
        for actuator in opened:
            with contextlib.suppress(Exception):  # closing must not hide the error that brought us here
                await actuator.close()
        await sampler.close()
        if progress is not None:
            progress.finish()
    return results


async def stage_q_um(actuator: Actuator, limits: ActuatorConfig, progress: Progress | None) -> float | None:
    """Where an axis is before the first move (None: unknown, which ``progress`` is told)."""
    start = await locate_stage(actuator, limits)
    if start.voltage_v is None:
        if progress is not None:
            progress.note(f"where the stage is before the first move is unknown ({actuator.description} cannot be "
                          "read back, safe_voltage_v = nan): the first move is written at once, not ramped")
        return None
    return limits.q_um_for(start.voltage_v)


async def leave_safe(drivers: DriverSet, limits: Limits, q_from: Mapping[str, float | None], timing: StepTiming, *,
                     quiet: bool = False) -> None:
    """Ramp every axis with a finite ``safe_voltage_v`` to it (the others stay where they are).

    ``quiet``: the procedure already failed; its error is the one to report, not this one's.
    """
    safe = {a: q for a in limits if (q := limits[a].safe_q_um) is not None}
    if not safe:
        return
    try:
        await ramp(drivers, limits, q_from, safe, timing)
    except Exception:
        if not quiet:
            raise
