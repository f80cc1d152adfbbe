"""The simulated XY/XYZ cell stepped through time: what the daemon's and a procedure's simulated drivers see.

:class:`SimulatedCell` for a stacked stage (:class:`~nanodrift.drivers.simulated.multiaxis.MultiAxisPhysics`):
one room and its thermocouples T1..T4 (read as on the one-axis cell), one closed-loop setpoint per axis
(each axis' output moves its own), and one interferometer beam per axis (channel
``interferometer_<axis>``) with its own white noise and slow wander. An axis' attained position depends
on every axis' setpoint (crosstalk, non-orthogonality, coupled bending) and on the room's drift, so
commanding y moves what the x beam then reads, as on the real stack.

``truth_log``: every interferometer reading beside the true position, one line each
(``t_s,axis,q_um,true_um,measured_um``).
"""

from __future__ import annotations

import math

import numpy as np

from nanodrift.drivers.base import Clock
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.multiaxis import MultiAxisPhysics
from nanodrift.drivers.simulated.physics import THERMOCOUPLES, TRUTH_CHANNELS

POSITION_PREFIX = "interferometer_"


def position_channel(axis: str) -> str:
    """The interferometer beam along ``axis``: ``interferometer_y``."""
    return POSITION_PREFIX + axis


class SimulatedMultiCell(SimulatedCell):
    """A stacked XY or XYZ stage in the one-axis cell's room, one setpoint and one beam per axis."""

    TRUTH_HEADER = "t_s,axis,q_um,true_um,measured_um\n"

    def __init__(self, physics: MultiAxisPhysics, clock: Clock | None = None, truth_log: str | None = None) -> None:
        super().__init__(physics.room, clock, truth_log)
        self.stack = physics
        self.axes = physics.axes
        self.channels = (*THERMOCOUPLES, *TRUTH_CHANNELS, *(position_channel(a) for a in self.axes))
        self._axis_of = {position_channel(a): a for a in self.axes}
        #: each axis' closed-loop setpoint (0 µm on a fresh cell) and its landing error
        self.q_um = dict.fromkeys(self.axes, 0.0)
        self.landing_um = dict.fromkeys(self.axes, 0.0)
        self.last_true_um = dict.fromkeys(self.axes, math.nan)

    def command_axis(self, axis: str, q_um: float) -> None:
        """``axis``' closed loop takes setpoint ``q_um`` now (the other axes hold theirs)."""
        self.landing_um[axis] = float(self._landing_rng.normal(0.0, self.physics.params.landing_sigma_um))
        self.q_um[axis] = float(q_um)
        self.commands += 1

    def command(self, q_um: float) -> None:
        raise TypeError("a multi-axis cell is commanded per axis (command_axis)")

    def true_positions(self, t: float | None = None) -> dict[str, float]:
        """Every axis' true attained position now (or at scenario time ``t``)."""
        when = np.array([self.sim_time() if t is None else t])
        static = self.stack.static({a: np.array([self.q_um[a]]) for a in self.axes})
        drift = self.stack.drift(when)
        return {a: float(static[a][0] + drift[a][0]) + self.landing_um[a] for a in self.axes}

    def true_position(self, t: float | None = None) -> float:
        return self.true_positions(t)[self.axes[0]]

    def is_position(self, channel: str) -> bool:
        return channel in self._axis_of

    def true_reading(self, channel: str) -> float | None:
        axis = self._axis_of.get(channel)
        return self.last_true_um[axis] if axis is not None else None

    def _read_position(self, channel: str, t: float, now: float, noise: float) -> float:
        axis = self._axis_of[channel]
        true_um = self.true_positions(t)[axis]
        self.last_true_um[axis] = true_um
        value = float(self.stack.measure(axis, np.array([t]), np.array([true_um]), np.array([noise]))[0])
        if self.truth_log is not None:
            self._log_axis_truth(now, axis, true_um, value)
        return value

    def _log_axis_truth(self, t: float, axis: str, true_um: float, measured_um: float) -> None:
        self._log_line(f"{t!r},{axis},{self.q_um[axis]!r},{true_um!r},{measured_um!r}\n")
