"""``[health] record_dir`` in the running daemon (issue 12): the simulated cell serves targets over Zenoh and
every settled target becomes a row of the day's CSV, readable by ``fit``."""

from __future__ import annotations

import datetime as dt
import time
import urllib.request
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)
from helpers.wall_clock import WallShift

from nanodrift.calibration.dataset import Dataset, read_csv
from nanodrift.config import DEFAULT_MODEL_PATH
from nanodrift.model.model import load_model
from nanodrift.service.recorder import TIMESYNC_FLAG, file_name

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
            ready = client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
            cell_t_first = min(s["t"] for s in ready["sensors"].values())
            commands = []
            for i, x in enumerate(TARGETS_UM):
                ok, command = client.query({"x_um": x, "id": f"rec-{i}"})
                assert ok, command
                commands.append(command)
                # the stage holds the target: one settled row (settle_s 1 s, window 0.5 s of cell time)
                wait_until(lambda n=i + 1: (d := recorded(records)) is not None and len(d) >= n, 30,
                           f"{i + 1} recorded rows")
            cell_t_last = max(s["t"] for s in client.status()["sensors"].values())
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
    data = recorded(records)
    assert data is not None and len(data) == len(TARGETS_UM)
    model = load_model(DEFAULT_MODEL_PATH)
    assert set(model.channels) < set(data.channel_names) == {"T1", "T2", "T3", "T4"}  # every polled channel
    np.testing.assert_array_equal(data.extra["valid"], 1)  # every channel ok through each window
    np.testing.assert_allclose(data.extra["target_um"], TARGETS_UM)
    np.testing.assert_allclose(data.q, [c["q_um"] for c in commands])
    assert np.all(np.abs(data.x - data.extra["target_um"]) < 0.5)  # measured by the interferometer, compensated
    np.testing.assert_allclose(data.extra["residual_um"], data.x - data.extra["target_um"], atol=1e-12)
    # labelled with the simulated lab's clock (speed 10: issue 19.6), between the first and last readings (a row's
    # label is taken just after the reading that closed its window: up to a poll later than the status saw)
    assert np.all((data.t >= cell_t_first) & (data.t <= cell_t_last + 1.0)) and np.all(np.diff(data.t) > 0)
    assert daemon.log_events("recording")[0]["record_dir"] == str(records)


# --- the wall clock only labels (issue 16): steps of the daemon's wall clock, every polled channel ---------


def real_utc_day() -> dt.date:
    return dt.datetime.now(dt.UTC).date()


def rows_in(path: Path) -> int:
    try:
        return len(read_csv(path))
    except (OSError, ValueError):  # not there yet, or only its header
        return 0


def test_wall_clock_steps_neither_delete_records_nor_stall_them_and_rows_keep_every_polled_channel(
        tmp_path: Path) -> None:
    """+120 days, then -1 h, on the daemon's wall clock only (its monotonic clock runs on): retention
    decides on the daemon's own clock, rows keep coming (a label that went back opens ``.2.csv``), and
    every row holds every polled temperature channel, the model's (T1, T2) and T4, which it does not use."""
    records = tmp_path / "records"
    records.mkdir()
    today = real_utc_day()
    recent = [records / file_name(today - dt.timedelta(days=k)) for k in range(31)]
    header = "t_s,x_um,q_um,target_um,residual_um,T1,T2\n"
    for path in recent:
        path.write_text(header)
    expired = records / file_name(today - dt.timedelta(days=91))  # beyond keep_days of the real today
    expired.write_text(header)

    shift = WallShift(tmp_path / "wall_shift")
    plugins = install_file_plugin(tmp_path / "plugins")
    model_path = tmp_path / "model.json"
    model = write_test_model(model_path)
    sensors = SensorFile(tmp_path / "sensors.json", {**TEMPS, "T4": 23.456, "interferometer": 0.0})
    port = free_port()
    extra = ('[health]\nsettle_s = 0.1\nwindow_s = 0.2\nrecord_dir = "records"\nrecord_keep_days = 90\n'
             f'[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "file"\npath = "{sensors.path}"\n'
             "interval_s = 0.05\nmax_age_s = 1.0\n")
    config = tmp_path / "nanodrift.toml"
    config.write_text(file_sensor_config(tmp_path, cell="recstep", port=port, model_path=model_path,
                                         sensor_file=sensors.path, channels=("T1", "T2", "T4"), extra=extra))
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log", [plugins, WallShift.SITE_DIR],
                    env=shift.env())
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "recstep")
        try:
            client.wait_ready(["T1", "T2", "T4", "interferometer"])

            def settle(x_um: float, target_id: str, path: Path) -> dict[str, Any]:
                """Serve ``x_um`` with the stage 0.1 um beyond it; until its row is in ``path``."""
                before = rows_in(path), client.status()["health"]["n"]
                sensors.set(interferometer=x_um + 0.1)
                ok, command = client.query({"x_um": x_um, "id": target_id})
                assert ok, command
                wait_until(lambda: rows_in(path) > before[0], 15, f"the row of {target_id} in {path.name}")
                assert client.status()["health"]["n"] > before[1]  # the health unit has its residual too
                return command

            # +120 days, landing at noon (UTC) of that day: the -1 h step below stays within it
            future = dt.datetime.combine(today + dt.timedelta(days=120), dt.time(12), dt.UTC)
            shift.step(future.timestamp() - time.time())
            future_file = records / file_name(future.date())
            first = [settle(x, f"fwd-{i}", future_file) for i, x in enumerate((80.0, 240.0, 400.0))]
            assert all(abs(c["t"] - future.timestamp()) < 600 for c in first)  # the labels did step
            assert all(p.exists() for p in recent)  # retention decides on the daemon's clock: nothing to expire
            assert not expired.exists()  # ... and still expires what is old by it

            shift.step(-3600.0)  # NTP steps the clock back an hour
            second_file = records / file_name(future.date(), 2)
            for i, x in enumerate((160.0, 320.0)):
                settle(x, f"back-{i}", second_file)
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
    assert all(p.exists() for p in recent)
    assert daemon.log_events("record_failed") == []
    for path, n in ((future_file, 3), (second_file, 2)):
        data = read_csv(path)
        assert len(data) == n
        assert set(data.channel_names) == {"T1", "T2", "T4"}  # every polled channel, not only the model's
        assert set(model.channels) < set(data.channel_names)
        np.testing.assert_allclose(data.channels["T4"], 23.456)
        np.testing.assert_allclose(data.channels["T1"], TEMPS["T1"])
        np.testing.assert_allclose(data.extra["residual_um"], 0.1, atol=1e-9)
        np.testing.assert_array_equal(data.extra["valid"], 1)


def test_a_daemon_started_on_a_clock_months_ahead_deletes_no_record(tmp_path: Path) -> None:
    """Issue 26.7: a lab PC whose RTC is 120 days ahead and NTP not synchronised yet starts the daemon (its
    wall clock, and so the daemon's own clock, 120 days ahead from the start). Four day files, kept 90
    days: none is deleted by that clock, the row goes on being written, and the hold is said once."""
    if TIMESYNC_FLAG.exists():
        pytest.skip(f"this host says its clock is synchronised ({TIMESYNC_FLAG}): the daemon rightly believes a "
                    "clock the test shifts; the unit test of RetentionClock covers the flag")
    records = tmp_path / "records"
    records.mkdir()
    today = real_utc_day()
    header = "t_s,x_um,q_um,target_um,residual_um,valid,T1,T2\n"
    days = [records / file_name(today - dt.timedelta(days=k)) for k in range(4)]
    for path in days:
        path.write_text(header)
    shift = WallShift(tmp_path / "wall_shift")
    shift.step(120 * 86400.0)  # before the daemon starts: its clock is wrong from its first reading
    plugins = install_file_plugin(tmp_path / "plugins")
    model_path = tmp_path / "model.json"
    write_test_model(model_path)
    sensors = SensorFile(tmp_path / "sensors.json", {**TEMPS, "interferometer": 0.0})
    port = free_port()
    extra = ('[health]\nsettle_s = 0.1\nwindow_s = 0.2\nrecord_dir = "records"\nrecord_keep_days = 90\n'
             f'[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "file"\npath = "{sensors.path}"\n'
             "interval_s = 0.05\nmax_age_s = 1.0\n")
    config = tmp_path / "nanodrift.toml"
    config.write_text(file_sensor_config(tmp_path, cell="wrongclock", port=port, model_path=model_path,
                                         sensor_file=sensors.path, extra=extra))
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log", [plugins, WallShift.SITE_DIR],
                    env=shift.env())
    future_files: list[Path] = []
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "wrongclock")
        try:
            client.wait_ready(["T1", "T2", "interferometer"])
            sensors.set(interferometer=240.1)
            ok, command = client.query({"x_um": 240.0, "id": "ahead"})
            assert ok, command
            assert command["t"] > time.time() + 119 * 86400.0  # the daemon's clock is the shifted one
            future_files = wait_until(lambda: [p for p in records.glob("records-*.csv") if p not in days
                                               and rows_in(p) >= 1], 15, "the row in the (future) day's file")
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
    assert all(p.exists() for p in days), sorted(p.name for p in records.iterdir())
    assert daemon.log_events("record_expired") == []
    held = daemon.log_events("record_retention_held")
    assert len(held) == 1 and held[0]["newest_file_day"] == today.isoformat(), held
    assert "not known synchronised" in held[0]["reason"]
    # the row went on being written, labelled by the (wrong) clock: a later fit can still use it
    assert future_files and all(p.name >= file_name(today + dt.timedelta(days=120)) for p in future_files)


def test_held_targets_the_position_poll_cannot_fill_are_counted_and_said_once(tmp_path: Path) -> None:
    """Issue 26.9: an interferometer polled every second and a 0.05 s window: most held targets have no
    reading inside their window, so no residual and no row. They were dropped silently (a fast simulated
    clock recorded nothing for a week with health ok); now each is counted in the health document and the
    metrics, and the first is logged with the reason."""
    plugins = install_file_plugin(tmp_path / "plugins")
    model_path = tmp_path / "model.json"
    write_test_model(model_path)
    temperatures = SensorFile(tmp_path / "sensors.json", dict(TEMPS))
    position = SensorFile(tmp_path / "position.json", {"interferometer": 0.0})  # its own group: its own poll
    port, metrics_port = free_port(), free_port()
    extra = (f'[metrics]\nlisten = "127.0.0.1:{metrics_port}"\n'
             '[health]\nsettle_s = 0.05\nwindow_s = 0.05\nrecord_dir = "records"\n'
             f'[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "file"\npath = "{position.path}"\n'
             "interval_s = 1.0\nmax_age_s = 5.0\n")
    config = tmp_path / "nanodrift.toml"
    config.write_text(file_sensor_config(tmp_path, cell="slowpos", port=port, model_path=model_path,
                                         sensor_file=temperatures.path, extra=extra))
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log", [plugins])
    targets = (80.0, 240.0, 400.0, 160.0)
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "slowpos")
        try:
            client.wait_ready(["T1", "T2", "interferometer"])

            def resolved() -> int:
                health = client.status()["health"]
                return int(health["n"]) + int(health["holds_unrecorded"])

            for i, x in enumerate(targets):
                position.set(interferometer=x + 0.1)
                ok, command = client.query({"x_um": x, "id": i})
                assert ok, command
                wait_until(lambda n=i + 1: resolved() >= n, 10, f"target {i}'s hold to end, recorded or not")
            health = client.status()["health"]
            with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=5) as page:
                metrics = page.read().decode()
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
    unrecorded = health["holds_unrecorded"]
    assert unrecorded >= 1 and unrecorded + health["n"] == len(targets), health
    assert f'nanodrift_health_holds_unrecorded_total{{cell="slowpos"}} {float(unrecorded)}' in metrics, metrics
    said = daemon.log_events("hold_unrecorded")
    assert len(said) == 1, said  # once, however many follow
    assert "interval_s = 1 s" in said[0]["reason"] and "window_s" in said[0]["reason"], said
    assert said[0]["reading_gap_s"] == pytest.approx(1.0, abs=0.5)  # what the poll achieved, on the cell clock
    rows = sum(rows_in(p) for p in (tmp_path / "records").glob("records-*.csv"))
    assert rows == health["n"]  # every hold with a residual is a row; the others are the counted ones
