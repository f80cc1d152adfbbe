"""Terms for the effects discovery adds beyond the paper's model, registered with ``register_term``.

Imported by ``nanodrift.model`` so a model file naming these terms loads anywhere. Each term computes
its feature over a whole series (``batch``, vectorised) and sample by sample (``stream``) with the
same result; ``lag(T4, 2100 s)`` and ``dir`` already live in :mod:`nanodrift.model.terms`.

- ``x*T1``: position-thermal coupling, the stage's gain changes with its temperature.
- ``rate(T4, 300 s)``: rate of change of a channel, smoothed by a first-order lag of time constant
  τ: ``(T4 - lag(T4, τ)) / τ`` in °C/s, which is exactly the derivative of the lagged signal, so the
  batch (``lag_filter``) and streaming (the same recurrence) values agree.
- ``creep(15 s)``: the stage settling after its steps: ``Σ_i dq_i exp(-(t - t_i)/τ)`` over the
  commanded steps dq_i (row-to-row changes of x larger than the deadband, as ``dir`` detects them),
  each at the time it was commanded. With rows recorded a fixed delay after their step (the
  paper's step averages) the delay only scales the feature, which the coefficient absorbs.
"""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from nanodrift.model.terms import (
    Channels,
    Term,
    TermStream,
    _Aimed,
    _ChannelStream,
    _LagStream,
    _read_axes,
    axis_position,
    lag_filter,
    register_term,
    time_constant,
)

CREEP_DEADBAND_UM = 0.5


class _CouplingStream(_Aimed, _ChannelStream):
    """The channel's latest value, times the target's position on the axis."""

    __slots__ = ("axis", "positions")

    def __init__(self, channel: str, axis: str) -> None:
        super().__init__(channel)
        self.axis = axis
        self.positions = {}

    def value(self, t: float, x: float) -> float:
        return self.at(self.axis, x) * self.last


class PositionCoupling(Term):
    """``x*T1``: position times a channel (``y*T1``: axis y's, in a cell of several axes). Physics: the stage's
    gain depends on its temperature."""

    uses_x = True

    def __init__(self, channel: str, axis: str = "x") -> None:
        self.channel, self.axis = channel, axis
        self.channels = (channel,)
        self.axes = _read_axes(axis)

    @property
    def name(self) -> str:
        return f"{self.axis}*{self.channel}"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        result: np.ndarray = axis_position(self.axis, x, channels) * np.asarray(channels[self.channel],
                                                                                dtype=np.float64)
        return result

    def stream(self) -> TermStream:
        return _CouplingStream(self.channel, self.axis)


class _RateStream(_LagStream):
    """The lag's state plus the last input: rate = (u - lag(u)) / tau."""

    __slots__ = ("u",)

    def __init__(self, channel: str, tau_s: float) -> None:
        super().__init__(channel, tau_s)
        self.u = math.nan

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        super().observe(t, temps)
        self.u = temps.get(self.channel, self.u)

    def value(self, t: float, x: float) -> float:
        return (self.u - self.y) / self.tau_s


class Rate(Term):
    """``rate(T4, 300 s)``: smoothed rate of change of a channel, °C/s (derivative of its τ-lag).

    Physics: while the room warms or cools, a temperature gradient through the cell bends it in
    proportion to how fast the temperature changes, not to its level.
    """

    def __init__(self, channel: str, tau_s: float) -> None:
        self.channel, self.tau_s = channel, time_constant(tau_s, "rate smoothing time constant")
        self.channels = (channel,)

    @property
    def name(self) -> str:
        return f"rate({self.channel}, {self.tau_s:g} s)"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        u = np.asarray(channels[self.channel], dtype=np.float64)
        rate: np.ndarray = (u - lag_filter(t, u, self.tau_s)) / self.tau_s
        return rate

    def stream(self) -> TermStream:
        return _RateStream(self.channel, self.tau_s)


class _CreepStream(_Aimed, TermStream):
    __slots__ = ("axis", "deadband", "last_x", "positions", "state", "t_last", "tau_s")

    def __init__(self, tau_s: float, deadband: float, axis: str) -> None:
        self.tau_s, self.deadband, self.axis = tau_s, deadband, axis
        self.state = 0.0
        self.t_last = math.nan
        self.last_x = math.nan
        self.positions = {}

    def _value(self, t: float, x: float) -> float:
        if math.isnan(self.last_x):
            return 0.0
        step = x - self.last_x
        dq = step if abs(step) > self.deadband else 0.0
        return self.state * math.exp(-(t - self.t_last) / self.tau_s) + dq

    def value(self, t: float, x: float) -> float:
        return self._value(t, self.at(self.axis, x))

    def moved(self, t: float, x: float) -> None:
        x = self.at(self.axis, x)
        self.state = self._value(t, x)
        self.t_last, self.last_x = t, x


class Creep(Term):
    """``creep(15 s)``: the steps' sizes, each decaying with time constant τ since it was commanded
    (``creep(y, 15 s)``: axis y's, in a cell of several axes).

    Physics: a piezo stack keeps creeping after a step, by a fraction of the step that dies out.
    Batch form: with s_k = a_k s_{k-1} + dq_k (a_k = exp(-Δt_k/τ)), ``x_eff - s`` follows the lag
    recurrence driven by the previous row's ``x_eff`` (the running sum of the counted steps), so
    ``s = x_eff - lag_filter(t, x_eff delayed one row, τ)``: vectorised, and equal to the stream.
    """

    uses_x = True

    def __init__(self, tau_s: float, deadband_um: float = CREEP_DEADBAND_UM, axis: str = "x") -> None:
        self.tau_s = time_constant(tau_s, "creep time constant")
        if not (math.isfinite(deadband_um) and deadband_um >= 0):
            raise ValueError(f"creep deadband must be a finite number >= 0 um, got {deadband_um}")
        self.deadband_um = float(deadband_um)
        self.axis = axis
        self.axes = _read_axes(axis)

    @property
    def name(self) -> str:
        deadband = [] if self.deadband_um == CREEP_DEADBAND_UM else [f"{self.deadband_um:g} um"]
        return f"creep({', '.join([*self.axes, f'{self.tau_s:g} s', *deadband])})"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        x = axis_position(self.axis, x, channels)
        if x.shape[0] == 0:
            return np.empty(0)
        step = np.diff(x, prepend=x[:1])
        counted = np.where(np.abs(step) > self.deadband_um, step, 0.0)
        x_eff = np.cumsum(counted)
        delayed = np.concatenate((x_eff[:1], x_eff[:-1]))
        creep: np.ndarray = x_eff - lag_filter(t, delayed, self.tau_s)
        return creep

    def stream(self) -> TermStream:
        return _CreepStream(self.tau_s, self.deadband_um, self.axis)


register_term(r"x\s*\*\s*(?P<ch>{channel})", lambda m: PositionCoupling(m.group("ch")))
register_term(
    r"rate\(\s*(?P<ch>{channel})\s*,\s*(?P<tau>{number})\s*s\s*\)",
    lambda m: Rate(m.group("ch"), float(m.group("tau"))),
)
register_term(
    r"creep\(\s*(?P<tau>{number})\s*s\s*(?:,\s*(?P<db>{number})\s*um\s*)?\)",
    lambda m: Creep(float(m.group("tau")), float(m.group("db")) if m.group("db") else CREEP_DEADBAND_UM),
)
