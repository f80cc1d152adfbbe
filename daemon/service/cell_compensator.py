"""A multi-axis target -> :class:`CellCommand`, or a :class:`Refusal`: one temperature snapshot, every axis.

The multi-axis twin of :mod:`nanodrift.service.compensator` (which serves a one-axis cell, unchanged). The
rule it adds: **a target is served whole or refused whole.** Every axis' workspace, the model, the
freshness of every channel, and every axis' voltage against its own ``[v_min, v_max]`` are checked
before anything moves (the evaluator's ``moved`` is the last step); a refusal names the axis, and
since nothing is handed to the actuation unless a command is returned, nothing is written to any axis.

Also here: :func:`load_served_model`, which refuses a model whose axes are not the cell's (a one-axis
model for an XY cell, an XY model for a one-axis or an XZ cell) with a message saying both.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any

from nanodrift.bus.protocol import CellCommand, CellTarget, Refusal
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import State
from nanodrift.model.cell_model import CellEvaluator, CellModel, load_any_model
from nanodrift.model.model import Model, ModelFileError, load_model
from nanodrift.motion import VoltageLimitError, checked_voltage
from nanodrift.service.compensator import temperature_snapshot
from nanodrift.service.table import SensorTable


def _axes_text(axes: Sequence[str]) -> str:
    return ", ".join(axes) + (" (one axis)" if len(axes) == 1 else "")


def load_served_model(path: Path, axes: Sequence[str]) -> Model | CellModel:
    """The model in ``path`` if it serves exactly the cell's ``axes`` (a one-axis cell: ``("x",)``, a
    :class:`Model` read by :func:`load_model` as always); :class:`ModelFileError` otherwise."""
    if tuple(axes) == ("x",):
        try:
            return load_model(path)
        except ModelFileError as error:
            try:
                other = load_any_model(path)
            except ModelFileError:
                raise error from None
            if isinstance(other, CellModel):
                raise ModelFileError(f"{path}: a multi-axis model (axes {_axes_text(other.axes)}), but this cell has "
                                     "one axis (x): describe its axes with [[axes]] in the config, or serve a "
                                     "one-axis model") from None
            raise
    model = load_any_model(path)
    model_axes = model.axes if isinstance(model, CellModel) else ("x",)
    if sorted(model_axes) != sorted(axes):
        raise ModelFileError(f"{path}: the model serves axes {_axes_text(model_axes)}, the cell has axes "
                             f"{_axes_text(axes)} ([[axes]] in the config): calibrate this cell's axes, or serve "
                             "its own model")
    return model


def load_cell_model_or_problem(path: Path, axes: Sequence[str]) -> tuple[CellModel | None, str]:
    """:func:`load_served_model` for a multi-axis cell, or None and why not (the daemon serves refusals)."""
    try:
        model = load_served_model(path, axes)
    except ModelFileError as error:
        return None, str(error)
    assert isinstance(model, CellModel)
    return model, ""


class CellCompensator:
    """Turns a multi-axis target into one command for every axis (the :class:`Compensator` of an XY/XYZ cell)."""

    def __init__(self, model: CellModel | None, actuators: Mapping[str, ActuatorConfig], table: SensorTable,
                 model_problem: str = "") -> None:
        self.model = model
        self.actuators = dict(actuators)
        self.axes = tuple(actuators)
        self.table = table
        self.model_problem = model_problem
        self.evaluator: CellEvaluator | None = model.evaluator() if model is not None else None
        self.channels: tuple[str, ...] = model.channels if model is not None else ()
        self.missing = tuple(c for c in self.channels if c not in table.entries)
        self.last_extrapolating: list[str] = []
        #: the bias correction per axis (None: adaptation off); set by the axes' health units
        self.correction_um: dict[str, float] | None = None
        #: the trackers behind those corrections, per axis (set by the health units): a corrected axis'
        #: command carries the σ its tracker leaves (``q_sigma_adapted_um``, :meth:`BiasTracker.sigma_um`)
        self.trackers: dict[str, BiasTracker] = {}
        self._wander_um = {a: m.wander_um for a, m in (model.models.items() if model is not None else ())}
        #: (cell time, command) of every command served, for a health unit (None: none listens)
        self.served: deque[tuple[float, Any]] | None = None
        self._model_id = model.id if model is not None else None
        self._entries = tuple((c, table.entries[c]) for c in self.channels if c in table.entries)
        ranges = model.channel_ranges if model is not None else {}
        self._ranges = tuple((c, *ranges[c]) for c in self.channels if c in ranges)
        self._position_ranges = model.position_ranges if model is not None else {}
        self._version = -1
        self._fresh_until = -math.inf
        self._temps: Mapping[str, float] = MappingProxyType({})
        self._temps_outside: list[str] = []

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        if self.evaluator is not None and temps:
            self.evaluator.observe(t, temps)

    def warm(self) -> None:
        latest = self.table.latest_temperatures()
        if latest is not None:
            self.observe(*latest)

    def _refuse_outside_workspace(self, target: CellTarget) -> None:
        outside = []
        for axis, actuator in self.actuators.items():
            value = target.positions_um[axis]
            if not actuator.x_min_um <= value <= actuator.x_max_um:
                outside.append(f"{axis}_um {value:g} outside axis {axis}'s workspace [{actuator.x_min_um:g}, "
                               f"{actuator.x_max_um:g}] µm")
        if outside:
            raise Refusal("out_of_workspace", "; ".join(outside) + ": no axis moves", target.id)

    def compensate(self, target: CellTarget, now: float, unix_now: float) -> CellCommand:
        """The command of every axis for ``target`` at ``now`` (the cell clock); raises :class:`Refusal`
        (then nothing has changed: no evaluator state, nothing to write)."""
        self._refuse_outside_workspace(target)
        if self.evaluator is None or self.model is None:
            raise Refusal("no_model", f"no model loaded ({self.model_problem or 'none configured'})", target.id)
        if self.missing:
            raise Refusal("missing_channel", f"channel {', '.join(self.missing)} needed by model {self.model.id} "
                          "has no configured sensor", target.id)
        if self._version != self.table.version:
            self._version = self.table.version
            self._fresh_until, self._temps, self._temps_outside = temperature_snapshot(
                self._entries, self.missing, self._ranges)
        if not now <= self._fresh_until:
            for name, _ in self._entries:
                state, reason = self.table.state(name, now)
                if state is not State.OK:
                    raise Refusal(state.value, f"channel {name} is {state.value}: {reason}", target.id)
            raise Refusal("stale", "temperatures not ready", target.id)
        positions = target.positions_um
        evaluator = self.evaluator
        q_by_axis = evaluator.value(positions, now)  # one snapshot of the filters for every axis
        correction = self.correction_um
        q_um: dict[str, float] = {}
        voltage_v: dict[str, float] = {}
        for axis, actuator in self.actuators.items():
            q = q_by_axis[axis] + (correction.get(axis, 0.0) if correction is not None else 0.0)
            try:
                voltage_v[axis] = checked_voltage(actuator, q)
            except VoltageLimitError as error:
                raise Refusal("voltage_limit", f"axis {axis}: {error}: no axis moves", target.id) from None
            q_um[axis] = q
        sigma = evaluator.sigma(positions, now)
        adapted = {axis: tracker.sigma_um(sigma[axis], self._wander_um.get(axis, 0.0))
                   for axis, tracker in self.trackers.items()} or None
        evaluator.moved(positions, now)  # only a command that goes out moves the stage
        outside_axes = [a for a in self.axes if a in self._position_ranges
                        and not self._position_ranges[a][0] <= positions[a] <= self._position_ranges[a][1]]
        extrapolating = [*outside_axes, *self._temps_outside]
        self.last_extrapolating = extrapolating
        command = CellCommand(id=target.id, positions_um=positions, q_um=q_um, voltage_v=voltage_v,
                              q_sigma_um={a: sigma[a] for a in self.axes}, temperatures_c=self._temps,
                              model=self._model_id, t=unix_now, extrapolating=extrapolating,
                              correction_um=dict(correction) if correction is not None else None,
                              q_sigma_adapted_um=adapted)
        if self.served is not None:
            self.served.append((now, command))
        return command

    def model_info(self) -> dict[str, Any] | None:
        if self.model is None:
            return None
        model = self.model
        first = model.models[model.axes[0]].training
        return {
            "id": model.id,
            "axes": list(model.axes),
            "terms": {a: model.models[a].term_names() for a in model.axes},
            "channels": list(self.channels),
            "missing_channels": list(self.missing),
            "training": {
                "positions_um": {a: list(r) for a, r in model.position_ranges.items()},
                "channels": {c: list(r) for c, r in model.channel_ranges.items()},
                "rows": first.rows,
                "t_span_s": first.t_span_s,
            },
            "ready": self.evaluator.ready if self.evaluator is not None else False,
            "created": model.provenance.get("created"),
        }

    def extrapolating_now(self, now: float) -> list[str]:
        """Channels whose current reading lies outside the training range."""
        if self.model is None:
            return []
        temps = {name: entry.value for name in self.channels
                 if (entry := self.table.entries.get(name)) is not None and entry.value is not None}
        return self.model.out_of_range(None, temps)
