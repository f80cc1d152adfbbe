"""A model is a list of named terms: this module is that vocabulary.

A term is a feature with a physical meaning (``x^3``, ``T2``, ``1``, ``lag(T4, 2100 s)``, ``dir``,
``(T2 - 22.05)^2``).
Each computes its feature two ways that must agree:

- ``batch(t, x, channels)`` over a whole recorded series (fit, predict, discovery), and
- ``stream()``: a small state machine the daemon feeds sample by sample (``observe`` a temperature
  sample, ``value`` at a target, ``moved`` when the stage is commanded).

Feeding a series row by row (observe, value, moved) reproduces ``batch`` to rounding, which is why an
effect found offline is applied online without new code. The term's ``name`` is its canonical text:
the model file stores names, and :func:`parse_term` turns them back into terms.
"""

from __future__ import annotations

import math
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TypeGuard

import numpy as np

Channels = Mapping[str, np.ndarray]

#: highest power of x a model may use: the paper needs 3, and x^13 of a 500 um stroke is ~1e35,
#: where a coefficient that cancels it cannot be written down exactly
MAX_POWER = 12


class UnknownTermError(ValueError):
    """A term name no registered kind understands."""


class TermStream:
    """Streaming state of one term. The default is stateless: override what the term needs."""

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        """A temperature sample arrived at ``t`` (``temps`` may hold only some channels)."""

    @abstractmethod
    def value(self, t: float, x: float) -> float:
        """The feature for target ``x`` at time ``t`` given everything observed so far."""

    def moved(self, t: float, x: float) -> None:
        """The stage was commanded to ``x`` at ``t``."""

    def targets(self, positions: Mapping[str, float]) -> None:
        """A multi-axis cell's target, every axis' position (µm), given before ``value`` and ``moved``.

        Only terms that read an axis other than ``x`` (:attr:`Term.axes`) use it: ``x`` itself is
        the ``x`` argument, as in a one-axis cell.
        """


class Term(ABC):
    """A named feature of the model."""

    #: temperature channels the feature reads
    channels: tuple[str, ...] = ()
    #: depends on the target or the motion (else only on temperatures and time)
    uses_x: bool = False
    #: axes other than ``x`` whose position the feature reads (multi-axis cells): in a series they
    #: arrive in ``channels`` as ``<axis>_um`` (:func:`position_key`), in a stream through ``targets``
    axes: tuple[str, ...] = ()

    @property
    @abstractmethod
    def name(self) -> str: ...

    @abstractmethod
    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        """The feature for every row of a series."""

    @abstractmethod
    def stream(self) -> TermStream:
        """A fresh streaming state."""

    def __repr__(self) -> str:
        return f"<term {self.name}>"

    def __eq__(self, other: object) -> bool:
        return isinstance(other, Term) and other.name == self.name

    def __hash__(self) -> int:
        return hash(self.name)


# --- positions -------------------------------------------------------------------------------------


def position_key(axis: str) -> str:
    """Where a series' ``channels`` mapping carries an axis' position for the terms that read it."""
    return f"{axis}_um"


def axis_position(axis: str, x: np.ndarray | float, channels: Channels) -> np.ndarray:
    """``axis``' position over a series: the ``x`` argument for the x axis, else ``channels[position_key(axis)]``."""
    if axis == "x":
        return np.asarray(x, dtype=np.float64)
    return np.asarray(channels[position_key(axis)], dtype=np.float64)


def _read_axes(axis: str) -> tuple[str, ...]:
    """:attr:`Term.axes` of a term reading ``axis``' position: none for x, which comes as the ``x`` argument."""
    return () if axis == "x" else (axis,)


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


# --- the paper's terms (eq. 3) --------------------------------------------------------------


class _PowerStream(_Aimed, TermStream):
    __slots__ = ("axis", "k", "positions")

    def __init__(self, axis: str, k: int) -> None:
        self.axis, self.k = axis, k
        self.positions = {}

    def value(self, t: float, x: float) -> float:
        return float(self.at(self.axis, x) ** self.k)


class Power(Term):
    """``x^k``: the geometric (inverse-kinematic) polynomial of eq. 1. In a cell of several axes, ``y^k``:
    another axis' position to a power in this axis' model (crosstalk, non-orthogonality, sag of a stacked stage)."""

    uses_x = True

    def __init__(self, k: int, axis: str = "x") -> None:
        if not 1 <= k <= MAX_POWER:
            raise ValueError(f"power of {axis} must be between 1 and {MAX_POWER} ({axis} .. {axis}^{MAX_POWER}), "
                             f"got {k}")
        self.k, self.axis = k, axis
        self.axes = _read_axes(axis)

    @property
    def name(self) -> str:
        return self.axis if self.k == 1 else f"{self.axis}^{self.k}"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        result: np.ndarray = axis_position(self.axis, x, channels) ** self.k
        return result

    def stream(self) -> TermStream:
        return _PowerStream(self.axis, self.k)


def is_x_power(term: Term) -> TypeGuard[Power]:
    """A power of the target ``x`` itself: what the evaluators fold into one polynomial."""
    return isinstance(term, Power) and term.axis == "x"


class _ConstStream(TermStream):
    def value(self, t: float, x: float) -> float:
        return 1.0


class Bias(Term):
    """``1``: the bias γ of eq. 2."""

    @property
    def name(self) -> str:
        return "1"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        return np.ones_like(t, dtype=np.float64)

    def stream(self) -> TermStream:
        return _ConstStream()


class _ChannelStream(TermStream):
    __slots__ = ("channel", "last")

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.last = math.nan

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        value = temps.get(self.channel)
        if value is not None:
            self.last = value

    def value(self, t: float, x: float) -> float:
        return self.last


class Channel(Term):
    """A temperature channel, first order (eq. 2): the thermal elongation is linear in temperature."""

    def __init__(self, channel: str) -> None:
        self.channel = channel
        self.channels = (channel,)

    @property
    def name(self) -> str:
        return self.channel

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        return np.asarray(channels[self.channel], dtype=np.float64)

    def stream(self) -> TermStream:
        return _ChannelStream(self.channel)


class _ChannelSquareStream(_ChannelStream):
    __slots__ = ("centre_c",)

    def __init__(self, channel: str, centre_c: float) -> None:
        super().__init__(channel)
        self.centre_c = centre_c

    def value(self, t: float, x: float) -> float:
        return (self.last - self.centre_c) ** 2


class ChannelSquare(Term):
    """``(T2 - 22.05)^2``: a channel's curvature about a centre (the bracket's bending, II.B.2).

    Invisible in the paper's 0.5 °C calibration, it is what a linear thermal model misses over a week's
    few degrees; :func:`nanodrift.model.identify.curvature_candidates` offers it only where the data spans
    enough of the channel to estimate it. The centre (the training range's middle) keeps the feature
    small and the fit well conditioned; beside the channel's linear term and the bias any centre spans
    the same models.
    """

    def __init__(self, channel: str, centre_c: float) -> None:
        if not math.isfinite(centre_c):
            raise ValueError(f"the centre of ({channel} - c)^2 must be a finite temperature, got {centre_c}")
        self.channel = channel
        self.centre_c = float(centre_c)
        self.channels = (channel,)

    @property
    def name(self) -> str:
        sign = "-" if self.centre_c >= 0 else "+"
        centre = repr(abs(self.centre_c))  # the shortest text that reads back as the same float
        return f"({self.channel} {sign} {centre.removesuffix('.0')})^2"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        return (np.asarray(channels[self.channel], dtype=np.float64) - self.centre_c) ** 2

    def stream(self) -> TermStream:
        return _ChannelSquareStream(self.channel, self.centre_c)


# --- stateful terms ---------------------------------------------------------------------------


def time_constant(tau_s: float, what: str) -> float:
    """``tau_s`` as a float; ValueError naming ``what`` unless it is a finite number > 0 s."""
    if not (math.isfinite(tau_s) and tau_s > 0):
        raise ValueError(f"{what} must be a finite number > 0 s, got {tau_s}")
    return float(tau_s)


def lag_filter(t: np.ndarray, u: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag of ``u`` sampled at times ``t``, exact per sample: y_k = y_{k-1} + α_k (u_k - y_{k-1}).

    α_k = 1 - exp(-(t_k - t_{k-1}) / τ), y_0 = u_0 — the same recurrence the streaming state runs.
    Uniform sampling runs that recurrence in C (``scipy.signal.lfilter``). Irregular sampling uses the
    closed form y_k = w_k (y_0 + Σ_{j≤k} α_j u_j / w_j), w_k = exp(-(t_k - t_0)/τ), on ``u`` minus
    its first value (smaller sums, smaller rounding), in chunks short enough that w stays finite.
    """
    t = np.asarray(t, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    n = t.shape[0]
    if n == 0:
        return np.empty(0, dtype=np.float64)
    dt = np.diff(t)
    u0 = float(u[0])
    v = u - u0
    if n > 1 and float(dt.max() - dt.min()) <= 1e-12 * max(1.0, abs(float(dt[0]))):
        from scipy.signal import lfilter  # a second to import: only for series, never at a command's start

        step = -math.expm1(-float(dt[0]) / tau_s)
        y, _ = lfilter([step], [1.0, step - 1.0], v[1:], zi=[(1.0 - step) * 0.0])
        return np.concatenate(([u0], y + u0))
    alpha = np.empty(n, dtype=np.float64)
    alpha[0] = 1.0  # y_0 = u_0
    alpha[1:] = -np.expm1(-dt / tau_s)
    y = np.empty(n, dtype=np.float64)
    start, y_prev = 0, 0.0
    max_span = 200.0 * tau_s  # keeps exp(±span/τ) far from overflow
    while start < n:
        stop = max(int(np.searchsorted(t, t[start] + max_span, side="right")), start + 1)
        w = np.exp(-(t[start:stop] - t[start]) / tau_s)
        a = alpha[start:stop]
        # fold the state before the chunk into its first step: y_start = (1-a0) y_prev + a0 v_start
        acc = np.cumsum(a * v[start:stop] / w)
        chunk = w * (acc + (1.0 - a[0]) * y_prev)
        y[start:stop] = chunk
        y_prev = float(chunk[-1])
        start = stop
    return y + u0


class _LagStream(TermStream):
    __slots__ = ("channel", "t_last", "tau_s", "y")

    def __init__(self, channel: str, tau_s: float) -> None:
        self.channel, self.tau_s = channel, tau_s
        self.t_last = math.nan
        self.y = math.nan

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        u = temps.get(self.channel)
        if u is None:
            return
        if math.isnan(self.y):
            self.y = u
        else:
            self.y += -math.expm1(-(t - self.t_last) / self.tau_s) * (u - self.y)
        self.t_last = t

    def value(self, t: float, x: float) -> float:
        return self.y


#: the lag time constants a model may name (s): a thermal path from a tenth of a second to about twelve
#: days. Beyond it the lagged channel is a constant over any calibration, collinear with the bias, and its
#: coefficient is meaningless (``lag(T1, 1e300 s)`` was fitted at 3.4e16)
LAG_TAU_RANGE_S = (0.1, 1.0e6)


class Lag(Term):
    """``lag(T4, 2100 s)``: a channel seen through a first-order lag of time constant τ.

    Physics: a part of the cell whose temperature follows the measured one with a delay (thermal
    mass behind a thermal resistance), so its expansion tracks the lagged signal, not the raw one.
    τ lies in :data:`LAG_TAU_RANGE_S`.
    """

    def __init__(self, channel: str, tau_s: float) -> None:
        tau_s = time_constant(tau_s, "lag time constant")
        low, high = LAG_TAU_RANGE_S
        if not low <= tau_s <= high:
            raise ValueError(f"lag time constant {tau_s:g} s is outside [{low:g}, {high:g}] s (a tenth of a second "
                             f"to {high / 86400:.1f} days): a longer lag is a constant over any calibration, the "
                             "bias' twin, and a shorter one the channel itself")
        self.channel, self.tau_s = channel, tau_s
        self.channels = (channel,)

    @property
    def name(self) -> str:
        return f"lag({self.channel}, {self.tau_s:g} s)"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        return lag_filter(t, channels[self.channel], self.tau_s)

    def stream(self) -> TermStream:
        return _LagStream(self.channel, self.tau_s)


class _DirectionStream(_Aimed, TermStream):
    __slots__ = ("axis", "deadband", "direction", "last_x", "positions")

    def __init__(self, deadband: float, axis: str) -> None:
        self.deadband, self.axis = deadband, axis
        self.direction = 1.0
        self.last_x = math.nan
        self.positions = {}

    def _after(self, x: float) -> float:
        if not math.isnan(self.last_x):
            step = x - self.last_x
            if step > self.deadband:
                return 1.0
            if step < -self.deadband:
                return -1.0
        return self.direction

    def value(self, t: float, x: float) -> float:
        return self._after(self.at(self.axis, x))

    def moved(self, t: float, x: float) -> None:
        x = self.at(self.axis, x)
        self.direction = self._after(x)
        self.last_x = x


class Direction(Term):
    """``dir``: +1 after a step up, -1 after a step down (steps within the deadband keep it); +1 at start.
    ``dir(y)``: the same for axis y of a cell of several axes.

    Physics: hysteresis of the piezo stack leaves an offset that depends on the direction of approach.
    """

    uses_x = True

    def __init__(self, deadband_um: float = 0.5, axis: str = "x") -> None:
        if not (math.isfinite(deadband_um) and deadband_um >= 0):
            raise ValueError(f"direction deadband must be a finite number >= 0 um, got {deadband_um}")
        self.deadband_um = float(deadband_um)
        self.axis = axis
        self.axes = _read_axes(axis)

    @property
    def name(self) -> str:
        inside = [*self.axes, *([] if self.deadband_um == 0.5 else [f"{self.deadband_um:g} um"])]
        return f"dir({', '.join(inside)})" if inside else "dir"

    def batch(self, t: np.ndarray, x: np.ndarray, channels: Channels) -> np.ndarray:
        x = axis_position(self.axis, x, channels)
        step = np.diff(x, prepend=x[:1])
        sign = np.where(step > self.deadband_um, 1.0, np.where(step < -self.deadband_um, -1.0, 0.0))
        sign[0] = 1.0 if sign[0] == 0 else sign[0]
        idx = np.where(sign != 0, np.arange(x.shape[0]), 0)
        np.maximum.accumulate(idx, out=idx)
        return sign[idx]

    def stream(self) -> TermStream:
        return _DirectionStream(self.deadband_um, self.axis)


# --- names <-> terms --------------------------------------------------------------------------


@dataclass(frozen=True)
class _TermKind:
    pattern: re.Pattern[str]
    factory: Callable[[re.Match[str]], Term]


_KINDS: list[_TermKind] = []
_CHANNEL = r"[A-Za-z_][A-Za-z0-9_.\-]*"
_NUMBER = r"[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?"


def register_term(pattern: str, factory: Callable[[re.Match[str]], Term]) -> None:
    """Teach :func:`parse_term` a new kind of term (checked before the built-in channel rule).

    ``pattern`` must match the whole name; ``{channel}`` and ``{number}`` expand to the usual regexes.
    """
    regex = re.compile("^" + pattern.format(channel=_CHANNEL, number=_NUMBER) + "$")
    _KINDS.insert(len(_KINDS) - 1 if _KINDS else 0, _TermKind(regex, factory))


#: makers of the terms only a multi-axis cell has, tried first when a name is parsed for such a cell
#: (``nanodrift.model.axis_terms`` registers them): one-axis names parse exactly as before
_AXIS_KINDS: list[Callable[[str, tuple[str, ...]], Term | None]] = []


def register_axis_term(factory: Callable[[str, tuple[str, ...]], Term | None]) -> None:
    """Teach :func:`parse_term` a multi-axis term: ``factory(name, axes)`` returns it or None."""
    _AXIS_KINDS.append(factory)


def parse_term(name: str, axes: tuple[str, ...] = ("x",)) -> Term:
    """The term a canonical name stands for; :class:`UnknownTermError` if none does.

    ``axes``: the cell's axes. With more than one, a name made of axis letters (``y``, ``y^2``, ``x*y``,
    ``y*T1``) is that axis' term, never a channel named ``y``.
    """
    text = name.strip()
    if len(axes) > 1:
        for factory in _AXIS_KINDS:
            made = factory(text, axes)
            if made is not None:
                return made
    for kind in _KINDS:
        if match := kind.pattern.match(text):
            return kind.factory(match)
    raise UnknownTermError(f"unknown term {name!r}")


# order matters: the catch-all channel rule stays last (register_term inserts before it)
_KINDS.append(_TermKind(re.compile(r"^1$"), lambda m: Bias()))
_KINDS.append(_TermKind(re.compile(r"^x(?:\^(?P<k>[1-9]\d*))?$"), lambda m: Power(int(m.group("k") or 1))))
_KINDS.append(_TermKind(re.compile(rf"^dir(?:\((?P<db>{_NUMBER}) um\))?$"),
                        lambda m: Direction(float(m.group("db"))) if m.group("db") else Direction()))
_KINDS.append(
    _TermKind(
        re.compile(rf"^lag\(\s*(?P<ch>{_CHANNEL})\s*,\s*(?P<tau>{_NUMBER})\s*s\s*\)$"),
        lambda m: Lag(m.group("ch"), float(m.group("tau"))),
    )
)
_KINDS.append(
    _TermKind(
        re.compile(rf"^\(\s*(?P<ch>{_CHANNEL}) (?P<sign>[-+]) (?P<c>{_NUMBER})\s*\)\^2$"),
        lambda m: ChannelSquare(m.group("ch"), float(m.group("c")) * (1.0 if m.group("sign") == "-" else -1.0)),
    )
)
_KINDS.append(_TermKind(re.compile(rf"^(?P<ch>{_CHANNEL})$"), lambda m: Channel(m.group("ch"))))
