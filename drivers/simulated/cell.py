"""The simulated cell stepped through time: what the simulated sensors read and the actuators move.

One instance per daemon/procedure, shared by every simulated sensor group and actuator (through
``DriverContext.resources``), so a command moves the stage the interferometer then sees. Each axis has its
own closed-loop setpoint and interferometer beam (``interferometer`` on a cell of one axis, else
``interferometer_<axis>``); on a stack an axis' position depends on every axis' setpoint (crosstalk,
non-orthogonality, coupled bending), so commanding y moves what the x beam reads. Time is the clock's,
relative to the cell's creation (scenario time 0). Faults can be injected per channel
for tests and demos: ``fault`` (burnout reading), ``stale`` (the device repeats an old sample),
``device_error`` (the link fails: :class:`~nanodrift.drivers.base.DeviceError`).

``truth_log``: a CSV the cell appends each interferometer reading to with the true attained position, one
line each, line-buffered (nothing held in memory), so a benchmark can score what the daemon served against
the truth, not only the interferometer's view: ``t_s,q_um,true_x_um,measured_x_um`` on a cell of one axis,
``t_s,axis,q_um,true_um,measured_um`` on a stack.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TextIO

import numpy as np

from nanodrift.drivers.base import Clock, DeviceError, MonotonicClock, Reading, State
from nanodrift.drivers.simulated.physics import POSITION_CHANNEL, THERMOCOUPLES, TRUTH_CHANNELS, CellPhysics, StageState

FaultMode = Literal["fault", "stale", "device_error"]


def position_channels(axes: tuple[str, ...]) -> dict[str, str]:
    """Interferometer channel -> its axis: ``interferometer`` on a cell of one axis, ``interferometer_y`` on a stack."""
    if len(axes) == 1:
        return {POSITION_CHANNEL: axes[0]}
    return {f"{POSITION_CHANNEL}_{axis}": axis for axis in axes}


@dataclass(frozen=True)
class FaultWindow:
    channel: str
    start_s: float
    end_s: float
    mode: FaultMode = "fault"


class SimulatedCell:
    def __init__(self, physics: CellPhysics, clock: Clock | None = None, truth_log: str | None = None) -> None:
        self.physics = physics
        self.axes = physics.axes
        self.clock = clock or MonotonicClock()
        self.epoch = self.clock.now()
        #: each axis' stage after its last command (setpoint 0 µm on a fresh cell)
        self.states = {axis: StageState() for axis in self.axes}
        self.faults: list[FaultWindow] = []
        self.commands = 0
        self._landing_rng = np.random.default_rng([physics.seed, 2])
        self._noise_rng = np.random.default_rng([physics.seed, 3])
        self._last_ok: dict[str, Reading] = {}
        self._axis_of = position_channels(self.axes)
        #: what a sensor may read (``[[sensors]] channel``)
        self.channels: tuple[str, ...] = (*THERMOCOUPLES, *TRUTH_CHANNELS, *self._axis_of)
        self.truth_log = truth_log
        self._truth_file: TextIO | None = None
        #: the true attained position behind each axis' last interferometer reading (nan before one):
        #: what a validation on the simulated cell is scored against besides the interferometer
        self.last_true_um = dict.fromkeys(self.axes, math.nan)

    def sim_time(self) -> float:
        return self.clock.now() - self.epoch

    # ----- actuator side -------------------------------------------------------------------------
    def command(self, axis: str, q_um: float) -> None:
        """``axis``' closed loop takes setpoint ``q_um`` now (the other axes hold theirs)."""
        landing = float(self._landing_rng.normal(0.0, self.physics.params.landing_sigma_um))
        self.states[axis] = self.physics.after_command(self.states[axis], self.sim_time(), float(q_um), landing)
        self.commands += 1

    def true_positions(self, t: float | None = None) -> dict[str, float]:
        """Every axis' true attained position now (or at scenario time ``t``)."""
        return self.physics.attained_now(self.sim_time() if t is None else t, self.states)

    # ----- sensor side ---------------------------------------------------------------------------
    def inject_fault(self, channel: str, start_s: float, end_s: float, mode: FaultMode = "fault") -> None:
        """Make ``channel`` misbehave during [start_s, end_s) of scenario time."""
        if channel not in self.channels:
            raise ValueError(f"unknown simulated channel {channel!r}; channels: {', '.join(self.channels)}")
        self.faults.append(FaultWindow(channel, start_s, end_s, mode))

    def read(self, channels: Iterable[str]) -> dict[str, Reading]:
        """One poll of ``channels`` now, with noise; honours injected faults."""
        t = self.sim_time()
        now = self.clock.now()
        names = list(channels)
        out: dict[str, Reading] = {}
        axis_of, physics, faults, last_ok = self._axis_of, self.physics, self.faults, self._last_ok
        normal = self._noise_rng.standard_normal
        thermal = physics.thermal1(t) if any(name not in axis_of for name in names) else {}
        for name in names:
            axis = axis_of.get(name)
            unit = "degC" if axis is None else "um"
            window = (next((w for w in faults if w.channel == name and w.start_s <= t < w.end_s), None)
                      if faults else None)
            if window is not None:
                if window.mode == "device_error":
                    raise DeviceError(f"simulated {name}: link failure (injected)")
                if window.mode == "fault":
                    out[name] = Reading.fault(now, "open thermocouple (injected)" if unit == "degC" else
                                              "beam lost (injected)", unit=unit)
                    continue
                if window.mode == "stale" and name in last_ok:
                    out[name] = last_ok[name]
                    continue
            noise = float(normal())
            if axis is not None:
                value = self._read_position(axis, t, now, noise)
            else:
                value = physics.measure_temperature1(physics.sensor_truth(name, thermal), noise)
            reading = Reading(value, now, State.OK, "", unit)
            if math.isfinite(value):
                last_ok[name] = reading
            out[name] = reading
        return out

    def is_position(self, channel: str) -> bool:
        """Whether ``channel`` is an interferometer (µm), not a temperature."""
        return channel in self._axis_of

    def true_reading(self, channel: str) -> float | None:
        """The true attained position behind ``channel``'s last reading (None: a temperature channel)."""
        axis = self._axis_of.get(channel)
        return self.last_true_um[axis] if axis is not None else None

    def _read_position(self, axis: str, t: float, now: float, noise: float) -> float:
        self.last_true_um[axis] = true_um = self.physics.attained_now(t, self.states)[axis]
        value = float(self.physics.measure_position1(axis, t, true_um, noise))  # the realistic cell's is numpy's
        if self.truth_log is not None:
            self._log_truth(now, axis, true_um, value)
        return value

    def _log_truth(self, t: float, axis: str, true_um: float, measured_um: float) -> None:
        one_axis = len(self.axes) == 1  # the one-axis log keeps the columns benchmarks/week.py reads
        if self._truth_file is None:
            assert self.truth_log is not None
            path = Path(self.truth_log)
            fresh = not path.exists() or path.stat().st_size == 0
            self._truth_file = open(path, "a", buffering=1, encoding="utf-8")  # held open: a line a poll
            if fresh:
                self._truth_file.write("t_s,q_um,true_x_um,measured_x_um\n" if one_axis
                                       else "t_s,axis,q_um,true_um,measured_um\n")
        where = "" if one_axis else f"{axis},"
        self._truth_file.write(f"{float(t)!r},{where}{float(self.states[axis].q)!r},{float(true_um)!r},"
                               f"{float(measured_um)!r}\n")  # plain floats: np.float64's repr is not a number
