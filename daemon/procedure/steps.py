"""A procedure step by step: ramp the command, hold, average the window, re-measure a dirty one.

A channel that faults or goes stale inside the window is never averaged: the window is measured
again (up to ``max_retries`` times), then the step is kept with ``valid = 0`` (identification
ignores it). The same code drives the simulated cell on a virtual clock and real hardware.

The operator's ``[actuator]`` motion keys hold here too: no ramp is faster than
``max_slew_um_per_s`` (a ramp is stretched instead), every sub-command's voltage is checked against
``[v_min, v_max]``, and a finite ``safe_voltage_v`` is where the stage is left at the end. The first
ramp starts where the stage is, by the daemon's rule (:func:`nanodrift.outputs.locate_stage`:
the output read back, else a finite ``safe_voltage_v``); when that is unknown the first move is
written at once, and the progress stream says so.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence

from nanodrift.calibration.plans import PAPER_TIMING, PlannedStep, StepResult, StepTiming, ramp_commands
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator, Clock
from nanodrift.drivers_set import DriverSet
from nanodrift.outputs import bind_limits, checked_sent_voltage, locate_stage
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.sampler import Sampler

CommandFor = Callable[[PlannedStep, float], float]


def ramp_s(q_from: float | None, q_to: float, timing: StepTiming, limits: ActuatorConfig) -> float:
    """How long the move takes: ``timing.ramp_s``, stretched so it never exceeds ``max_slew_um_per_s``."""
    slew = limits.max_slew_um_per_s
    return max(timing.ramp_s, abs(q_to - q_from) / slew) if slew > 0 and q_from is not None else timing.ramp_s


def planned_seconds(plan: Sequence[PlannedStep], q_from: float | None, timing: StepTiming,
                    limits: ActuatorConfig) -> list[float]:
    """Each step's planned duration on the cell's clock: its rise (stretched by the slew limit) and hold."""
    out = []
    for step in plan:
        out.append(ramp_s(q_from, step.target_um, timing, limits) + timing.hold_s)
        q_from = step.target_um
    return out


async def ramp(actuator: Actuator, clock: Clock, q_from: float | None, q_to: float, timing: StepTiming,
               limits: ActuatorConfig) -> None:
    """Sub-commands every ``ramp_interval_s`` from ``q_from`` to ``q_to``; each voltage checked before it is sent.

    ``q_from`` None (where the stage is is unknown): ``q_to`` is written at once, then the rise time passes."""
    if q_from is None:
        await actuator.command(q_to, checked_sent_voltage(actuator, limits, limits.checked_voltage(q_to)))
        await clock.sleep(timing.ramp_s)
        return
    duration = ramp_s(q_from, q_to, timing, limits)
    _, commands = ramp_commands(q_from, q_to, duration, timing.ramp_interval_s)
    for q in commands.tolist():
        await clock.sleep(duration / len(commands))
        await actuator.command(q, checked_sent_voltage(actuator, limits, limits.checked_voltage(q)))


async def measure_step(sampler: Sampler, step: PlannedStep, q_from: float | None, q_to: float,
                       timing: StepTiming, limits: ActuatorConfig) -> StepResult:
    """Ramp, hold, average the last window; re-measure a dirty window up to ``max_retries`` times.

    Every sub-command's voltage is checked against ``limits`` before it is sent."""
    backend = sampler.drivers
    clock, actuator = backend.clock, backend.actuator
    assert actuator is not None and backend.position_channel is not None
    t_command = clock.now()
    await ramp(actuator, clock, q_from, q_to, timing, limits)
    sampler.clear()
    channels = (backend.position_channel, *backend.temperature_channels)
    # temperatures all through the hold (stateful model terms see them); the position where it is used
    thermal_groups = [g for g in backend.groups if backend.position_channel not in g.names]
    await sampler.sample_for(timing.hold_s - timing.window_s, thermal_groups)
    await sampler.sample_for(timing.window_s)
    retries = 0
    while True:
        end = clock.now()
        means, problem = sampler.window(channels, end - timing.window_s, end)
        x_true = sampler.true_mean(backend.position_channel, end - timing.window_s, end)
        if not problem:
            return StepResult(step, end, q_to, means[backend.position_channel],
                              {c: means[c] for c in backend.temperature_channels}, True, retries,
                              t_command_s=t_command, x_true_um=x_true)
        if retries >= timing.max_retries:
            fb = sampler.fallback(channels, end - timing.window_s, end)
            return StepResult(step, end, q_to, fb[backend.position_channel],
                              {c: fb[c] for c in backend.temperature_channels}, False, retries, problem,
                              t_command_s=t_command, x_true_um=x_true)
        retries += 1
        sampler.clear()
        await sampler.sample_for(timing.window_s)


async def run_steps(
    drivers: DriverSet,
    plan: Sequence[PlannedStep],
    *,
    limits: ActuatorConfig | None = None,
    timing: StepTiming = PAPER_TIMING,
    command_for: CommandFor | None = None,
    on_step: Callable[[StepResult], Awaitable[None] | None] | None = None,
    on_temperatures: Callable[[float, dict[str, float]], None] | None = None,
    progress: Progress | None = None,
    follow: FollowCheck | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
) -> list[StepResult]:
    """Drive ``plan`` step by step; ``command_for(step, t)`` gives the command (default: the target).

    ``limits``: the operator's ``[actuator]`` section (default: its defaults). ``ready``: a check that
    must pass once the drivers are open, before the first command (an output node is listening).
    ``follow``: each step is shown to it after it is recorded; it stops the run when the stage did
    not move as commanded. The first ramp starts where the stage is (a resumed run too)."""
    limits = limits or ActuatorConfig()
    sampler = Sampler(drivers, on_temperatures=on_temperatures)
    results: list[StepResult] = []
    q_prev: float | None = None
    commanded = False  # a run refused before its first move (no output node) leaves the stage alone
    if drivers.actuator is not None:
        bind_limits(drivers.actuator, limits)
    await sampler.open()
    try:
        if ready is not None:
            await ready()
        q_prev = await stage_q_um(drivers, limits, progress)
        if progress is not None:
            progress.begin(planned_seconds(plan, q_prev, timing, limits))
        await sampler.poll_all()  # know the temperatures before the first command
        for step in plan:
            q = command_for(step, drivers.clock.now()) if command_for else step.target_um
            commanded = True
            result = await measure_step(sampler, step, q_prev, q, timing, limits)
            q_prev = q
            results.append(result)
            if on_step is not None:
                maybe = on_step(result)
                if asyncio.iscoroutine(maybe):
                    await maybe
            if progress is not None:
                progress.advance(result)
            if follow is not None:
                follow.observe(result)
    except BaseException:
        if commanded:
            await leave_safe(drivers, q_prev, timing, limits, quiet=True)
        raise
    else:
        if commanded:
            await leave_safe(drivers, q_prev, timing, limits)
    finally:
        await sampler.close()
        if progress is not None:
            progress.finish()
    return results


async def stage_q_um(drivers: DriverSet, limits: ActuatorConfig, progress: Progress | None) -> float | None:
    """Where the stage is before the first move (None: unknown, which ``progress`` is told)."""
    actuator = drivers.actuator
    if actuator is None:
        return None
    start = await locate_stage(actuator, limits)
    if start.voltage_v is None:
        if progress is not None:
            progress.note(f"where the stage is before the first move is unknown ({actuator.description} cannot be "
                          "read back, safe_voltage_v = nan): the first move is written at once, not ramped")
        return None
    return limits.q_um_for(start.voltage_v)


async def leave_safe(drivers: DriverSet, q_from: float | None, timing: StepTiming, limits: ActuatorConfig, *,
                     quiet: bool = False) -> None:
    """Ramp to ``safe_voltage_v`` when it is finite (else leave the stage where it is).

    ``quiet``: the procedure already failed; its error is the one to report, not this one's.
    """
    q_safe = limits.safe_q_um
    if q_safe is None or drivers.actuator is None:
        return
    try:
        await ramp(drivers.actuator, drivers.clock, q_from, q_safe, timing, limits)
    except Exception:
        if not quiet:
            raise
