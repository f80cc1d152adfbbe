"""Terms only a multi-axis cell has: another axis' position in an axis' model.

On an XY stage the command of x depends on where y is: crosstalk and non-orthogonality move x by a
fraction of y (``y``), the stage bends when both are out (``x*y``), a stacked stage sags with the
other axis' extension (``y^2``), and an axis' gain can follow a temperature (``y*T1``). The same
stepwise selection chooses among them for every axis.

Names use the axes' own letters, so a model file reads as physics: ``x``, ``x^2`` and ``x*T1`` are
the one-axis terms (the ``x`` argument is always the x axis' position); ``y``, ``y^3``, ``x*y``,
``y*z``, ``y*T1``, ``dir(y)`` and ``creep(y, 15 s)`` are these. They parse only for a multi-axis
model (``parse_term(name, axes)``): in a one-axis file ``y`` stays a channel named ``y``. Their
features read the other axes' positions from ``channels[position_key(axis)]`` over a series
(``nanodrift.model.segments.features`` puts them there) and from :meth:`TermStream.targets` in the daemon.
"""

from __future__ import annotations

import math
import re
from collections.abc import Mapping

import numpy as np

from nanodrift.model.effect_terms import CREEP_DEADBAND_UM, Creep, _CreepStream
from nanodrift.model.terms import (
    _CHANNEL,
    _NUMBER,
    MAX_POWER,
    Channels,
    Direction,
    Term,
    TermStream,
    _ChannelStream,
    _DirectionStream,
    position_key,
    register_axis_term,
)


def _position(axis: str, x: np.ndarray | float, channels: Channels) -> np.ndarray:
    if axis == "x":
        return np.asarray(x, dtype=np.float64)
    return np.asarray(channels[position_key(axis)], dtype=np.float64)


class _Aimed:
    """Holds the target's positions (``targets``); each stream declares the ``positions`` slot."""

    __slots__ = ()
    positions: Mapping[str, float]

    def targets(self, positions: Mapping[str, float]) -> None:
        # the slot is each stream's own (two bases with slots cannot be combined), which mypy cannot see here
        self.positions = positions  # type: ignore[misc]

    def at(self, axis: str, x: float) -> float:
        """The target's position on ``axis``: ``x`` itself for the x axis, nan before any target."""
        return x if axis == "x" else self.positions.get(axis, math.nan)


class _AxisStream(_Aimed, TermStream):
    """``x`` comes as the ``x`` argument, the other axes through ``targets``."""

    __slots__ = ("positions",)

    def __init__(self) -> None:
        self.positions = {}


class _AxisPowerStream(_AxisStream):
    __slots__ = ("axis", "k")

    def __init__(self, axis: str, k: int) -> None:
        super().__init__()
        self.axis, self.k = axis, k

    def value(self, t: float, x: float) -> float:
        return float(self.at(self.axis, x) ** self.k)


class AxisPower(Term):
    """``y^k``: another axis' position to a power (crosstalk, non-orthogonality, sag of a stacked stage)."""

    uses_x = True

    def __init__(self, axis: str, k: int) -> None:
        if axis == "x":
            raise ValueError("the x axis' powers are the one-axis terms x .. x^k (nanodrift.model.terms.Power)")
        if not 1 <= k <= MAX_POWER:
            raise ValueError(f"power of {axis} must be between 1 and {MAX_POWER}, got {k}")
        self.axis, self.k = axis, k
        self.axes = (axis,)

    @property
    def name(self) -> str:
        return self.axis if self.k == 1 else f"{self.axis}^{self.k}"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        result: np.ndarray = _position(self.axis, x, channels) ** self.k
        return result

    def stream(self) -> TermStream:
        return _AxisPowerStream(self.axis, self.k)


class _ProductStream(_AxisStream):
    __slots__ = ("a", "b")

    def __init__(self, a: str, b: str) -> None:
        super().__init__()
        self.a, self.b = a, b

    def value(self, t: float, x: float) -> float:
        return self.at(self.a, x) * self.at(self.b, x)


class AxisProduct(Term):
    """``x*y``: two axes' positions multiplied (the stage bends when both are extended)."""

    uses_x = True

    def __init__(self, a: str, b: str) -> None:
        if a == b:
            raise ValueError(f"a product of two axes needs two different axes, got {a}*{b} (use {a}^2)")
        self.a, self.b = sorted((a, b))
        self.axes = tuple(axis for axis in (self.a, self.b) if axis != "x")

    @property
    def name(self) -> str:
        return f"{self.a}*{self.b}"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        result: np.ndarray = _position(self.a, x, channels) * _position(self.b, x, channels)
        return result

    def stream(self) -> TermStream:
        return _ProductStream(self.a, self.b)


class _AxisCouplingStream(_Aimed, _ChannelStream):
    __slots__ = ("axis", "positions")

    def __init__(self, axis: str, channel: str) -> None:
        super().__init__(channel)
        self.axis = axis
        self.positions = {}

    def value(self, t: float, x: float) -> float:
        return self.at(self.axis, x) * self.last


class AxisCoupling(Term):
    """``y*T1``: another axis' position times a channel (that axis' gain follows its temperature)."""

    uses_x = True

    def __init__(self, axis: str, channel: str) -> None:
        if axis == "x":
            raise ValueError("x*T1 is the one-axis term (nanodrift.model.effect_terms.PositionCoupling)")
        self.axis, self.channel = axis, channel
        self.axes = (axis,)
        self.channels = (channel,)

    @property
    def name(self) -> str:
        return f"{self.axis}*{self.channel}"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        result: np.ndarray = _position(self.axis, x, channels) * np.asarray(channels[self.channel], dtype=np.float64)
        return result

    def stream(self) -> TermStream:
        return _AxisCouplingStream(self.axis, self.channel)


class _AxisDirectionStream(_Aimed, _DirectionStream):
    __slots__ = ("axis", "positions")

    def __init__(self, axis: str, deadband: float) -> None:
        super().__init__(deadband)
        self.axis = axis
        self.positions = {}

    def value(self, t: float, x: float) -> float:
        return super().value(t, self.at(self.axis, x))

    def moved(self, t: float, x: float) -> None:
        super().moved(t, self.at(self.axis, x))


class AxisDirection(Direction):
    """``dir(y)``: the direction of the last step of axis y (hysteresis of that axis' piezo stack)."""

    def __init__(self, axis: str, deadband_um: float = 0.5) -> None:
        if axis == "x":
            raise ValueError("the x axis' direction is the one-axis term dir")
        super().__init__(deadband_um)
        self.axis = axis
        self.axes = (axis,)

    @property
    def name(self) -> str:
        return f"dir({self.axis})" if self.deadband_um == 0.5 else f"dir({self.axis}, {self.deadband_um:g} um)"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        return super().batch(t, _position(self.axis, x, channels), channels)

    def stream(self) -> TermStream:
        return _AxisDirectionStream(self.axis, self.deadband_um)


class _AxisCreepStream(_Aimed, _CreepStream):
    __slots__ = ("axis", "positions")

    def __init__(self, axis: str, tau_s: float, deadband: float) -> None:
        super().__init__(tau_s, deadband)
        self.axis = axis
        self.positions = {}

    def value(self, t: float, x: float) -> float:
        return super().value(t, self.at(self.axis, x))

    def moved(self, t: float, x: float) -> None:
        super().moved(t, self.at(self.axis, x))


class AxisCreep(Creep):
    """``creep(y, 15 s)``: axis y's steps, each decaying with time constant τ (that axis' piezo creep)."""

    def __init__(self, axis: str, tau_s: float, deadband_um: float = CREEP_DEADBAND_UM) -> None:
        if axis == "x":
            raise ValueError("the x axis' creep is the one-axis term creep(τ s)")
        super().__init__(tau_s, deadband_um)
        self.axis = axis
        self.axes = (axis,)

    @property
    def name(self) -> str:
        if self.deadband_um == CREEP_DEADBAND_UM:
            return f"creep({self.axis}, {self.tau_s:g} s)"
        return f"creep({self.axis}, {self.tau_s:g} s, {self.deadband_um:g} um)"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        return super().batch(t, _position(self.axis, x, channels), channels)

    def stream(self) -> TermStream:
        return _AxisCreepStream(self.axis, self.tau_s, self.deadband_um)


_POWER = re.compile(r"^(?P<axis>[a-z])(?:\^(?P<k>[1-9]\d*))?$")
_PRODUCT = re.compile(r"^(?P<a>[a-z])\s*\*\s*(?P<b>[a-z])$")
_COUPLING = re.compile(rf"^(?P<axis>[a-z])\s*\*\s*(?P<ch>{_CHANNEL})$")
_DIRECTION = re.compile(rf"^dir\(\s*(?P<axis>[a-z])\s*(?:,\s*(?P<db>{_NUMBER})\s*um\s*)?\)$")
_CREEP = re.compile(rf"^creep\(\s*(?P<axis>[a-z])\s*,\s*(?P<tau>{_NUMBER})\s*s\s*(?:,\s*(?P<db>{_NUMBER})\s*um\s*)?\)$")


def _parse(name: str, axes: tuple[str, ...]) -> Term | None:
    """The multi-axis term ``name`` stands for in a cell with ``axes``, or None (a one-axis name)."""
    if (m := _POWER.match(name)) and m["axis"] in axes and m["axis"] != "x":
        return AxisPower(m["axis"], int(m["k"] or 1))
    if (m := _PRODUCT.match(name)) and m["a"] in axes and m["b"] in axes and m["a"] != m["b"]:
        return AxisProduct(m["a"], m["b"])
    if (m := _COUPLING.match(name)) and m["axis"] in axes and m["axis"] != "x" and m["ch"] not in axes:
        return AxisCoupling(m["axis"], m["ch"])
    if (m := _DIRECTION.match(name)) and m["axis"] in axes and m["axis"] != "x":
        return AxisDirection(m["axis"], float(m["db"]) if m["db"] else 0.5)
    if (m := _CREEP.match(name)) and m["axis"] in axes and m["axis"] != "x":
        return AxisCreep(m["axis"], float(m["tau"]), float(m["db"]) if m["db"] else CREEP_DEADBAND_UM)
    return None


register_axis_term(_parse)
