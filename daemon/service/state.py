"""What the target path (on Zenoh's threads) reads and the asyncio loop writes, behind one lock.

``CellState.lock`` is held for short computations only, never while publishing: the loop takes it
to ingest readings, swap a reload and build the status, so a publish that waits on a congested
subscriber must never hold it (``nanodrift.service.targets`` publishes under its own answer lock).
"""

from __future__ import annotations

import threading
import time
from collections import Counter
from typing import Any

from nanodrift.config import Config
from nanodrift.drivers.base import Clock
from nanodrift.service.cell_compensator import CellCompensator
from nanodrift.service.compensator import Compensator
from nanodrift.service.table import SensorTable


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

    def __init__(self, config: Config, compensator: Compensator | CellCompensator, clock: Clock) -> None:
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
        return self.compensator.table

    def model_id(self) -> str | None:
        model = self.compensator.model
        return model.id if model is not None else None
