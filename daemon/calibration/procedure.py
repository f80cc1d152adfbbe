"""The paper's stepped procedure (section III.B, Fig. 6 and 7) on any backend: sensor groups, an
actuator and a clock. The same code drives the simulated cell on a virtual clock and real hardware.

One step: the command ramps from the previous target in ``ramp_s`` (4 s), holds ``hold_s`` (25 s)
while every sensor group is polled at its own interval, and the step's measurement is the average
of the last ``window_s`` (5 s). A channel that faults or goes stale inside the window is never
averaged: the window is measured again (up to ``max_retries`` times), then the step is kept with
``valid = 0`` (identification ignores it).

Calibration: 0..480 µm in 30 µm steps, forward, ``cycles`` times (24: about 3.3 h); each completed
step is appended to the CSV and fsynced, so an interrupted run resumes from the file.
"""

from __future__ import annotations

import asyncio
import math
import sys
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

import numpy as np

from drivers.base import Actuator, Clock, DeviceError, Reading, SensorGroup, State

CALIBRATION_POINTS_UM: tuple[float, ...] = tuple(float(x) for x in range(0, 481, 30))


@dataclass(frozen=True)
class StepTiming:
    ramp_s: float = 4.0
    hold_s: float = 25.0
    window_s: float = 5.0
    ramp_interval_s: float = 0.25
    max_retries: int = 2

    @property
    def step_s(self) -> float:
        return self.ramp_s + self.hold_s


@dataclass(frozen=True)
class PlannedStep:
    index: int
    cycle: int
    target_um: float


def calibration_plan(cycles: int, points: Sequence[float] = CALIBRATION_POINTS_UM) -> list[PlannedStep]:
    """Forward sweeps, as the paper measures (Fig. 7)."""
    return [PlannedStep(i, c, x) for i, (c, x) in enumerate((c, x) for c in range(cycles) for x in points)]


def bidirectional_plan(cycles: int, points: Sequence[float] = CALIBRATION_POINTS_UM) -> list[PlannedStep]:
    """Alternate up and down sweeps: direction-dependent effects become visible."""
    order = [list(points) if c % 2 == 0 else list(points)[::-1] for c in range(cycles)]
    return [PlannedStep(i, c, x) for i, (c, x) in enumerate((c, x) for c in range(cycles) for x in order[c])]


@dataclass
class Backend:
    """What a procedure drives: the cell's sensor groups, its actuator and the clock they share."""

    groups: list[SensorGroup]
    actuator: Actuator
    clock: Clock
    max_age_s: dict[str, float]
    position_channel: str
    temperature_channels: tuple[str, ...]
    volts_per_um: float = 0.02
    offset_v: float = 0.0
    v_min: float = -2.0
    v_max: float = 12.0
    description: str = ""
    simulated_cell: Any = None  # the SimulatedCell when the backend is simulated (tests inject faults)

    def voltage(self, q_um: float) -> float:
        v = self.offset_v + self.volts_per_um * q_um
        if not self.v_min <= v <= self.v_max:
            raise ValueError(f"command {q_um:.3f} um needs {v:.3f} V, outside [{self.v_min}, {self.v_max}] V")
        return v


@dataclass
class StepResult:
    step: PlannedStep
    t_s: float
    q_um: float
    x_um: float
    temperatures: dict[str, float]
    valid: bool
    retries: int = 0
    problem: str = ""
    t_command_s: float = math.nan


@dataclass
class _Sample:
    t: float  # when polled (backend clock)
    reading: Reading


@dataclass
class Sampler:
    """Polls every group on its own schedule during holds and keeps the samples of the current step."""

    backend: Backend
    samples: dict[str, list[_Sample]] = field(default_factory=dict)
    latest: dict[str, Reading] = field(default_factory=dict)
    on_temperatures: Callable[[float, dict[str, float]], None] | None = None
    _broken: set[int] = field(default_factory=set)

    async def open(self) -> None:
        for group in self.backend.groups:
            await group.open()
        await self.backend.actuator.open()

    async def close(self) -> None:
        for group in self.backend.groups:
            try:
                await group.close()
            except Exception:  # closing must not hide the error that brought us here
                pass
        try:
            await self.backend.actuator.close()
        except Exception:
            pass

    async def poll(self, group: SensorGroup) -> None:
        now = self.backend.clock.now()
        key = id(group)
        try:
            if key in self._broken:
                await group.close()
                await group.open()
                self._broken.discard(key)
            async with asyncio.timeout(group.timeout_s):
                readings = await group.read()
        except (DeviceError, TimeoutError, OSError) as err:
            self._broken.add(key)
            reason = f"device error: {err}" if str(err) else f"device error: {type(err).__name__}"
            readings = {name: Reading.fault(now, reason) for name in group.names}
        temps: dict[str, float] = {}
        for name, reading in readings.items():
            self.samples.setdefault(name, []).append(_Sample(now, reading))
            if reading.state is State.OK and math.isfinite(reading.value):
                self.latest[name] = reading
                if name in self.backend.temperature_channels:
                    temps[name] = reading.value
        if temps and self.on_temperatures is not None:
            self.on_temperatures(now, temps)

    async def poll_all(self) -> None:
        for group in self.backend.groups:
            await self.poll(group)

    async def sample_for(self, duration_s: float, groups: Sequence[SensorGroup] | None = None) -> None:
        """Poll ``groups`` (default: all) each at its interval for ``duration_s`` of backend time."""
        clock = self.backend.clock
        start = clock.now()
        end = start + duration_s
        groups = list(self.backend.groups if groups is None else groups)
        if not groups:
            await clock.sleep(duration_s)
            return
        due = {id(g): start for g in groups}
        while True:
            t_next = min(due.values())
            if t_next > end + 1e-9:
                break
            wait = t_next - clock.now()
            if wait > 0:
                await clock.sleep(wait)
            for group in groups:
                if due[id(group)] <= t_next + 1e-9:
                    await self.poll(group)
                    due[id(group)] += group.interval_s
        if end - clock.now() > 0:
            await clock.sleep(end - clock.now())

    def window(self, channels: Sequence[str], start: float, end: float) -> tuple[dict[str, float], str]:
        """Averages over [start, end] per channel, or a problem if any sample there is not clean."""
        means: dict[str, float] = {}
        for name in channels:
            inside = [s for s in self.samples.get(name, []) if start - 1e-9 <= s.t <= end + 1e-9]
            if not inside:
                return means, f"{name}: no sample in the averaging window"
            max_age = self.backend.max_age_s.get(name, math.inf)
            for s in inside:
                if s.reading.state is not State.OK or not math.isfinite(s.reading.value):
                    return means, f"{name}: {s.reading.reason or s.reading.state.value} at t={s.t:.1f}"
                if s.t - s.reading.t > max_age:
                    return means, f"{name}: stale (reading {s.t - s.reading.t:.1f} s old > max_age_s {max_age:g})"
            means[name] = float(np.mean([s.reading.value for s in inside]))
        return means, ""

    def fallback(self, channels: Sequence[str], start: float, end: float) -> dict[str, float]:
        """For an invalid step: means of the clean samples, else the last clean value, else 0."""
        out: dict[str, float] = {}
        for name in channels:
            good = [s.reading.value for s in self.samples.get(name, [])
                    if start - 1e-9 <= s.t <= end + 1e-9 and s.reading.state is State.OK
                    and math.isfinite(s.reading.value)]
            last = self.latest.get(name)
            out[name] = float(np.mean(good)) if good else (last.value if last else 0.0)
        return out


CommandFor = Callable[[PlannedStep, float], float]


async def measure_step(sampler: Sampler, step: PlannedStep, q_from: float, q_to: float,
                       timing: StepTiming) -> StepResult:
    """Ramp, hold, average the last window; re-measure a dirty window up to ``max_retries`` times."""
    backend = sampler.backend
    clock, actuator = backend.clock, backend.actuator
    n = max(1, round(timing.ramp_s / timing.ramp_interval_s))
    t_command = clock.now()
    for k in range(1, n + 1):
        await clock.sleep(timing.ramp_s / n)
        q = q_from + (q_to - q_from) * k / n
        await actuator.command(q, backend.voltage(q))
    sampler.samples.clear()
    channels = (backend.position_channel, *backend.temperature_channels)
    # temperatures all through the hold (stateful model terms see them); the position where it is used
    thermal_groups = [g for g in backend.groups if backend.position_channel not in g.names]
    await sampler.sample_for(timing.hold_s - timing.window_s, thermal_groups)
    await sampler.sample_for(timing.window_s)
    retries = 0
    while True:
        end = clock.now()
        means, problem = sampler.window(channels, end - timing.window_s, end)
        if not problem:
            return StepResult(step, end, q_to, means[backend.position_channel],
                              {c: means[c] for c in backend.temperature_channels}, True, retries,
                              t_command_s=t_command)
        if retries >= timing.max_retries:
            fb = sampler.fallback(channels, end - timing.window_s, end)
            return StepResult(step, end, q_to, fb[backend.position_channel],
                              {c: fb[c] for c in backend.temperature_channels}, False, retries, problem,
                              t_command_s=t_command)
        retries += 1
        sampler.samples.clear()
        await sampler.sample_for(timing.window_s)


async def run_steps(
    backend: Backend,
    plan: Sequence[PlannedStep],
    *,
    timing: StepTiming = StepTiming(),
    command_for: CommandFor | None = None,
    on_step: Callable[[StepResult], Awaitable[None] | None] | None = None,
    on_temperatures: Callable[[float, dict[str, float]], None] | None = None,
    progress: Progress | None = None,
) -> list[StepResult]:
    """Drive ``plan`` step by step; ``command_for(step, t)`` gives the command (default: the target)."""
    sampler = Sampler(backend, on_temperatures=on_temperatures)
    results: list[StepResult] = []
    await sampler.open()
    try:
        await sampler.poll_all()  # know the temperatures before the first command
        q_prev = 0.0
        for step in plan:
            q = command_for(step, backend.clock.now()) if command_for else step.target_um
            result = await measure_step(sampler, step, q_prev, q, timing)
            q_prev = q
            results.append(result)
            if on_step is not None:
                maybe = on_step(result)
                if asyncio.iscoroutine(maybe):
                    await maybe
            if progress is not None:
                progress.advance(result)
    finally:
        await sampler.close()
        if progress is not None:
            progress.finish()
    return results


class Progress:
    """A bar on stderr with the time left in the backend's time (a line per cycle when not a TTY)."""

    def __init__(self, plan: Sequence[PlannedStep], step_s: float, label: str, stream: IO[str] | None = None,
                 done: int = 0) -> None:
        self.cycles = [s.cycle for s in plan]
        self.total, self.step_s, self.label = len(plan), step_s, label
        self.done = done
        self.stream = stream if stream is not None else sys.stderr
        self.tty = bool(getattr(self.stream, "isatty", lambda: False)())
        self.invalid = 0

    @staticmethod
    def _hms(seconds: float) -> str:
        s = max(0, round(seconds))
        return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}"

    def advance(self, result: StepResult) -> None:
        self.done += 1
        self.invalid += 0 if result.valid else 1
        left = self._hms((self.total - self.done) * self.step_s)
        if self.tty:
            width = 30
            filled = int(width * self.done / max(1, self.total))
            bar = "#" * filled + "-" * (width - filled)
            self.stream.write(f"\r{self.label} [{bar}] {self.done}/{self.total} steps, {left} left ")
            self.stream.flush()
        elif self.done >= self.total or self.cycles[self.done] != self.cycles[self.done - 1]:  # a cycle ended
            self.stream.write(f"{self.label}: {self.done}/{self.total} steps, {left} left, {self.invalid} invalid\n")
            self.stream.flush()

    def finish(self) -> None:
        if self.tty:
            self.stream.write("\n")
            self.stream.flush()


# ----- calibration ---------------------------------------------------------------------------------


def calibration_columns(backend: Backend) -> list[str]:
    return ["t_s", "x_um", "q_um", "cycle", "valid", *backend.temperature_channels]


def completed_steps(data_path: Path, columns: Sequence[str]) -> tuple[int, float]:
    """Rows already recorded in ``data_path`` (for --resume) and the last time stamp."""
    from daemon.calibration.dataset import read_csv

    if not data_path.exists() or data_path.stat().st_size == 0:
        return 0, -math.inf
    ds = read_csv(data_path)
    found = list(ds.columns())
    if sorted(found) != sorted(columns):
        from daemon.calibration.dataset import DataError

        raise DataError(f"{data_path}: cannot resume, its columns {found} differ from this cell's {list(columns)}")
    return len(ds), float(ds.t[-1])


async def record_calibration(
    backend: Backend,
    data_path: str | Path,
    *,
    cycles: int = 24,
    plan: Sequence[PlannedStep] | None = None,
    timing: StepTiming = StepTiming(),
    resume: bool = False,
    progress_stream: IO[str] | None = None,
    on_step: Callable[[StepResult], None] | None = None,
) -> int:
    """Run (or continue) the calibration trajectory, appending each step to ``data_path``.

    Returns the number of steps recorded in this call. With ``resume``, steps already in the file
    are skipped; without it, an existing non-empty file is an error (never overwrite hours of data).
    """
    from daemon.calibration.dataset import CsvAppender

    path = Path(data_path)
    columns = calibration_columns(backend)
    plan = list(plan if plan is not None else calibration_plan(cycles))
    done = 0
    if resume:
        done, _ = completed_steps(path, columns)
    elif path.exists() and path.stat().st_size > 0:
        raise FileExistsError(f"{path} already holds recorded steps; use --resume to continue it, or another --data")
    remaining = plan[done:]
    progress = Progress(plan, timing.step_s, "calibration", progress_stream, done=done)
    with CsvAppender(path, columns) as appender:

        def write(result: StepResult) -> None:
            row = {"t_s": result.t_s, "x_um": result.x_um, "q_um": result.q_um, "cycle": result.step.cycle,
                   "valid": int(result.valid), **result.temperatures}
            appender.append(row)
            if on_step is not None:
                on_step(result)

        await run_steps(backend, remaining, timing=timing, on_step=write, progress=progress)
    return len(remaining)


def resume_hint(out: str | Path, data: str | Path, recorded: int, total: int) -> str:
    return (f"calibration stopped after {recorded} of {total} steps; every completed step is in {data}. "
            f"Resume with: nanodrift calibrate --out {out} --data {data} --resume")


def fit_recorded(data_path: str | Path, model_path: str | Path) -> Any:
    """Identify the model from the recorded steps (valid rows only) and save it atomically."""
    from daemon.calibration.dataset import read_csv
    from daemon.model.identify import fit
    from daemon.model.model import save_model

    ds = read_csv(data_path)
    result = fit(ds, source=str(data_path))
    save_model(result.model, model_path)
    return result


# ----- backends ------------------------------------------------------------------------------------


def simulated_backend(
    scenario: str = "train",
    effects: object = None,
    seed: int = 0,
    *,
    start_s: float = 0.0,
    params: Mapping[str, float] | None = None,
) -> Backend:
    """The paper's cell, simulated, on a :class:`VirtualClock` starting at scenario time ``start_s``."""
    from daemon.config import parse_config

    settings: dict[str, Any] = {"scenario": scenario, "seed": seed}
    if effects:
        settings["effects"] = effects if not isinstance(effects, str) else [effects]
    if params:
        settings["params"] = dict(params)
    return config_backend(parse_config({"simulation": settings}, source="<simulated cell>"), start_s=start_s)


def config_backend(config: Any, *, start_s: float = 0.0) -> Backend:
    """The backend an operator config describes (``daemon.config.Config``).

    All-simulated configs run on a :class:`VirtualClock` (a 4-hour calibration takes seconds);
    anything with real hardware runs on the wall clock.
    """
    from daemon.service_drivers import build_drivers, make_context
    from drivers.simulated.cell import SimulatedCell
    from drivers.simulated.clock import VirtualClock
    from drivers.simulated.plugin import SHARED_KEY

    kinds = {s.kind for s in config.sensors}
    simulated = kinds == {"simulated"}
    context = make_context(config)
    cell = None
    if simulated:
        context.clock = VirtualClock(start_s)
        cell = SimulatedCell(config.simulation.physics(), context.clock)
        cell.epoch = 0.0  # scenario time = clock time, so a resumed run continues the same room history
        context.shared[SHARED_KEY] = cell
    drivers = build_drivers(config, context)
    actuator = drivers.actuator
    if actuator is None:  # real hardware: the lab's output node applies published commands
        from daemon.bus_actuator import ZenohActuator

        actuator = ZenohActuator(config)
    positions = [s for s in config.sensors if s.role == "position"]
    if not positions:
        raise ValueError("the config has no position sensor (role = \"position\"); a calibration needs one")
    act = config.actuator
    return Backend(
        groups=drivers.groups,
        actuator=actuator,
        clock=context.clock,
        max_age_s={s.name: s.max_age_s for s in config.sensors},
        position_channel=positions[0].name,
        temperature_channels=tuple(s.name for s in config.sensors if s.role == "temperature"),
        volts_per_um=act.volts_per_um,
        offset_v=act.offset_v,
        v_min=act.v_min,
        v_max=act.v_max,
        description="simulated cell (virtual clock)" if simulated else (
            "hardware" if drivers.actuator is not None else f"hardware; stage commands published on {actuator.key}"
        ),
        simulated_cell=cell,
    )
