"""A lying interferometer is not believed (issue 16, problem 10), end to end.

``nanodrift run`` in its own process on the harness's ``file`` plugin (the test writes what each
channel reads), a real Zenoh client over 127.0.0.1. A position reading of 1e200 µm is a ``fault`` in
``status`` and gives no health residual, no record row and no correction; a position value frozen for
longer than ``frozen_after_s`` makes the channel ``stale``, and the health advice names the sensor
instead of blaming the cell. Each "nothing was taken" is checked behind a witness: a position reading
stamped after the held target's window (had the window counted, it would be closed and counted).
"""

from __future__ import annotations

import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    TEMPS,
    HealthCell,
    SensorFile,
    file_sensor_config,
    install_file_plugin,
    wait_until,
    write_test_model,
)

from nanodrift.calibration.dataset import Dataset, read_csv
from nanodrift.model.model import save_model

SETTLE_S, WINDOW_S = 0.1, 0.2


@contextmanager
def live(sensors: SensorFile, ifm_um: float) -> Iterator[None]:
    """The interferometer alive at ``ifm_um``: its last digits change on every write (noise of 1e-9 um)."""
    stop = threading.Event()

    def jitter() -> None:
        k = 0
        while not stop.wait(0.02):
            k += 1
            sensors.set(ifm=ifm_um + 1e-9 * (k % 7))

    thread = threading.Thread(target=jitter, daemon=True)
    sensors.set(ifm=ifm_um)
    thread.start()
    try:
        yield
    finally:
        stop.set()
        thread.join(5)


def start(tmp_path: Path, cell: str, ifm_keys: str, ifm_um: float,
          rmse_um: float | None = None) -> tuple[HealthCell, SensorFile]:
    """T1, T2 and the position sensor ``ifm`` on one file; health on, bias adaptation on, records on;
    ``rmse_um``: the model's σ (else it has none)."""
    plugins = install_file_plugin(tmp_path / "plugins")
    model = tmp_path / "model.json"
    made = write_test_model(model)
    if rmse_um is not None:
        made.fit["rmse_um"] = rmse_um
        save_model(made, model)
    sensors = SensorFile(tmp_path / "sensors.json", {**TEMPS, "ifm": ifm_um})
    extra = (f'[health]\nsettle_s = {SETTLE_S}\nwindow_s = {WINDOW_S}\nrecord_dir = "records"\n'
             '[adapt]\nmode = "bias"\ntau_s = 1.0\nmax_um = 1.0\n'
             f'[[sensors]]\nname = "ifm"\nrole = "position"\nkind = "file"\npath = "{sensors.path}"\n'
             f"interval_s = 0.05\nmax_age_s = 1.0\n{ifm_keys}")
    config = file_sensor_config(tmp_path, cell=cell, port=0, model_path=model, sensor_file=sensors.path,
                                extra=extra).replace("127.0.0.1:0", "127.0.0.1:@PORT@")
    return HealthCell(tmp_path, cell, config, plugins), sensors


def ifm_status(cell: HealthCell) -> dict[str, Any]:
    assert cell.client is not None
    return cell.client.status()["sensors"]["ifm"]


def read_after(cell: HealthCell, command: dict[str, Any]) -> None:
    """Until the daemon has a position reading stamped after the command's settle window."""
    client = cell.client
    assert client is not None
    end = command["t"] + SETTLE_S + WINDOW_S + 0.1
    wait_until(lambda: (p := client.telemetry.get("position")) is not None and p["t"] > end, 10,
               "a position reading stamped after the window")


def recorded(folder: Path) -> Dataset | None:
    files = sorted(folder.glob("records-*.csv"))
    if len(files) != 1:
        return None
    try:
        return read_csv(files[0])
    except ValueError:  # the header is there, no row yet
        return None


def test_a_position_reading_of_1e200_is_a_fault_and_feeds_neither_health_nor_records(tmp_path: Path) -> None:
    cell, sensors = start(tmp_path, "lie200", "frozen_after_s = 0\n", 100.3)  # range only
    records = tmp_path / "records"
    try:
        client = cell.client
        assert client is not None
        client.wait_ready(["T1", "T2", "ifm"])
        cell.settle(100.0, "good")  # the stage 0.3 um beyond the target: one residual, one row
        health = cell.health()
        assert health["n"] == 1 and health["residual_mean_nm"] == pytest.approx(300.0, abs=1e-6)
        correction = health["correction_um"]
        assert correction == pytest.approx(-0.3, abs=0.01)
        wait_until(lambda: (d := recorded(records)) is not None and len(d) == 1, 10, "the first record row")

        sensors.set(ifm=1e200)
        wait_until(lambda: ifm_status(cell)["state"] == "fault", 10, "ifm faulted in status")
        entry = ifm_status(cell)
        # the default range: the workspace [0, 500] um with 10 % of the stroke on each side
        assert entry["reason"] == "reading 1e+200 um outside the valid range [-50, 550] um (valid_min/valid_max)"
        assert entry["value"] == 100.3  # the last believed value, never the lie
        ok, lied = client.query({"x_um": 300.0, "id": "lied"})
        assert ok and lied["correction_um"] == correction  # temperatures are fine: served, uncorrected anew
        read_after(cell, lied)
        assert client.telemetry["position"]["state"] == "fault"
        health = cell.health()
        assert (health["n"], health["correction_um"]) == (1, correction)
        assert health["advice"].startswith(
            "position sensor 'ifm' is faulted: reading 1e+200 um outside the valid range [-50, 550] um")
        assert "check the interferometer, not the cell" in health["advice"]

        sensors.set(ifm=400.0)  # believable again: the next held target counts, and is the second row
        wait_until(lambda: ifm_status(cell)["state"] == "ok", 10, "ifm ok again")
        cell.settle(400.0, "after")
        assert cell.health()["n"] == 2
        data = wait_until(lambda: (d := recorded(records)) is not None and len(d) >= 2 and d, 10, "the second row")
        assert len(data) == 2 and list(data.extra["target_um"]) == [100.0, 400.0]  # none for the lied target
        assert "position sensor" not in (cell.health()["advice"] or "")
    finally:
        assert cell.close() == 0


def test_a_frozen_position_reading_goes_stale_and_the_advice_names_the_sensor(tmp_path: Path) -> None:
    cell, sensors = start(tmp_path, "frozen", "frozen_after_s = 1.0\n", 300.0)
    try:
        client = cell.client
        assert client is not None
        client.wait_ready(["T1", "T2"])
        # the file says 300.0 every poll: bit-identical for longer than frozen_after_s (1 s) -> stale
        wait_until(lambda: ifm_status(cell)["state"] == "stale", 10, "ifm stale in status")
        reason = ifm_status(cell)["reason"]
        assert reason.startswith("value frozen at 300 um for ") and reason.endswith(" s (frozen_after_s 1)"), reason

        # a target far from where the frozen value says the stage is: believed, that would be a -200 um
        # residual and the correction at its clamp; it must feed nothing
        ok, command = client.query({"x_um": 100.0, "id": "frozen"})
        assert ok, command
        read_after(cell, command)
        health = cell.health()
        assert (health["n"], health["correction_um"]) == (0, 0.0)
        assert health["advice"].startswith("position sensor 'ifm' is stale: value frozen at 300 um for "), health
        assert "check the interferometer, not the cell" in health["advice"]

        with live(sensors, 100.3):  # it moves: believed again, and the next held target counts
            wait_until(lambda: ifm_status(cell)["state"] == "ok", 10, "ifm ok once the value moves")
            cell.settle(100.0, "moving")
            health = cell.health()
        assert health["n"] == 1 and health["residual_mean_nm"] == pytest.approx(300.0, abs=1e-3)
        assert "position sensor" not in (health["advice"] or "")
    finally:
        assert cell.close() == 0


def test_a_residual_of_1e200_inside_a_widened_range_is_refused_and_the_adapted_sigma_recovers(
        tmp_path: Path) -> None:
    """Issue 26.9: an operator widened the interferometer's range (valid_max = 1e300) and it read 1e200 once:
    the settled residual's square overflowed, and ``q_sigma_adapted_um`` stayed NaN for good. Now the
    residual is refused (counted in ``residuals_rejected``), and the next good hold serves finite σ again."""
    cell, sensors = start(tmp_path, "lie200w", "frozen_after_s = 0\nvalid_min = -1e300\nvalid_max = 1e300\n", 100.3,
                          rmse_um=0.02)
    try:
        client = cell.client
        assert client is not None
        client.wait_ready(["T1", "T2", "ifm"])
        cell.settle(100.0, "good")
        sensors.set(ifm=1e200)  # inside the widened range: an ok reading
        ok, lied = client.query({"x_um": 300.0, "id": "lied"})
        assert ok, lied

        def held() -> int:
            health = cell.health()
            return int(health["n"]) + int(health.get("residuals_rejected", 0))

        wait_until(lambda: held() >= 2, 10, "the lied hold's window to close")
        health = cell.health()
        assert (health["n"], health["residuals_rejected"]) == (1, 1), health
        assert health["residual_mean_nm"] == pytest.approx(300.0, abs=1e-6)  # the statistics never saw it
        sensors.set(ifm=400.1)
        cell.settle(400.0, "after")
        ok, command = client.query({"x_um": 240.0, "id": "next"})
        assert ok, command
        sigma = command["q_sigma_adapted_um"]
        assert 0.0 < sigma < 1.0, command  # finite: the 0.1-0.3 µm residuals it learnt from, not NaN
        assert abs(command["correction_um"]) <= 1.0
    finally:
        assert cell.close() == 0
