"""A multi-axis cell's health and adaptation: one :class:`HealthUnit` per axis that has a position sensor.

Each axis is watched exactly as a one-axis cell is (``nanodrift.service.health_unit``): its commands (the
axis' position as the target, its ``q``), its position sensor's readings, the settle windows, the rolling
statistics and, with ``[adapt] mode = "bias"``, its own bias tracker, whose correction the
:class:`CellCompensator` adds to that axis' command. Each unit sees a one-axis view of the config (its
axis' actuator and position sensor, every temperature sensor) and of the model (its axis' model).

The ``health`` document is the worst state of the axes (degraded, then ok, then unknown) with every
axis' own document under ``"axes"``. A target held on every watched axis is one recorded row
(:class:`nanodrift.service.recorder.CellSettled`: ``x_um, y_um, q_x_um, q_y_um, target_x_um, ...``).
"""

from __future__ import annotations

import asyncio
import functools
import time
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from nanodrift.bus.protocol import CellCommand, Command, dumps
from nanodrift.bus.session import Bus
from nanodrift.calibration.residuals import BiasTracker, Settled
from nanodrift.config import Config
from nanodrift.model.cell_model import CellModel
from nanodrift.service.cell_compensator import CellCompensator
from nanodrift.service.health_unit import PUBLISH_INTERVAL_S, HealthUnit
from nanodrift.service.recorder import CellSettled, Polled

#: a cell's state is its worst axis'
#: targets held on some axes, waiting for the others (oldest dropped beyond this)
MAX_PENDING_TARGETS = 64
_RANK = {"degraded": 2, "ok": 1, "unknown": 0}


def axis_view(config: Config, axis: str) -> Config:
    """``config`` as a one-axis cell's: the axis' actuator, its position sensor and every other sensor."""
    actuator = config.axis_actuators()[axis]
    sensors = [s for s in config.sensors if s.role != "position" or config.sensor_axis(s.name) == axis]
    return config.model_copy(update={"axes": [], "actuator": actuator, "sensors": sensors})


class _AxisCompensator:
    """What one axis' health unit attaches to: it routes that axis' correction into the cell's compensator."""

    def __init__(self, axis: str, cell: CellCompensator | None, model: CellModel | None) -> None:
        self.axis = axis
        self.cell = cell
        self.model = model.models[axis] if model is not None else None
        self.served: Any = None  # set by the unit; the cell's commands reach it through :class:`CellHealth`

    @property
    def correction_um(self) -> float | None:
        corrections = self.cell.correction_um if self.cell is not None else None
        return corrections.get(self.axis) if corrections is not None else None

    @correction_um.setter
    def correction_um(self, value: float | None) -> None:
        if self.cell is None:
            return
        if value is None:
            if self.cell.correction_um is not None:
                self.cell.correction_um.pop(self.axis, None)
                if not self.cell.correction_um:
                    self.cell.correction_um = None
            return
        if self.cell.correction_um is None:
            self.cell.correction_um = {}
        self.cell.correction_um[self.axis] = value

    @property
    def tracker(self) -> BiasTracker | None:
        return self.cell.trackers.get(self.axis) if self.cell is not None else None

    @tracker.setter
    def tracker(self, value: BiasTracker | None) -> None:
        if self.cell is None:
            return
        if value is None:
            self.cell.trackers.pop(self.axis, None)
        else:
            self.cell.trackers[self.axis] = value


class _Served:
    """The cell compensator's ``served`` queue: each command split into one per watched axis."""

    def __init__(self, units: Mapping[str, HealthUnit]) -> None:
        self.units = units

    def append(self, item: tuple[float, CellCommand]) -> None:
        t, command = item
        for axis, unit in self.units.items():
            if unit.position_channel is None:
                continue
            correction = command.correction_um.get(axis) if command.correction_um is not None else None
            adapted = command.q_sigma_adapted_um.get(axis) if command.q_sigma_adapted_um is not None else None
            unit.served.append((t, Command(
                id=command.id, x_um=command.positions_um[axis], q_um=command.q_um[axis],
                voltage_v=command.voltage_v[axis], temperatures_c=command.temperatures_c, model=command.model,
                t=command.t, extrapolating=command.extrapolating, q_sigma_um=command.q_sigma_um[axis],
                correction_um=correction, q_sigma_adapted_um=adapted)))


class CellHealth:
    """The health unit of a multi-axis cell: the :class:`HealthUnit` interface the service uses, per axis."""

    def __init__(self, config: Config, model: CellModel | None, log: Any) -> None:
        self.log = log
        self.axes = config.axis_names
        self.units = {axis: HealthUnit(axis_view(config, axis), model.models[axis] if model is not None else None,
                                       log.bind(axis=axis) if hasattr(log, "bind") else log, axis=axis)
                      for axis in self.axes}
        #: told (on the loop) of every target settled on every watched axis: one row of the cell (the recorder)
        self.settled_listeners: list[Callable[[CellSettled, float, Polled], None]] = []
        self._pending: dict[Any, dict[str, tuple[Settled, float, Polled]]] = {}  # target id -> axes settled
        for axis, unit in self.units.items():
            unit.settled_listeners.append(functools.partial(self._axis_settled, axis))
        self._served = _Served(self.units)
        self._publisher: Any = None
        self._announced = self.state
        self._model = model

    # --- the service's interface ---------------------------------------------------------------

    @property
    def awaits_reach(self) -> bool:
        return any(u.awaits_reach for u in self.units.values())

    @awaits_reach.setter
    def awaits_reach(self, value: bool) -> None:
        for unit in self.units.values():
            unit.awaits_reach = value

    @property
    def label_clock(self) -> Callable[[], float]:
        """What labels the recorded rows (the drivers' ``DriverContext.label_clock``), one for every axis."""
        return next((u.label_clock for u in self.units.values()), time.time)

    @label_clock.setter
    def label_clock(self, clock: Callable[[], float]) -> None:
        for unit in self.units.values():
            unit.label_clock = clock

    def attach(self, compensator: Any) -> None:
        """Serve through ``compensator`` (a :class:`CellCompensator`): each axis' correction goes into it,
        its commands come to the axes with a position sensor."""
        cell = compensator if isinstance(compensator, CellCompensator) else None
        model = cell.model if cell is not None else None
        for axis, unit in self.units.items():
            unit.attach(_AxisCompensator(axis, cell, model))  # type: ignore[arg-type]
        if cell is not None:
            watched = any(u.position_channel is not None for u in self.units.values())
            cell.served = self._served if watched else None  # type: ignore[assignment]

    def reconfigure(self, config: Config, compensator: Any) -> None:
        cell = compensator if isinstance(compensator, CellCompensator) else None
        model = cell.model if cell is not None else None
        for axis, unit in self.units.items():
            unit.reconfigure(axis_view(config, axis), _AxisCompensator(axis, cell, model))  # type: ignore[arg-type]
        if cell is not None:
            watched = any(u.position_channel is not None for u in self.units.values())
            cell.served = self._served if watched else None  # type: ignore[assignment]

    def _axis_settled(self, axis: str, settled: Settled, unix_s: float, polled: Polled) -> None:
        """One axis held a target: once every watched axis held it, the cell's row goes to the listeners."""
        watched = [a for a, u in self.units.items() if u.position_channel is not None]
        key = repr(settled.target_id)
        axes = self._pending.setdefault(key, {})
        axes[axis] = (settled, unix_s, polled)
        if len(self._pending) > MAX_PENDING_TARGETS:  # an axis that never settles must not grow this
            self._pending.pop(next(iter(self._pending)))
        if not all(a in axes for a in watched):
            return
        del self._pending[key]
        cell = CellSettled({a: axes[a][0] for a in watched})
        last = max(watched, key=lambda a: axes[a][1])
        valid = all(axes[a][2].valid for a in watched)
        polled_cell = Polled(axes[last][2].values_c, valid)
        for listener in self.settled_listeners:
            listener(cell, axes[last][1], polled_cell)

    def on_temperatures(self, t: float, temps: Mapping[str, float]) -> None:
        for unit in self.units.values():
            unit.on_temperatures(t, temps)

    def on_channel(self, name: str, t: float, value_c: float, ok: bool) -> None:
        for unit in self.units.values():
            unit.on_channel(name, t, value_c, ok)

    def on_position(self, now: float, t: float, value_um: float, ok: bool, problem: str = "",
                    channel: str | None = None) -> None:
        for unit in self.units.values():
            if unit.position_channel is not None and unit.position_channel == channel:
                unit.on_position(now, t, value_um, ok, problem)

    def on_reached(self, t: float, q_um: Mapping[str, float]) -> None:
        for unit in self.units.values():
            unit.on_reached(t, q_um)  # each unit takes its own axis

    @property
    def state(self) -> str:
        return max((u.state for u in self.units.values()), key=lambda s: _RANK.get(s, 0))

    @property
    def correction_um(self) -> dict[str, float] | None:
        corrections = {a: u.correction_um for a, u in self.units.items() if u.correction_um is not None}
        return {a: c for a, c in corrections.items() if c is not None} or None

    def document(self) -> dict[str, object]:
        return {"state": self.state, "correction_um": self.correction_um,
                "axes": {axis: unit.document() for axis, unit in self.units.items()}}

    def flush(self) -> None:
        for unit in self.units.values():
            unit.flush()  # its own log lines (with its axis); it publishes nothing itself
        state = self.state
        if state != self._announced:
            self._announced = state
            self.publish(self.document())

    def start(self, bus: Bus) -> asyncio.Task[None]:
        self._publisher = bus.session.declare_publisher(bus.keys.health)
        self.publish(self.document())
        return asyncio.create_task(self._periodic(), name="health")

    async def _periodic(self) -> None:
        while True:
            await asyncio.sleep(PUBLISH_INTERVAL_S)
            self.flush()
            self.publish(self.document())

    def publish(self, doc: Mapping[str, object]) -> None:
        if self._publisher is None:
            return
        try:
            self._publisher.put(dumps(doc))
        except zenoh.ZError as error:
            self.log.warning("health_publish_failed", error=str(error))
