"""The compensation of one target, pure: a :class:`Target` in, a :class:`Command` for every axis or a :class:`Refusal`.

A one-axis cell is a cell of one axis, ``x``: the same code path serves one axis or several. No zenoh, no
asyncio, no service: the bus parses payloads into a :class:`Target` and encodes a :class:`Command` (the
one-axis wire shapes, scalar ``q_um`` and so on, live there); the service holds the sensor readings (its
``SensorTable`` is a :class:`Readings`) and calls :meth:`Compensator.compensate` under its lock.

**A target is served whole or refused whole.** Every axis' workspace, the model, the freshness of every
channel the model uses and every axis' voltage against its own ``[v_min, v_max]`` are checked before
anything moves (the evaluators' ``moved`` is the last step); a refusal names the axis, and since nothing
is handed to the actuation unless a command is returned, nothing is written to any output.

Each command carries ``q_sigma_um`` per axis (the model's standard uncertainty, taken before the move)
and, with adaptation on, ``correction_um`` (already inside ``q_um`` before the voltage is computed and
checked) and ``q_sigma_adapted_um``: what the :class:`Monitor` (the daemon's health unit) says, through
the explicit hook the compensator is built with.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Protocol

# the axis of a cell without [[axes]] and the test for its shapes, as the bus and the service know them
from nanodrift.model.cell_model import ONE_AXIS as ONE_AXIS
from nanodrift.model.cell_model import CellModel, load_any_model
from nanodrift.model.cell_model import one_axis as one_axis
from nanodrift.model.model import Evaluator, Model, ModelFileError, aim
from nanodrift.motion import MotionLimits, VoltageLimitError, checked_voltage

_NO_TEMPERATURES: Mapping[str, float] = MappingProxyType({})


class Refusal(Exception):
    """A target that gets an ``error`` instead of a ``command``; ``kind`` feeds the counters."""

    __slots__ = ("id", "kind", "message")

    def __init__(self, kind: str, message: str, target_id: Any = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.id = target_id


@dataclass(slots=True)
class Target:
    """Where every axis of the cell should go (µm), in the cell's axis order."""

    id: str | int | None
    positions_um: dict[str, float]


@dataclass(slots=True, kw_only=True)
class Command:
    """One answer: every axis from one temperature snapshot (per-axis values keyed by axis). The optional
    fields are left out of the payload when None (a procedure step has a ``procedure`` and no
    ``extrapolating``). Treat it as immutable once encoded."""

    id: str | int | None
    positions_um: Mapping[str, float]
    q_um: Mapping[str, float]
    voltage_v: Mapping[str, float]
    temperatures_c: Mapping[str, float]
    model: str | None
    t: float  # unix seconds
    extrapolating: Sequence[str] | None = None  # axis names and channels outside the model's training range
    procedure: str | None = None  # the calibration or validation that sent this step
    q_sigma_um: Mapping[str, float] | None = None  # the model's standard uncertainty of q per axis
    correction_um: Mapping[str, float] | None = None  # the bias correction per axis, inside q_um (adaptation on)
    #: per corrected axis, the standard uncertainty of its corrected command (adaptation on)
    q_sigma_adapted_um: Mapping[str, float] | None = None


class AxisLimits(MotionLimits, Protocol):
    """An axis' workspace and output limits (``nanodrift.config.ActuatorConfig`` has them)."""

    x_min_um: float
    x_max_um: float


class Readings(Protocol):
    """What the compensator reads of the sensors (``nanodrift.service.table.SensorTable`` is one)."""

    version: int  # bumped by every change: what is derived from the readings is kept until it moves

    def has(self, name: str) -> bool: ...

    def fresh_temperatures(self, channels: Sequence[str]) -> tuple[float, dict[str, float]]: ...

    def problem(self, name: str, now: float) -> tuple[str, str] | None: ...

    def latest_temperatures(self) -> tuple[float, dict[str, float]] | None: ...

    def values(self, channels: Sequence[str]) -> dict[str, float]: ...


class Monitor(Protocol):
    """The hook a compensator serves through (the daemon's health unit): told every command that goes
    out, asked the bias correction per axis and the σ a corrected command keeps."""

    def correction_um(self) -> Mapping[str, float] | None: ...

    def sigma_adapted_um(self, sigma_um: Mapping[str, float],
                         wander_um: Mapping[str, float]) -> Mapping[str, float] | None: ...

    def served(self, now: float, command: Command) -> None: ...


def axis_models(model: Model | CellModel | None) -> dict[str, Model]:
    """Every axis' model (a one-axis model is axis ``x``'s)."""
    return {} if model is None else dict(CellModel.of(model).models)


def _axes_text(axes: Sequence[str]) -> str:
    return ", ".join(axes) + (" (one axis)" if len(axes) == 1 else "")


def load_served_model(path: Path, axes: Sequence[str]) -> Model | CellModel:
    """The model in ``path`` if it serves exactly the cell's ``axes`` (a one-axis cell: ``("x",)``, a
    :class:`Model` as always); :class:`ModelFileError` otherwise, saying both."""
    model = load_any_model(path)
    model_axes = CellModel.of(model).axes
    if one_axis(axes) and not one_axis(model_axes):
        raise ModelFileError(f"{path}: a multi-axis model (axes {_axes_text(model_axes)}), but this cell has one "
                             "axis (x): describe its axes with [[axes]] in the config, or serve a one-axis model")
    if sorted(model_axes) != sorted(axes):
        raise ModelFileError(f"{path}: the model serves axes {_axes_text(model_axes)}, the cell has axes "
                             f"{_axes_text(axes)} ([[axes]] in the config): calibrate this cell's axes, or serve "
                             "its own model")
    return model


class Compensator:
    """Turns a target into one command for every axis with the model, the readings and each axis' limits."""

    def __init__(self, model: Model | CellModel | None, limits: Mapping[str, AxisLimits], readings: Readings,
                 model_problem: str = "", *, monitor: Monitor | None = None) -> None:
        self.model = model
        self.limits = dict(limits)
        self.axes = tuple(limits)
        self.readings = readings
        self.model_problem = model_problem
        self.monitor = monitor
        models = axis_models(model)
        #: every axis' evaluator (lag filters, direction): a reload of the same model keeps them
        self.evaluators: dict[str, Evaluator] | None = {a: m.evaluator() for a, m in models.items()} or None
        self.channels: tuple[str, ...] = model.channels if model is not None else ()
        self.missing = tuple(c for c in self.channels if not readings.has(c))
        self.last_extrapolating: list[str] = []
        self._wander_um = {a: m.wander_um for a, m in models.items()}
        self._model_id = model.id if model is not None else None
        # the training ranges: every channel the model reads, every axis' position
        channel_ranges: Mapping[str, tuple[float, float]] = {}
        self._position_ranges: Mapping[str, tuple[float, float]] = {}
        if model is not None:
            cell = CellModel.of(model)
            channel_ranges, self._position_ranges = cell.channel_ranges, cell.position_ranges
        self._ranges = tuple((c, *channel_ranges[c]) for c in self.channels if c in channel_ranges)
        # what the model's channels say, derived once per change of the readings instead of once per target
        self._version = -1
        self._fresh_until = -math.inf  # cell-clock time until which every model channel is ok
        self._temps = _NO_TEMPERATURES  # read-only: commands share it (and its encoding is kept)
        self._temps_outside: list[str] = []  # channels outside their training range

    @property
    def ready(self) -> bool:
        """Every channel the model needs has been observed at least once."""
        return self.evaluators is not None and all(ev.ready for ev in self.evaluators.values())

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        if self.evaluators is not None and temps:
            for evaluator in self.evaluators.values():
                evaluator.observe(t, temps)

    def warm(self) -> None:
        """Feed new evaluators the latest good readings so they can serve at once."""
        latest = self.readings.latest_temperatures()
        if latest is not None:
            self.observe(*latest)

    def _snapshot(self) -> None:
        self._version = self.readings.version
        if self.missing:
            self._fresh_until, self._temps, self._temps_outside = -math.inf, _NO_TEMPERATURES, []
            return
        self._fresh_until, temps = self.readings.fresh_temperatures(self.channels)
        self._temps = MappingProxyType(temps) if temps else _NO_TEMPERATURES
        self._temps_outside = [name for name, lo, hi in self._ranges if not lo <= temps.get(name, lo) <= hi]

    def _refuse_outside_workspace(self, target: Target) -> None:
        outside = []
        for axis, limits in self.limits.items():
            value = target.positions_um[axis]
            if not limits.x_min_um <= value <= limits.x_max_um:
                outside.append(f"{axis}_um {value:g} outside " + ("the workspace" if len(self.axes) == 1 else
                               f"axis {axis}'s workspace") + f" [{limits.x_min_um:g}, {limits.x_max_um:g}] µm")
        if outside:
            raise Refusal("out_of_workspace", "; ".join(outside) + ("" if len(self.axes) == 1 else ": no axis moves"),
                          target.id)

    def compensate(self, target: Target, now: float, unix_now: float) -> Command:
        """The command of every axis for ``target`` at ``now`` (the cell clock); raises :class:`Refusal`
        (then nothing has changed: no evaluator state, nothing to write)."""
        self._refuse_outside_workspace(target)
        evaluators = self.evaluators
        if evaluators is None or self.model is None:
            raise Refusal("no_model", f"no model loaded ({self.model_problem or 'none configured'})", target.id)
        if self.missing:
            raise Refusal("missing_channel", f"channel {', '.join(self.missing)} needed by model {self.model.id} "
                          "has no configured sensor", target.id)
        if self._version != self.readings.version:
            self._snapshot()
        if not now <= self._fresh_until:
            for name in self.channels:  # say which channel and why
                problem = self.readings.problem(name, now)
                if problem is not None:
                    raise Refusal(problem[0], f"channel {name} is {problem[0]}: {problem[1]}", target.id)
            raise Refusal("stale", "temperatures not ready", target.id)
        positions = target.positions_um
        x = aim(evaluators.values(), positions)
        correction = self.monitor.correction_um() if self.monitor is not None else None
        q_um: dict[str, float] = {}
        voltage_v: dict[str, float] = {}
        sigma: dict[str, float] = {}
        for axis, limits in self.limits.items():  # one pass over the axes: the hot path of every target
            evaluator = evaluators[axis]
            q = evaluator.value(x, now) + (correction.get(axis, 0.0) if correction is not None else 0.0)
            try:  # q = model + correction: the voltage and its limits are the corrected command's
                voltage_v[axis] = checked_voltage(limits, q)
            except VoltageLimitError as error:
                raise Refusal("voltage_limit", str(error) if len(self.axes) == 1 else
                              f"axis {axis}: {error}: no axis moves", target.id) from None
            q_um[axis] = q
            sigma[axis] = evaluator.sigma(x, now)  # before the move: as value() saw (sigma changes nothing)
        adapted = self.monitor.sigma_adapted_um(sigma, self._wander_um) if self.monitor is not None else None
        for evaluator in evaluators.values():
            evaluator.moved(x, now)  # only a command that goes out moves the stage
        ranges = self._position_ranges
        extrapolating = [a for a in self.axes if a in ranges and not ranges[a][0] <= positions[a] <= ranges[a][1]]
        extrapolating += self._temps_outside
        self.last_extrapolating = extrapolating
        command = Command(id=target.id, positions_um=positions, q_um=q_um, voltage_v=voltage_v,
                          temperatures_c=self._temps, model=self._model_id, t=unix_now, extrapolating=extrapolating,
                          q_sigma_um=sigma, correction_um=dict(correction) if correction is not None else None,
                          q_sigma_adapted_um=adapted)
        if self.monitor is not None:
            self.monitor.served(now, command)
        return command

    def extrapolating_now(self) -> list[str]:
        """Channels whose current reading lies outside the training range."""
        temps = self.readings.values(self.channels)
        return [name for name, lo, hi in self._ranges if name in temps and not lo <= temps[name] <= hi]
