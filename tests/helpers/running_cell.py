"""A simulated cell served by a real daemon (``nanodrift run`` subprocess) on a free 127.0.0.1 port, for the
bridges' tests (Bluesky, EPICS): one axis or XY, with an optional slew so a move ramps long enough to be
stopped midway.

:class:`RunningCell` returns once the daemon serves and its temperatures are ok (a target is then answered,
not refused as stale); :meth:`RunningCell.watch_command` gives an event set when a command for a given
target is published (the "mid-ramp" moment a stop test waits on).
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import zenoh

from helpers.daemon_harness import Daemon, free_port, wait_until
from nanodrift import Client

#: the simulated cell's gain (its default ``[actuator] volts_per_um``)
VOLTS_PER_UM = 0.02


def simulated_config(port: int, cell: str, *, axes: str = "", slew_um_per_s: float = 0.0) -> str:
    """The simulated cell (its own sensors and model); ``axes = "xy"``: the stacked XY stage; a slew puts
    each axis' simulated output behind ``max_slew_um_per_s``."""
    text = (f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            '[simulation]\nscenario = "room"\nspeed = 1.0\nseed = 0\n')
    if axes:
        text += f'axes = "{axes}"\n'
        if slew_um_per_s:
            text += "".join(f'[[axes]]\nname = "{a}"\nmin_um = 0.0\nmax_um = 480.0\n[axes.actuator]\n'
                            f'kind = "simulated"\nmax_slew_um_per_s = {slew_um_per_s}\n' for a in axes)
    elif slew_um_per_s:
        text += f'[actuator]\nkind = "simulated"\nmax_slew_um_per_s = {slew_um_per_s}\n'
    return text


class RunningCell:
    def __init__(self, root: Path, cell: str, *, axes: str = "", slew_um_per_s: float = 0.0) -> None:
        self.cell = cell
        self.port = free_port()
        self.endpoint = f"tcp/127.0.0.1:{self.port}"
        config = root / f"{cell}.toml"
        config.write_text(simulated_config(self.port, cell, axes=axes, slew_um_per_s=slew_um_per_s))
        self.daemon = Daemon(["--config", str(config)], root / f"{cell}.log")
        try:
            self.daemon.wait_log("serving", timeout=30)
            self.client = Client(self.endpoint, cell=cell)
            wait_until(self._temperatures_ok, 30, f"cell {cell}'s temperatures ok", interval=0.1)
        except BaseException:
            self.daemon.stop()
            raise

    def _temperatures_ok(self) -> bool:
        try:
            sensors = self.client.status(timeout_s=1.0)["sensors"]
        except TimeoutError:
            return False
        return all(s["state"] == "ok" for s in sensors.values())

    def status(self) -> dict[str, Any]:
        return self.client.status()

    def last_voltage_v(self, axis: str | None = None) -> float:
        """What the cell's (simulated) output last received: the device side of a move."""
        doc = self.status()
        actuator = doc["axes"][axis]["actuator"] if axis else doc["actuator"]
        return float(actuator["last_voltage_v"])

    def watch_command(self, matches: Callable[[dict[str, Any]], bool]) -> tuple[threading.Event, Any]:
        """An event set once a published ``command`` matches; undeclare the returned subscriber when done."""
        seen = threading.Event()

        def on_command(sample: zenoh.Sample) -> None:
            if matches(json.loads(sample.payload.to_bytes())):
                seen.set()

        return seen, self.client.session.declare_subscriber(f"{self.client.keys.prefix}/command", on_command)

    def close(self) -> int:
        self.client.close()
        return self.daemon.stop()
