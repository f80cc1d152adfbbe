"""What a bridge (``nanodrift.bluesky``, ``nanodrift ioc``) sees of one cell besides moving it: its axes,
their workspaces and position sensors (from ``status``), the latest command's target per axis and the
latest measured position per axis (from the cell's ``command`` and ``sensors/position`` broadcasts).

Both bridges move one axis of a cell of several "with the others at their last setpoints". The last
setpoint is the target of the cell's latest ``command``, whoever sent it (a script, ``nanodrift target``,
another bridge), so a bridge never drags an axis back to where it itself last put it.

Thread-safe: the Zenoh callbacks fill a table under a lock and then call the listeners (on Zenoh's
thread: an asyncio bridge hands the value to its loop with ``call_soon_threadsafe``).
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import zenoh

from nanodrift.bus.session import undeclare_all
from nanodrift.client import Client, Command, Position, json_object, number

__all__ = ["AxisInfo", "CellView", "Measured", "axes_of", "axis_value", "cell_state", "measured_of", "number",
           "setpoints_of"]

#: the longest :meth:`CellView.open` waits for the first position samples (the interferometers read every 0.1 s)
FIRST_POSITION_TIMEOUT_S = 2.0

#: ``listener(kind, axis, value)``: kind ``"command"`` (axis ``""``, value: the payload as a dict) or ``"position"``
#: (value: :class:`Measured`)
Listener = Callable[[str, str, Any], None]


@dataclass(frozen=True)
class AxisInfo:
    """One axis of a cell as its ``status`` describes it."""

    name: str
    min_um: float
    max_um: float
    position_sensor: str | None  # the sensor measuring this axis, None when nothing measures it


@dataclass(frozen=True)
class Measured:
    """A position sample: ``value_um`` at ``t`` (the daemon's wall-clock label, comparable with a ``done``'s)."""

    value_um: float
    t: float


def cell_state(doc: Mapping[str, Any]) -> str:
    """A cell's state from its ``status`` (``nanodrift status``' STATE column, the EPICS ``STATE``): ok;
    degraded (a sensor not ok, no usable model, extrapolating); stalled (pollers not progressing)."""
    if doc.get("healthy") is False:
        return "stalled"
    sensors = doc.get("sensors")
    sensors = sensors if isinstance(sensors, dict) else {}
    if doc.get("model") is None or doc.get("model_problem"):
        return "no-model"
    if any(isinstance(s, dict) and s.get("state") != "ok" for s in sensors.values()):
        return "degraded"
    if doc.get("extrapolating"):
        return "extrapolating"
    return "ok"


def axis_value(doc: Mapping[str, Any], key: str, axis: str) -> float:
    """``key`` of a ``command`` payload for ``axis`` (a number in a one-axis cell, a mapping by axis in a cell
    of several); nan when it is not a finite number."""
    value = doc.get(key)
    if isinstance(value, Mapping):
        value = value.get(axis)
    found = number(value)
    return math.nan if found is None else found


def setpoints_of(doc: Mapping[str, Any], axes: Iterable[str]) -> dict[str, float]:
    """The targets a ``command`` payload names (``<axis>_um``) for ``axes``."""
    found = {axis: number(doc.get(f"{axis}_um")) for axis in axes}
    return {axis: value for axis, value in found.items() if value is not None}


def measured_of(doc: Mapping[str, Any]) -> Measured | None:
    """A ``sensors/position`` payload as a sample; None unless its state is ok and value and ``t`` are numbers."""
    value, t = number(doc.get("value")), number(doc.get("t"))
    if doc.get("state", "ok") != "ok" or value is None or t is None:
        return None
    return Measured(value, t)


def axes_of(status: Mapping[str, Any]) -> dict[str, AxisInfo]:
    """The axes of a cell from its ``status`` payload, in the cell's order (a one-axis cell: ``x``); a
    :class:`ValueError` when its ``axes`` describes none."""

    def bound(value: Any, default: float) -> float:
        found = number(value)
        return default if found is None else found

    axes = status.get("axes")
    if isinstance(axes, dict) and axes:
        found = {str(name): AxisInfo(str(name), bound(each.get("min_um"), -math.inf),
                                    bound(each.get("max_um"), math.inf),
                                    str(each["position_sensor"]) if each.get("position_sensor") else None)
                 for name, each in axes.items() if isinstance(each, dict)}
        if not found:
            raise ValueError(f"the status of cell {status.get('cell')!r} has 'axes' but no axis described in it")
        return found
    actuator = status.get("actuator")
    actuator = actuator if isinstance(actuator, dict) else {}
    sensors = status.get("sensors")
    sensors = sensors if isinstance(sensors, dict) else {}
    position = next((str(name) for name, s in sensors.items() if isinstance(s, dict) and s.get("role") == "position"),
                    None)
    return {"x": AxisInfo("x", bound(actuator.get("x_min_um"), -math.inf), bound(actuator.get("x_max_um"), math.inf),
                          position)}


class CellView:
    """The axes of ``client``'s cell and their latest setpoints and measured positions.

    ``status`` is the cell's status payload (its axes and position sensors); the subscribers live on the
    client's session until :meth:`close`.
    """

    def __init__(self, client: Client, status: Mapping[str, Any]) -> None:
        self.cell = str(client.cell)
        self.axes = axes_of(status)
        self.multi_axis = isinstance(status.get("axes"), dict) and bool(status.get("axes"))
        self._lock = threading.Lock()
        self._setpoints: dict[str, float] = {}
        self._positions: dict[str, Measured] = {}
        self._command_t = -math.inf
        self._command: dict[str, Any] = {}
        self._moved = threading.Condition(self._lock)
        self._listeners: list[Listener] = []
        keys = client.keys
        self._subscribers = [
            client.session.declare_subscriber(keys.command, self._on_command),
            client.session.declare_subscriber(f"{keys.prefix}/sensors/position/**", self._on_position),
        ]

    @classmethod
    def open(cls, client: Client, *, timeout_s: float = 5.0) -> CellView:
        """The view of ``client``'s cell, its axes read from one ``status`` query (:class:`TimeoutError` when
        the cell does not answer), once each measured axis has its first position sample (at most
        ``FIRST_POSITION_TIMEOUT_S`` later): a move of one axis holds the others where they are measured, and
        a bridge that served before its first sample would refuse that move ("no setpoint known"). A faulted
        sensor only delays this."""
        view = cls(client, client.status(timeout_s=timeout_s))
        deadline = time.monotonic() + min(timeout_s, FIRST_POSITION_TIMEOUT_S)
        for axis, info in view.axes.items():
            if info.position_sensor:
                view.wait_position(axis, -math.inf, max(deadline - time.monotonic(), 0.0))
        return view

    def add_listener(self, listener: Listener) -> None:
        self._listeners.append(listener)

    def close(self) -> None:
        undeclare_all(self._subscribers)

    # --- what is known ------------------------------------------------------------------------------

    def setpoint(self, axis: str) -> float | None:
        """The target of the cell's latest command on ``axis`` (None before any was seen)."""
        with self._lock:
            return self._setpoints.get(axis)

    def position(self, axis: str) -> Measured | None:
        """The latest ``ok`` sample of the position sensor on ``axis`` (None: none yet, or no sensor)."""
        with self._lock:
            return self._positions.get(axis)

    def command(self) -> dict[str, Any]:
        """The cell's latest ``command`` payload (empty before any was seen)."""
        with self._lock:
            return dict(self._command)

    def wait_position(self, axis: str, after_t: float, timeout_s: float) -> Measured | None:
        """The first sample on ``axis`` labelled ``after_t`` or later (a move's ``done`` ``t``), waiting up to
        ``timeout_s`` for it; None when none comes (a stale or faulted sensor: ``status`` says which)."""
        with self._moved:
            self._moved.wait_for(lambda: (m := self._positions.get(axis)) is not None and m.t >= after_t, timeout_s)
            measured = self._positions.get(axis)
        return measured if measured is not None and measured.t >= after_t else None

    def request(self, changes: Mapping[str, float]) -> Position:
        """The target to send to move the axes in ``changes`` and hold the others at their last setpoints:
        a number in a one-axis cell, a mapping by axis otherwise.

        An axis left out takes the cell's latest command, else its measured position (kept inside its
        workspace); with neither, a :class:`ValueError` names it. An unknown axis is a ValueError too.
        """
        unknown = sorted(set(changes) - set(self.axes))
        if unknown:
            raise ValueError(f"cell {self.cell!r} has no axis {', '.join(unknown)} (its axes: {', '.join(self.axes)})")
        if not self.multi_axis:
            return float(changes["x"])
        target: dict[str, float] = {}
        for axis, info in self.axes.items():
            if axis in changes:
                target[axis] = float(changes[axis])
                continue
            held = self._held(info)
            if held is None:
                raise ValueError(
                    f"cell {self.cell!r} axis {axis}: no setpoint known (no command seen since this client started"
                    + ("" if info.position_sensor else ", and no position sensor measures it")
                    + f"): move every axis once, e.g. with a mapping naming {', '.join(self.axes)}")
            target[axis] = held
        return target

    def _held(self, info: AxisInfo) -> float | None:
        setpoint = self.setpoint(info.name)
        if setpoint is not None:
            return setpoint
        measured = self.position(info.name)
        if measured is None:
            return None
        return min(max(measured.value_um, info.min_um), info.max_um)

    def note_command(self, command: Command) -> None:
        """Take a move's answered command as the latest (before its broadcast may arrive)."""
        self._apply_command(command.payload)

    # --- the broadcasts (Zenoh's threads) -----------------------------------------------------------

    def _on_command(self, sample: zenoh.Sample) -> None:
        doc = json_object(sample.payload.to_bytes())
        if doc is not None:
            self._apply_command(doc)

    def _apply_command(self, doc: Mapping[str, Any]) -> None:
        t = number(doc.get("t"))
        found = setpoints_of(doc, self.axes)
        with self._lock:
            if t is not None and t < self._command_t:  # an older command delivered late: the newer one stands
                return
            self._command_t = t if t is not None else self._command_t
            self._command = dict(doc)
            self._setpoints.update(found)
        self._tell("command", "", dict(doc))

    def _on_position(self, sample: zenoh.Sample) -> None:
        doc = json_object(sample.payload.to_bytes())
        measured = measured_of(doc) if doc is not None else None
        axis = str(sample.key_expr).rsplit("/sensors/position", 1)[-1].strip("/") or "x"  # one axis: no suffix
        if measured is None or axis not in self.axes:
            return
        with self._moved:
            self._positions[axis] = measured
            self._moved.notify_all()
        self._tell("position", axis, measured)

    def _tell(self, kind: str, axis: str, value: Any) -> None:
        for listener in list(self._listeners):
            listener(kind, axis, value)
