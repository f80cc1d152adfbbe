"""What only a cell of several axes adds to the terms: the product of two axes, and the names of another axis' terms.

On an XY stage the command of x depends on where y is: crosstalk and non-orthogonality move x by a
fraction of y (``y``), the stage bends when both are out (``x*y``), a stacked stage sags with the
other axis' extension (``y^2``), and an axis' gain can follow a temperature (``y*T1``). The same
stepwise selection chooses among them for every axis.

Names use the axes' own letters, so a model file reads as physics: ``x``, ``x^2`` and ``x*T1`` are
the one-axis terms (the ``x`` argument is always the x axis' position); ``y``, ``y^3``, ``y*T1``,
``dir(y)`` and ``creep(y, 15 s)`` are the same kinds of term (:class:`Power`, :class:`PositionCoupling`,
:class:`Direction`, :class:`Creep`) for axis y, and ``x*y`` is :class:`AxisProduct`. They parse only
for a multi-axis model (``parse_term(name, axes)``): in a one-axis file ``y`` stays a channel named
``y``. Their features read the other axes' positions from ``channels[position_key(axis)]`` over a
series (``nanodrift.model.segments.features`` puts them there) and from :meth:`TermStream.targets`
in the daemon.
"""

from __future__ import annotations

import re

import numpy as np

from nanodrift.model.effect_terms import CREEP_DEADBAND_UM, Creep, PositionCoupling
from nanodrift.model.terms import (
    _CHANNEL,
    _NUMBER,
    Channels,
    Direction,
    Power,
    Term,
    TermStream,
    _Aimed,
    _read_axes,
    axis_position,
    register_axis_term,
)


class _ProductStream(_Aimed, TermStream):
    __slots__ = ("a", "b", "positions")

    def __init__(self, a: str, b: str) -> None:
        self.a, self.b = a, b
        self.positions = {}

    def value(self, t: float, x: float) -> float:
        return self.at(self.a, x) * self.at(self.b, x)


class AxisProduct(Term):
    """``x*y``: two axes' positions multiplied (the stage bends when both are extended)."""

    uses_x = True

    def __init__(self, a: str, b: str) -> None:
        if a == b:
            raise ValueError(f"a product of two axes needs two different axes, got {a}*{b} (use {a}^2)")
        self.a, self.b = sorted((a, b))
        self.axes = _read_axes(self.a) + _read_axes(self.b)

    @property
    def name(self) -> str:
        return f"{self.a}*{self.b}"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        result: np.ndarray = axis_position(self.a, x, channels) * axis_position(self.b, x, channels)
        return result

    def stream(self) -> TermStream:
        return _ProductStream(self.a, self.b)


_POWER = re.compile(r"^(?P<axis>[a-z])(?:\^(?P<k>[1-9]\d*))?$")
_PRODUCT = re.compile(r"^(?P<a>[a-z])\s*\*\s*(?P<b>[a-z])$")
_COUPLING = re.compile(rf"^(?P<axis>[a-z])\s*\*\s*(?P<ch>{_CHANNEL})$")
_DIRECTION = re.compile(rf"^dir\(\s*(?P<axis>[a-z])\s*(?:,\s*(?P<db>{_NUMBER})\s*um\s*)?\)$")
_CREEP = re.compile(rf"^creep\(\s*(?P<axis>[a-z])\s*,\s*(?P<tau>{_NUMBER})\s*s\s*(?:,\s*(?P<db>{_NUMBER})\s*um\s*)?\)$")


def _parse(name: str, axes: tuple[str, ...]) -> Term | None:
    """The term of an axis other than x that ``name`` stands for in a cell with ``axes``, or None (a one-axis name:
    the x axis' terms parse as in a one-axis file)."""
    def other(axis: str) -> bool:
        return axis in axes and axis != "x"

    if (m := _POWER.match(name)) and other(m["axis"]):
        return Power(int(m["k"] or 1), m["axis"])
    if (m := _PRODUCT.match(name)) and m["a"] in axes and m["b"] in axes and m["a"] != m["b"]:
        return AxisProduct(m["a"], m["b"])
    if (m := _COUPLING.match(name)) and other(m["axis"]) and m["ch"] not in axes:
        return PositionCoupling(m["ch"], m["axis"])
    if (m := _DIRECTION.match(name)) and other(m["axis"]):
        return Direction(float(m["db"]) if m["db"] else 0.5, m["axis"])
    if (m := _CREEP.match(name)) and other(m["axis"]):
        return Creep(float(m["tau"]), float(m["db"]) if m["db"] else CREEP_DEADBAND_UM, m["axis"])
    return None


register_axis_term(_parse)
