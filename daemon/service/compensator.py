"""Target -> :class:`Command`, or a :class:`Refusal`: the loaded model, the sensor table, the actuator limits.

Each command carries ``q_sigma_um`` (:meth:`Evaluator.sigma`, taken before the move) and, with
``[adapt] mode = "bias"``, ``correction_um``: the health unit's correction (``nanodrift.service.health_unit``
sets :attr:`Compensator.correction_um` under the state lock), already added to ``q_um`` before the
voltage is computed and checked. With a position sensor every command that goes out is appended, with
its cell-clock time, to :attr:`Compensator.served` for the health unit (one append: the answer never
waits for the monitor).

Refused: a stale or faulted channel (named, with its reason), a target outside the workspace, a
voltage outside the actuator's limits, no model. (An output device in fault is refused before this,
by ``nanodrift.service.targets``: it is the actuation's state, not the model's.) What the command looks like on the
wire is
``nanodrift.bus.protocol``'s business, not this module's.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from pathlib import Path
from types import MappingProxyType
from typing import Any

from nanodrift.bus.protocol import Command, Refusal, Target
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import State
from nanodrift.model.model import Evaluator, Model, ModelFileError, load_model
from nanodrift.motion import VoltageLimitError, checked_voltage
from nanodrift.service.table import ChannelEntry, SensorTable

_NO_TEMPERATURES: Mapping[str, float] = MappingProxyType({})


def load_model_or_problem(path: Path) -> tuple[Model | None, str]:
    """The model in ``path``, or None and why not (the daemon serves refusals until there is one)."""
    try:
        return load_model(path), ""
    except ModelFileError as error:
        return None, str(error)


def temperature_snapshot(entries: Sequence[tuple[str, ChannelEntry]], missing: Sequence[str],
                         ranges: Sequence[tuple[str, float, float]]) -> tuple[float, Mapping[str, float], list[str]]:
    """What the model's channels say now: the cell-clock time until which every one is fresh (-inf: one
    is not ok, or missing), their values (read-only: commands share it) and those outside their
    training range. Derived once per table change, never per target; one snapshot serves every axis."""
    fresh_until = math.inf
    temps: dict[str, float] = {}
    for _, entry in entries:
        if entry.device_state is not State.OK or entry.t is None or entry.value is None:
            return -math.inf, _NO_TEMPERATURES, []
        fresh_until = min(fresh_until, entry.t + entry.max_age_s)
        temps[entry.name] = entry.value
    if missing:
        return -math.inf, _NO_TEMPERATURES, []
    return fresh_until, MappingProxyType(temps), [name for name, lo, hi in ranges if not lo <= temps[name] <= hi]


class Compensator:
    """Turns a target into a command with the loaded model, the sensor table and actuator limits."""

    def __init__(
        self, model: Model | None, actuator: ActuatorConfig, table: SensorTable, model_problem: str = ""
    ) -> None:
        self.model = model
        self.actuator = actuator
        self.table = table
        self.model_problem = model_problem
        self.evaluator: Evaluator | None = model.evaluator() if model is not None else None
        self.channels: tuple[str, ...] = model.channels if model is not None else ()
        self.missing = tuple(c for c in self.channels if c not in table.entries)
        self.last_extrapolating: list[str] = []
        #: the bias correction added to every command (None: adaptation off); set by the health unit
        self.correction_um: float | None = None
        #: the tracker behind that correction (set by the health unit): a corrected command carries, beside
        #: the model's q_sigma, the σ the tracker leaves (``q_sigma_adapted_um``, :meth:`BiasTracker.sigma_um`)
        self.tracker: BiasTracker | None = None
        self._wander_um = model.wander_um if model is not None else 0.0
        #: (cell time, command) of every command served, for the health unit (None: no position sensor)
        self.served: deque[tuple[float, Command]] | None = None
        # the hot path: channel entries and training ranges, prepared once
        self._model_id = model.id if model is not None else None
        self._entries = tuple((c, table.entries[c]) for c in self.channels if c in table.entries)
        training = model.training if model is not None else None
        self._x_range = training.x_range if training is not None else (-math.inf, math.inf)
        self._ranges = tuple(
            (c, *training.channel_ranges[c]) for c in self.channels if training and c in training.channel_ranges
        )
        # what the model's channels say, derived once per table change instead of once per target
        self._version = -1
        self._fresh_until = -math.inf  # cell-clock time until which every model channel is ok
        self._temps = _NO_TEMPERATURES  # read-only: commands share it (and its encoding is kept)
        self._temps_outside: list[str] = []  # channels outside their training range

    def _snapshot(self) -> None:
        self._version = self.table.version
        self._fresh_until, self._temps, self._temps_outside = temperature_snapshot(
            self._entries, self.missing, self._ranges)

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        if self.evaluator is not None and temps:
            self.evaluator.observe(t, temps)

    def warm(self) -> None:
        """Feed a new evaluator the table's latest good readings so it can serve at once."""
        latest = self.table.latest_temperatures()
        if latest is not None:
            self.observe(*latest)

    def compensate(self, target: Target, now: float, unix_now: float) -> Command:
        """The command for ``target`` at ``now`` (the cell clock); raises :class:`Refusal`."""
        actuator = self.actuator
        x = target.x_um
        if not actuator.x_min_um <= x <= actuator.x_max_um:
            raise Refusal(
                "out_of_workspace",
                f"x_um {x:g} outside the workspace [{actuator.x_min_um:g}, {actuator.x_max_um:g}] µm",
                target.id,
            )
        if self.evaluator is None or self.model is None:
            raise Refusal("no_model", f"no model loaded ({self.model_problem or 'none configured'})", target.id)
        if self.missing:
            raise Refusal(
                "missing_channel",
                f"channel {', '.join(self.missing)} needed by model {self.model.id} has no configured sensor",
                target.id,
            )
        if self._version != self.table.version:
            self._snapshot()
        if not now <= self._fresh_until:
            for name, _ in self._entries:  # say which channel and why
                state, reason = self.table.state(name, now)
                if state is not State.OK:
                    raise Refusal(state.value, f"channel {name} is {state.value}: {reason}", target.id)
            raise Refusal("stale", "temperatures not ready", target.id)
        evaluator = self.evaluator
        correction = self.correction_um
        q = evaluator.value(x, now)
        if correction is not None:
            q += correction  # q = model + correction: the voltage and its limits are the corrected command's
        try:
            voltage = checked_voltage(actuator, q)
        except VoltageLimitError as error:
            raise Refusal("voltage_limit", str(error), target.id) from None
        sigma = evaluator.sigma(x, now)  # before the move: motion terms see what value() saw
        tracker = self.tracker
        adapted = tracker.sigma_um(sigma, self._wander_um) if tracker is not None else None
        evaluator.moved(x, now)  # only a command that goes out moves the stage
        lo, hi = self._x_range
        extrapolating = [*self._temps_outside] if lo <= x <= hi else ["x", *self._temps_outside]
        self.last_extrapolating = extrapolating
        command = Command(id=target.id, x_um=x, q_um=q, voltage_v=voltage, temperatures_c=self._temps,
                          model=self._model_id, t=unix_now, extrapolating=extrapolating, q_sigma_um=sigma,
                          correction_um=correction, q_sigma_adapted_um=adapted)
        if self.served is not None:
            self.served.append((now, command))
        return command

    def model_info(self) -> dict[str, Any] | None:
        if self.model is None:
            return None
        training = self.model.training
        return {
            "id": self.model.id,
            "terms": self.model.term_names(),
            "channels": list(self.channels),
            "missing_channels": list(self.missing),
            "training": {
                "x_um": list(training.x_range),
                "channels": {c: list(r) for c, r in training.channel_ranges.items()},
                "rows": training.rows,
                "t_span_s": training.t_span_s,
            },
            "ready": self.evaluator.ready if self.evaluator is not None else False,
            "created": self.model.provenance.get("created"),  # the model's age in ``nanodrift status``
        }

    def extrapolating_now(self, now: float) -> list[str]:
        """Channels whose current reading lies outside the training range."""
        if self.model is None:
            return []
        temps = {
            name: entry.value
            for name in self.channels
            if (entry := self.table.entries.get(name)) is not None and entry.value is not None
        }
        return self.model.out_of_range(None, temps)
