"""A whole stepped run of the simulated cell as arrays, in one vectorised pass.

The schedule is the paper's (Fig. 7): for each target, the command ramps from the previous target in
``ramp_s`` (sub-commands every ``ramp_interval_s``), holds ``hold_s``, and the step's measurement is
the average of the samples in the last ``window_s`` of the hold, each sensor sampled every its own
interval from the start of the hold: exactly what the asynchronous procedure records from the
drivers, so ``nanodrift simulate`` output looks like a recorded calibration and fits directly.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from nanodrift.calibration.plans import StepTiming, ramp_commands
from nanodrift.drivers.simulated.physics import THERMOCOUPLES, CellPhysics


@dataclass(frozen=True)
class StepSchedule(StepTiming):
    """The procedure's step timing (Fig. 7), plus how often the simulated sensors are sampled."""

    position_interval_s: float = 0.1
    temperature_interval_s: float = 0.5


def _window_offsets(interval: float, schedule: StepSchedule) -> np.ndarray:
    """Sample times relative to the start of the hold that fall in the averaging window."""
    times = np.arange(0.0, schedule.hold_s + 1e-9, interval)
    return times[times > schedule.hold_s - schedule.window_s - 1e-9]


def simulate_steps(
    physics: CellPhysics,
    targets: Sequence[float],
    cycles: Sequence[int],
    *,
    schedule: StepSchedule | None = None,
    channels: Sequence[str] = tuple(THERMOCOUPLES),
    command_for: Callable[[float, float, dict[str, float]], float] | None = None,
    t_start: float = 0.0,
) -> dict[str, np.ndarray]:
    """Step averages for ``targets`` (one row per step): t_s, x_um (measured), q_um, cycle, channels.

    ``command_for(target, t, temps)`` turns a target into a command (a model's compensation); by
    default the command is the target. ``t_s`` is the end of each step's averaging window.
    """
    schedule = schedule or StepSchedule()
    target_um = np.asarray(targets, dtype=np.float64)
    n = target_um.size
    step_start = t_start + schedule.step_s * np.arange(n)
    hold_start = step_start + schedule.ramp_s
    commands = target_um.copy()
    noise_rng = np.random.default_rng([physics.seed, 3])
    if command_for is not None:  # needs the temperatures seen when each step is commanded
        thermal = physics.thermal(step_start)
        seen = {c: physics.measure_temperature(c, physics.sensor_truth(c, thermal), noise_rng.normal(size=n))
                for c in channels}
        for k in range(n):
            temps = {c: float(seen[c][k]) for c in channels}
            commands[k] = command_for(float(target_um[k]), float(step_start[k]), temps)
    cmd_t, cmd_q = [], []
    q_prev = 0.0
    for k in range(n):
        offsets, qs = ramp_commands(q_prev, float(commands[k]), schedule.ramp_s, schedule.ramp_interval_s)
        cmd_t.append(float(step_start[k]) + offsets)
        cmd_q.append(qs)
        q_prev = float(commands[k])
    landing_rng = np.random.default_rng([physics.seed, 2])
    track = physics.command_track(np.concatenate(cmd_t), np.concatenate(cmd_q), landing_rng)

    pos_off = _window_offsets(schedule.position_interval_s, schedule)
    pos_t = (hold_start[:, None] + pos_off[None, :]).ravel()
    true_x = physics.attained_along(pos_t, track)
    meas = physics.measure_position(pos_t, true_x, noise_rng.normal(size=pos_t.size))
    out: dict[str, np.ndarray] = {
        "t_s": hold_start + schedule.hold_s,
        "x_um": meas.reshape(n, -1).mean(axis=1),
        "q_um": commands,
        "cycle": np.asarray(cycles, dtype=np.float64),
    }
    tc_off = _window_offsets(schedule.temperature_interval_s, schedule)
    tc_t = (hold_start[:, None] + tc_off[None, :]).ravel()
    thermal = physics.thermal(tc_t)
    for c in channels:
        read = physics.measure_temperature(c, physics.sensor_truth(c, thermal), noise_rng.normal(size=tc_t.size))
        out[c] = read.reshape(n, -1).mean(axis=1)
    return out
