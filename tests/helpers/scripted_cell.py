"""A cell's Zenoh side scripted by a test, for the bridges' tests of a daemon that misbehaves: one that takes a
move's query and never answers it (stalled), or answers it and never says ``done`` (a lost ``done``)."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import zenoh

from helpers.daemon_harness import free_port
from nanodrift.bus.protocol import Keys

#: the scripted command's gain (the simulated cell's ``volts_per_um``)
VOLTS_PER_UM = 0.02


class ScriptedCell:
    """One axis' Zenoh side, scripted by the test on a real session over loopback: ``status`` answers (a
    cell whose state is ok); ``compensate`` is held unanswered while :attr:`answering` is clear (a stalled
    daemon), else answered with a command and no ``done`` ever follows (a lost ``done``); ``stop`` answers
    and publishes the ``done`` ``stopped`` of every move it answered.

    ``interferometer``: ``status`` lists a position sensor on the axis; ``first_position_um``: the one sample
    it publishes, only once a subscriber listens (a Zenoh matching listener), so a client sees it only after
    it has subscribed; None: the sensor never publishes (a faulted one)."""

    def __init__(self, cell: str, *, interferometer: bool = False, first_position_um: float | None = None) -> None:
        self.cell = cell
        self.interferometer = interferometer
        self.first_position_um = first_position_um
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.keys = Keys(cell)
        self.answering = threading.Event()
        self.stops: list[str] = []  # what the cell received on stop: the device side of a STOP put
        self.asked = threading.Semaphore(0)  # released per compensate query received
        self._held: list[zenoh.Query] = []  # queries taken and never answered (dropped at close)
        self._answered: list[Any] = []  # ids of the moves answered
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([self.endpoint]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self.session = zenoh.open(conf)
        self._entities = [self.session.declare_queryable(self.keys.status, self._status),
                          self.session.declare_queryable(self.keys.compensate, self._compensate),
                          self.session.declare_queryable(self.keys.stop, self._stop)]
        if first_position_um is not None:
            self._position = self.session.declare_publisher(self.keys.telemetry("position", "interferometer"))
            self._entities += [self._position, self._position.declare_matching_listener(self._on_matching)]

    def _on_matching(self, status: zenoh.MatchingStatus) -> None:
        if status.matching:
            self._position.put(json.dumps({"value": self.first_position_um, "t": time.time(), "state": "ok"}))

    def _status(self, query: zenoh.Query) -> None:
        sensors = {"interferometer": {"role": "position", "state": "ok"}} if self.interferometer else {}
        query.reply(self.keys.status, json.dumps({"cell": self.cell, "model": "m1", "sensors": sensors,
                                                   "actuator": {"x_min_um": 0.0, "x_max_um": 480.0}}))

    def _compensate(self, query: zenoh.Query) -> None:
        request = json.loads(query.payload.to_bytes()) if query.payload is not None else {}
        self.asked.release()
        if not self.answering.is_set():
            self._held.append(query)
            return
        x_um = float(request["x_um"])
        self._answered.append(request["id"])
        query.reply(self.keys.compensate, json.dumps({"id": request["id"], "x_um": x_um, "q_um": x_um,
                                                      "voltage_v": x_um * VOLTS_PER_UM, "q_sigma_um": 0.01,
                                                      "extrapolating": [], "model": "m1", "t": time.time()}))

    def _stop(self, query: zenoh.Query) -> None:
        self.stops.append(query.payload.to_bytes().decode() if query.payload is not None else "")
        query.reply(self.keys.stop, json.dumps({"held": True}))
        for move_id in self._answered:
            self.session.put(self.keys.done, json.dumps({"id": move_id, "state": "stopped",
                                                         "error": "stopped by a client", "t": time.time()}))
        self._answered.clear()

    def close(self) -> None:
        for entity in reversed(self._entities):
            entity.undeclare()
        self._held.clear()
        self.session.close()
