"""What the target path (on Zenoh's threads) reads and the asyncio loop writes, behind one lock; and the one
place the serving state (config + model -> compensator, sensor table, health) is built, at start and at
every reload (:func:`load_serving_model`, :func:`serving_state`), so both say the same of the same model.

``CellState.lock`` is held for short computations only, never while publishing: the loop takes it
to ingest readings, swap a reload and build the status, so a publish that waits on a congested
subscriber must never hold it (``nanodrift.service.targets`` publishes under its own answer lock).
"""

from __future__ import annotations

import json
import threading
import time
from collections import Counter
from typing import Any

from nanodrift.compensation import Compensator, load_served_model
from nanodrift.config import Config
from nanodrift.drivers.base import Clock
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Model, ModelFileError
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.table import SensorTable


def load_serving_model(config: Config) -> tuple[Model | CellModel | None, str]:
    """The model ``config`` names if it serves the cell's axes, or None and why not: the start serves
    without it (targets refused with the reason), a reload refuses the edit with the same reason."""
    try:
        return load_served_model(config.model.path, config.axis_names), ""
    except ModelFileError as error:
        return None, str(error)


def same_content(old: Model | CellModel | None, new: Model | CellModel | None) -> bool:
    """Whether ``new`` serves exactly what ``old`` does, so its evaluators (lag filters, direction) can be kept.

    The whole file's content, not the stored id: the id leaves out fit statistics, yet a file without
    a covariance serves ``fit.rmse_um`` as every command's sigma. A reload applies any change of
    content; an unchanged file keeps the running filters.
    """
    if old is None or new is None:
        return False
    return json.dumps(old.to_dict(), sort_keys=True) == json.dumps(new.to_dict(), sort_keys=True)


def serving_state(config: Config, model: Model | CellModel | None, health: HealthUnit, *, model_problem: str = "",
                  running: Compensator | None = None, table: SensorTable | None = None) -> Compensator:
    """The compensator of ``config`` and ``model`` serving through ``health`` (reconfigured for them), on
    ``table`` (None: a new table judging every reading, carrying ``running``'s last readings over). The
    evaluators of ``running`` are kept when its model has the same content, else fed the latest readings."""
    if table is None:
        table = SensorTable(config.sensors, config.actuator.workspace_um, config.sensor_workspaces())
        if running is not None and isinstance(running.readings, SensorTable):
            table.carry_over(running.readings)
    compensator = Compensator(model, config.axis_actuators(), table, model_problem, monitor=health)
    if running is not None and running.evaluators is not None and same_content(running.model, model):
        compensator.evaluators = running.evaluators  # same model: keep lag filters and direction
    else:
        compensator.warm()
    health.reconfigure(config, model)
    return compensator


class Counters:
    """What the service did, for ``status``."""

    def __init__(self) -> None:
        self.targets = 0
        self.commands = 0
        self.errors: Counter[str] = Counter()
        self.reloads = 0
        self.reload_failures = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "targets": self.targets,
            "commands": self.commands,
            "errors": dict(self.errors),
            "errors_total": sum(self.errors.values()),
            "reloads": self.reloads,
            "reload_failures": self.reload_failures,
        }


class CellState:
    """One cell's running configuration, sensor table, compensator and counters.

    A reload replaces ``config`` and ``compensator`` (and with it ``table``) under ``lock``; readers
    on other threads take the lock and read the attributes each time instead of keeping them.
    """

    def __init__(self, config: Config, compensator: Compensator, clock: Clock) -> None:
        self.lock = threading.Lock()
        self.config = config
        self.compensator = compensator
        self.clock = clock  # replaced by the drivers' context clock when they start
        self.counters = Counters()
        self.started_monotonic_s = time.monotonic()  # uptime: a wall-clock step does not change it
        #: targets are answered only while serving (not by a daemon that is starting or half closed)
        self.serving = False
        #: set when the daemon stops: targets are refused with ``shutting_down`` until the bus closes
        self.stopping = False

    @property
    def table(self) -> SensorTable:
        """The compensator's (one table per configuration)."""
        table = self.compensator.readings
        assert isinstance(table, SensorTable)
        return table

    def model_id(self) -> str | None:
        model = self.compensator.model
        return model.id if model is not None else None
