"""The ``status`` queryable and the one-line status systemd shows: built from the cell state on the loop.

Answered on the asyncio loop on purpose: a reply proves the loop runs; ``healthy`` adds that every
sensor poller is alive and making progress. ``health`` (the health unit's document: is the model
still right) comes last, when the daemon has a health unit.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from nanodrift.bus.protocol import dumps
from nanodrift.bus.session import Bus
from nanodrift.compensation import Compensator, one_axis
from nanodrift.config import ZENOH_KIND, ActuatorConfig, Config
from nanodrift.drivers.base import State
from nanodrift.model.cell_model import CellModel
from nanodrift.service.actuation import Actuation
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.state import CellState


def status_doc(state: CellState, healthy: bool, actuation: Actuation | None = None,
               health: HealthUnit | None = None) -> dict[str, Any]:
    """The ``status`` payload's document (README, Zenoh keys ``status``)."""
    driven: dict[str, Any] | None = None
    if actuation is not None:  # a one-axis cell shows its one output as it always did; a cell of several, per axis
        driven = actuation.axis_doc("x") if one_axis(state.config.axis_names) else actuation.doc()
    with state.lock:
        now = state.clock.now()
        comp = state.compensator
        config = state.config
        doc = {
            "cell": config.cell,
            "t": time.time(),
            "uptime_s": round(time.monotonic() - state.started_monotonic_s, 3),
            "config": config.source,
            "model": model_doc(comp),
            "model_path": str(config.model.path),
            "model_problem": comp.model_problem or None,
            "sensors": state.table.snapshot(now),
            "extrapolating": sorted(set(comp.extrapolating_now()) | set(comp.last_extrapolating)),
            "actuator": (actuator_doc(config.actuator, driven) if one_axis(config.axis_names)
                         else cell_actuator_doc(driven)),
            "counters": state.counters.as_dict(),
            "healthy": healthy,
        }
        if not one_axis(config.axis_names):
            doc["axes"] = axes_doc(config, driven, state.table.snapshot(now))
        if health is not None:
            doc["health"] = health.document()
        return doc


def model_doc(comp: Compensator) -> dict[str, Any] | None:
    """The served model in ``status``: a one-axis model's terms and x range, a cell model's per axis."""
    model = comp.model
    if model is None:
        return None
    doc: dict[str, Any] = {"id": model.id}
    if isinstance(model, CellModel):  # the model file's shape
        training = model.models[model.axes[0]].training
        doc.update(axes=list(model.axes), terms={a: model.models[a].term_names() for a in model.axes})
        positions: dict[str, Any] = {"positions_um": {a: list(r) for a, r in model.position_ranges.items()}}
        channels = model.channel_ranges
    else:
        training = model.training
        doc["terms"] = model.term_names()
        positions, channels = {"x_um": list(training.x_range)}, training.channel_ranges
    doc.update(channels=list(comp.channels), missing_channels=list(comp.missing),
               training={**positions, "channels": {c: list(r) for c, r in channels.items()}, "rows": training.rows,
                         "t_span_s": training.t_span_s},
               ready=comp.ready, created=model.provenance.get("created"))  # its age in ``nanodrift status``
    return doc


def status_line(state: CellState, health: HealthUnit | None = None) -> str:
    """``cell c: 3/4 sensors ok, model m-..., 12 commands, 0 refused, health ok`` (systemd's STATUS=)."""
    with state.lock:
        now = state.clock.now()
        table = state.table
        states = [table.state(n, now)[0] for n in table.entries]
        commands, refused = state.counters.commands, sum(state.counters.errors.values())
        model_id = state.model_id()
        health_state = health.state if health is not None else None
    ok = sum(s == State.OK for s in states)
    return (f"cell {state.config.cell}: {ok}/{len(states)} sensors ok, model {model_id or 'none'}, "
            f"{commands} commands, {refused} refused" + (f", health {health_state}" if health_state else ""))


class StatusHandler:
    """``on_status`` for the bus (called on the loop)."""

    def __init__(self, state: CellState, bus: Bus, healthy: Callable[[], bool], log: Any,
                 actuation: Actuation | None = None,
                 health: HealthUnit | None = None) -> None:
        self.state = state
        self.actuation = actuation
        self.health = health
        self.bus = bus
        self.healthy = healthy
        self.log = log

    def on_status(self, query: zenoh.Query) -> None:
        try:
            doc = status_doc(self.state, self.healthy(), self.actuation, self.health)
            self.bus.reply(query, self.bus.keys.status, dumps(doc))
        except zenoh.ZError as error:
            self.log.warning("status_reply_failed", error=str(error))


#: the ``[actuator]`` keys ``status`` always showed, in their order (clients read them)
_ACTUATOR_KEYS = ("volts_per_um", "offset_v", "v_min", "v_max", "x_min_um", "x_max_um")


def actuator_doc(actuator: ActuatorConfig, driven: Mapping[str, Any] | None = None) -> dict[str, Any]:
    """The actuator in ``status``: the conversion and limits, then who drives the stage and how.

    ``driven`` is :meth:`Actuation.axis_doc` (state, reason, device, last written voltage and time,
    writes, failures). With ``kind = "zenoh"`` there is no device: the daemon publishes ``command``
    and an output node applies it, so the state is always ``ok`` and ``output`` says ``published``.
    """
    doc: dict[str, Any] = {key: getattr(actuator, key) for key in _ACTUATOR_KEYS}
    doc.update(kind=actuator.kind, max_slew_um_per_s=actuator.max_slew_um_per_s,
               safe_voltage_v=actuator.safe_voltage_v if math.isfinite(actuator.safe_voltage_v) else None)
    if actuator.kind == ZENOH_KIND:
        doc.update(state="ok", reason=None, output="published", device=None)
    elif driven is not None:
        doc.update(driven)
        doc["output"] = "device"
    return doc


def cell_actuator_doc(driven: Mapping[str, Any] | None) -> dict[str, Any]:
    """A multi-axis cell's outputs as one actuator in ``status`` (the state of all its axes: one fault
    refuses every target); the per-axis detail is in ``axes``."""
    if driven is None:  # every axis published (kind = "zenoh")
        return {"kind": "axes", "state": "ok", "reason": None, "output": "published"}
    return {"kind": "axes", "state": driven["state"], "reason": driven["reason"], "failures": driven["failures"],
            "output": "device"}


def axes_doc(config: Config, driven: Mapping[str, Any] | None, sensors: Mapping[str, Any]) -> dict[str, Any]:
    """``"axes"`` in a multi-axis cell's status: each axis' workspace, actuator (as ``actuator`` of a
    one-axis cell, with its device's state) and position sensor."""
    devices = (driven or {}).get("axes", {})
    positions = {config.sensor_axis(s.name): s.name for s in config.sensors if s.role == "position"}
    out: dict[str, Any] = {}
    for axis, actuator in config.axis_actuators().items():
        device = devices.get(axis)
        doc = actuator_doc(actuator)
        if device is not None:
            doc.update(state=driven["state"] if driven else "ok", reason=driven["reason"] if driven else None,
                       output="device", **device)
        elif actuator.kind != ZENOH_KIND:
            doc.update(state="closed", reason=None, output="device", device=None)
        position = positions.get(axis)
        out[axis] = {"min_um": actuator.x_min_um, "max_um": actuator.x_max_um, "actuator": doc,
                     "position_sensor": position,
                     "position": sensors.get(position) if position is not None else None}
    return out
