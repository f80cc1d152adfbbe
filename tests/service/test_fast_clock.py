"""A simulated daemon on a fast clock serves (issue 19.6).

At ``[simulation] speed = 10000`` the paper's sensor timing (T1..T4 every 0.5 s, fresh for 5 s) is 50 µs
and 0.5 ms of wall time: the pollers spun a core and the daemon flapped between ok and stale, refusing
most targets ("channel T1 is stale: last reading 8.9 s old"). The default sensors now scale to what the
daemon serves at the speed, and records are labelled with the simulated lab's clock, so its days are
the record files' days.
"""

from __future__ import annotations

import csv
import itertools
import time
from pathlib import Path

from helpers.daemon_harness import Client, Daemon, free_port, wait_until

from nanodrift.config import DEFAULT_MODEL_PATH

CHANNELS = ("T1", "T2", "T3", "T4", "interferometer")
SPEED = 10_000.0
TARGETS = 40
PACE_WALL_S = 0.1  # one target every 1000 s of cell time


def test_a_simulated_daemon_at_speed_10000_answers_every_target_and_records_on_the_cell_clock(tmp_path: Path):
    port = free_port()
    records = tmp_path / "records"
    config = tmp_path / "fast.toml"
    config.write_text(
        f'cell = "fast"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
        f'[model]\npath = "{DEFAULT_MODEL_PATH}"\n'
        f'[health]\nsettle_s = 60.0\nwindow_s = 300.0\nrecord_dir = "{records}"\n'
        f'[simulation]\nscenario = "room"\nspeed = {SPEED}\n'  # no [[sensors]]: the simulated cell's own
    )
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "fast")
        try:
            first = client.wait_ready(CHANNELS)
            t_first = max(s["t"] for s in first["sensors"].values())
            refusals = []
            for i in range(TARGETS):
                ok, answer = client.query({"x_um": 80.0 * (i % 7), "id": i})
                if not ok:
                    refusals.append(answer)
                time.sleep(PACE_WALL_S)  # pacing the targets, not waiting for a condition
            assert refusals == []
            status = client.status()
            t_last = max(s["t"] for s in status["sensors"].values())
            assert t_last - t_first > 0.5 * TARGETS * PACE_WALL_S * SPEED  # hours of cell time went by
            assert status["counters"]["commands"] == TARGETS
            wait_until(lambda: list(records.glob("records-*.csv")), 10, "a record file")
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
    rows = []
    for path in sorted(records.glob("records-*.csv")):
        with open(path, newline="") as handle:
            rows += [float(r["t_s"]) for r in csv.DictReader(handle)]
    assert len(rows) >= TARGETS // 2
    # labelled with the cell's clock: inside its span, and as far apart as the targets in cell time (the
    # wall clock would put them a tenth of a second apart)
    assert all(t_first <= t <= t_last + 3600.0 for t in rows)
    assert min(b - a for a, b in itertools.pairwise(rows)) > 100.0
