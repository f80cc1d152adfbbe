"""A whole stepped run of the simulated cell as arrays, in one vectorised pass.

The schedule is the paper's (Fig. 7): for each step, every axis' command ramps from its previous target in
``ramp_s`` (sub-commands every ``ramp_interval_s``), holds ``hold_s``, and the step's measurement is
the average of the samples in the last ``window_s`` of the hold, each sensor sampled every its own
interval from the start of the hold: exactly what the asynchronous procedure records from the
drivers, so ``nanodrift simulate`` output looks like a recorded calibration and fits directly.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from nanodrift.calibration.plans import PAPER_TIMING, StepTiming, cell_validation_plan, ramp_commands
from nanodrift.drivers.simulated.physics import THERMOCOUPLES, CellPhysics
from nanodrift.model.model import aim

if TYPE_CHECKING:
    from nanodrift.model.cell_model import CellModel
    from nanodrift.model.model import Model


@dataclass(frozen=True)
class StepSchedule(StepTiming):
    """The procedure's step timing (Fig. 7), plus how often the simulated sensors are sampled."""

    position_interval_s: float = 0.1
    temperature_interval_s: float = 0.5


#: the stacked stage's runs move each axis in one command per step (its stages keep no memory of the path: no
#: creep, no hysteresis), so one landing error per step and axis: how its seeded runs draw them
ONE_MOVE = StepSchedule(ramp_interval_s=PAPER_TIMING.ramp_s)

#: ``command_for(targets, t, temps)``: one step's commands per axis from its targets and the temperatures then
CommandFor = Callable[[dict[str, float], float, dict[str, float]], dict[str, float]]


def _window_times(hold_start: np.ndarray, interval: float, schedule: StepSchedule) -> np.ndarray:
    """Each step's sample times in its averaging window (one every ``interval`` from its hold's start), in order."""
    offsets = np.arange(0.0, schedule.hold_s + 1e-9, interval)
    offsets = offsets[offsets > schedule.hold_s - schedule.window_s - 1e-9]
    return np.ravel(hold_start[:, None] + offsets[None, :])


def simulate_steps(
    physics: CellPhysics,
    targets: Mapping[str, Sequence[float] | np.ndarray],
    cycles: Sequence[int],
    *,
    schedule: StepSchedule | None = None,
    channels: Sequence[str] = tuple(THERMOCOUPLES),
    command_for: CommandFor | None = None,
    t_start: float = 0.0,
) -> dict[str, np.ndarray]:
    """Step averages for ``targets`` (per axis, one entry per step).

    Returns ``t_s`` (the end of each step's averaging window), per axis ``<a>_um`` (measured), ``q_<a>_um``
    (commanded) and ``<a>_true_um`` (the true position averaged over the same window), ``cycle`` and the
    channels. ``command_for`` turns one step's targets into its commands (a model's compensation); by default
    the command is the target.
    """
    schedule = schedule or StepSchedule()
    axes = physics.axes
    target_um = {a: np.asarray(targets[a], dtype=np.float64) for a in axes}
    n = len(cycles)
    if any(v.size != n for v in target_um.values()):
        raise ValueError("every axis needs one target per step, and every step a cycle")
    step_start = t_start + schedule.step_s * np.arange(n)
    hold_start = step_start + schedule.ramp_s
    commands = {a: v.copy() for a, v in target_um.items()}
    noise_rng = np.random.default_rng([physics.seed, 3])
    if command_for is not None:  # needs the temperatures seen when each step is commanded
        thermal = physics.thermal(step_start)
        seen = {c: physics.measure_temperature(c, physics.sensor_truth(c, thermal), noise_rng.normal(size=n))
                for c in channels}
        for k in range(n):
            q = command_for({a: float(target_um[a][k]) for a in axes}, float(step_start[k]),
                            {c: float(seen[c][k]) for c in channels})
            for a in axes:
                commands[a][k] = q[a]
    landing_rng = np.random.default_rng([physics.seed, 2])
    tracks = {}
    for a in axes:
        cmd_t, cmd_q = [], []
        q_prev = 0.0
        for k in range(n):
            offsets, qs = ramp_commands(q_prev, float(commands[a][k]), schedule.ramp_s, schedule.ramp_interval_s)
            cmd_t.append(float(step_start[k]) + offsets)
            cmd_q.append(qs)
            q_prev = float(commands[a][k])
        tracks[a] = physics.command_track(np.concatenate(cmd_t), np.concatenate(cmd_q), landing_rng)

    pos_t = _window_times(hold_start, schedule.position_interval_s, schedule)
    true = physics.attained_along(pos_t, tracks)
    out: dict[str, np.ndarray] = {"t_s": hold_start + schedule.hold_s}
    for a in axes:
        meas = physics.measure_position(a, pos_t, true[a], noise_rng.normal(size=pos_t.size))
        out[f"{a}_um"] = meas.reshape(n, -1).mean(axis=1)
        out[f"{a}_true_um"] = true[a].reshape(n, -1).mean(axis=1)
        out[f"q_{a}_um"] = commands[a]
    out["cycle"] = np.asarray(cycles, dtype=np.float64)
    tc_t = _window_times(hold_start, schedule.temperature_interval_s, schedule)
    thermal = physics.thermal(tc_t)
    for c in channels:
        read = physics.measure_temperature(c, physics.sensor_truth(c, thermal), noise_rng.normal(size=tc_t.size))
        out[c] = read.reshape(n, -1).mean(axis=1)
    return out


@dataclass
class CellValidationRun:
    """One ISO 9283 test on the simulated cell, run twice in the same room with the same noise: commanded
    through a model (``compensated``, None without one) and uncompensated (command = target)."""

    name: str
    axes: tuple[str, ...]
    targets_um: dict[str, np.ndarray]
    uncompensated: dict[str, np.ndarray]
    compensated: dict[str, np.ndarray] | None
    extrapolating_steps: int = 0

    def attained(self, with_model: bool, against: str = "truth") -> dict[str, np.ndarray]:
        """Per axis, the attained positions: the true ones (``truth``) or as the interferometer measured them."""
        run = self.compensated if with_model else self.uncompensated
        if run is None:
            raise ValueError(f"{self.name}: ran without a model")
        suffix = "_true_um" if against == "truth" else "_um"
        return {a: run[a + suffix] for a in self.axes}


def cell_command(model: CellModel) -> CommandFor:
    """A cell model as a run's ``command_for``: every axis' command from one temperature sample and target."""
    evaluators = model.evaluators()

    def command(targets: dict[str, float], t: float, temps: dict[str, float]) -> dict[str, float]:
        for evaluator in evaluators.values():
            evaluator.observe(t, temps)
        x = aim(evaluators.values(), targets)
        return {axis: evaluator.command(x, t) for axis, evaluator in evaluators.items()}

    return command


def independent_command(models: Mapping[str, Model]) -> CommandFor:
    """One-axis models side by side (each fitted on ``Dataset.alone``, or one model of a cell of one axis):
    each axis' command from its own target only, what one-axis cells on the stage would serve."""
    evaluators = {a: m.evaluator() for a, m in models.items()}

    def command(targets: dict[str, float], t: float, temps: dict[str, float]) -> dict[str, float]:
        out = {}
        for axis, ev in evaluators.items():
            ev.observe(t, temps)
            out[axis] = float(ev.command(targets[axis], t))
        return out

    return command


def run_cell_validation(physics: CellPhysics, command: CommandFor | None, *, cycles: int = 30,
                        name: str | None = None, out_of_range: Callable[[dict[str, float], dict[str, float]], bool]
                        | None = None) -> CellValidationRun:
    """The ISO 9283 plan (:func:`nanodrift.calibration.plans.cell_validation_plan`) on a stack, uncompensated
    and, given ``command`` (targets, t, temps -> commands), through it; ``out_of_range`` counts the steps
    a model extrapolates."""
    plan = cell_validation_plan(physics.axes, cycles)
    targets = {a: np.array([s.target(a) for s in plan]) for a in physics.axes}
    step_cycles = [s.cycle for s in plan]
    extrapolating = 0

    def counted(t_um: dict[str, float], t: float, temps: dict[str, float]) -> dict[str, float]:
        nonlocal extrapolating
        if out_of_range is not None and out_of_range(t_um, temps):
            extrapolating += 1
        assert command is not None
        return command(t_um, t, temps)

    without = simulate_steps(physics, targets, step_cycles, schedule=ONE_MOVE)
    with_ = simulate_steps(physics, targets, step_cycles, schedule=ONE_MOVE, command_for=counted) if command else None
    return CellValidationRun(name or physics.scenario.name, physics.axes, targets, without, with_, extrapolating)
