"""``[health] record_dir`` in the running daemon (issue 12): the simulated cell serves targets over Zenoh and
every settled target becomes a row of the day's CSV, readable by ``fit``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from helpers.daemon_harness import Client, Daemon, free_port, wait_until

from daemon.calibration.dataset import Dataset, read_csv
from daemon.config import DEFAULT_MODEL_PATH
from daemon.model.model import load_model

TARGETS_UM = (80.0, 400.0, 160.0, 320.0, 240.0)


def recorded(folder: Path) -> Dataset | None:
    files = sorted(folder.glob("records-*.csv"))
    if len(files) != 1:
        return None  # not yet (or a UTC midnight fell inside the test: then two files, waited for below)
    try:
        return read_csv(files[0])
    except ValueError:  # the header is there, no row yet
        return None


def test_the_daemon_records_every_settled_target_in_the_day_file(tmp_path: Path) -> None:
    port = free_port()
    records = tmp_path / "records"
    config = tmp_path / "sim.toml"
    config.write_text(
        f'cell = "reccell"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
        f'[model]\npath = "{DEFAULT_MODEL_PATH}"\n'
        f'[health]\nsettle_s = 1.0\nwindow_s = 0.5\nrecord_dir = "records"\n'  # relative to the config's folder
        f'[simulation]\nscenario = "room"\nspeed = 10.0\nseed = 4\n'
    )
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "reccell")
        try:
            client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
            commands = []
            for i, x in enumerate(TARGETS_UM):
                ok, command = client.query({"x_um": x, "id": f"rec-{i}"})
                assert ok, command
                commands.append(command)
                # the stage holds the target: one settled row (settle_s 1 s, window 0.5 s of cell time)
                wait_until(lambda n=i + 1: (d := recorded(records)) is not None and len(d) >= n, 30,
                           f"{i + 1} recorded rows")
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
    data = recorded(records)
    assert data is not None and len(data) == len(TARGETS_UM)
    model = load_model(DEFAULT_MODEL_PATH)
    assert data.channel_names == model.channels  # the channels the commands were computed from
    np.testing.assert_allclose(data.extra["target_um"], TARGETS_UM)
    np.testing.assert_allclose(data.q, [c["q_um"] for c in commands])
    assert np.all(np.abs(data.x - data.extra["target_um"]) < 0.5)  # measured by the interferometer, compensated
    np.testing.assert_allclose(data.extra["residual_um"], data.x - data.extra["target_um"], atol=1e-12)
    assert np.all(np.abs(data.t - np.array([c["t"] for c in commands])) < 30.0)  # unix seconds, near each command
    assert daemon.log_events("recording")[0]["record_dir"] == str(records)
