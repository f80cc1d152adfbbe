"""The simulated cell at the fastest allowed ``speed`` still serves and stops on SIGTERM (issue 10).

``speed = 1e9`` used to pass validation; every poll then made the cell compute ever longer stretches
of room history (billions of simulated seconds) in one synchronous call, so the event loop never ran
the SIGTERM handler. ``speed`` is now at most :data:`~nanodrift.drivers.simulated.config.MAX_SPEED`; at that
speed the daemon answers targets and SIGTERM stops it within a few seconds.
"""

from __future__ import annotations

import signal
import subprocess
import time
from pathlib import Path

from helpers.daemon_harness import Client, Daemon, free_port, wait_until

from nanodrift.config import DEFAULT_MODEL_PATH
from nanodrift.drivers.simulated.config import MAX_SPEED

CHANNELS = ("T1", "T2", "T3", "T4")  # every thermocouple: whichever the shipped model uses


def test_sigterm_stops_a_daemon_running_the_simulated_cell_at_the_maximum_speed(tmp_path: Path) -> None:
    port = free_port()
    # max_age_s = a simulated day: at this speed it is 8.6 wall seconds, so the channels stay ok
    sensors = "".join(f'[[sensors]]\nname = "{c}"\nkind = "simulated"\ninterval_s = 0.5\nmax_age_s = 86400.0\n'
                      for c in CHANNELS)
    config = tmp_path / "fast.toml"
    config.write_text(f'cell = "fast"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
                      f'[model]\npath = "{DEFAULT_MODEL_PATH}"\n'
                      f'[simulation]\nscenario = "room"\nspeed = {MAX_SPEED}\n{sensors}')
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "fast")
        try:
            client.wait_ready(CHANNELS)
            first = client.status()["sensors"]["T1"]["t"]
            ok, command = client.query({"x_um": 240.0, "id": "fast"})
            assert ok, command
            # the simulated clock runs at MAX_SPEED: a second status sees hours of cell time later
            wait_until(lambda: client.status()["sensors"]["T1"]["t"] > first + 3600.0, 10,
                       "an hour of simulated time", interval=0.05)
        finally:
            client.close()
        sent = time.monotonic()
        daemon.signal(signal.SIGTERM)
        try:
            code = daemon.proc.wait(timeout=10)
        except subprocess.TimeoutExpired:
            raise AssertionError("the daemon ignored SIGTERM for 10 s") from None
        took_s = time.monotonic() - sent
        assert code == 0 and took_s < 5.0, (code, took_s)
        assert daemon.log_events("stopped"), daemon.log_path.read_text()[-2000:]
    finally:
        daemon.stop()
