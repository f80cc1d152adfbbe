"""A two-axis cell served over real Zenoh (127.0.0.1), driving a real Modbus output module with two registers.

The daemon is a separate process (``nanodrift run``); the module is pymodbus' TCP server with one
holding register per axis; the temperatures come from the test-only ``file`` plugin. The registers are
read back from the module itself: what the stage gets is what was published, every axis of it, and a
target refused on one axis leaves both registers as they were.
"""

from __future__ import annotations

import csv
import json
import re
import signal
import subprocess
import urllib.request
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.cell_helpers import ThreadedModbus, expected_cell_q, write_cell_model
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    free_port,
    install_file_plugin,
    run_cli,
    wait_until,
    write_test_model,
)

from nanodrift.calibration.dataset import read_csv

SCALE_V = 0.001  # volts per count of the module's outputs
ADDRESSES = {"x": 10, "y": 11}


def cell_config(root: Path, *, port: int, modbus_port: int, model: Path, sensors: Path, metrics_port: int,
                extra: str = "") -> str:
    axes = "".join(
        f'[[axes]]\nname = "{axis}"\nmin_um = 0.0\nmax_um = {max_um}\n[axes.actuator]\nkind = "modbus"\nhub = "dac"\n'
        f"address = {address}\nscale = {SCALE_V}\nvolts_per_um = 0.02\nv_min = -2.0\nv_max = 12.0\n\n"
        for (axis, address), max_um in zip(ADDRESSES.items(), (480.0, 400.0), strict=True))
    channels = "".join(f'[[sensors]]\nname = "{ch}"\nkind = "file"\npath = "{sensors}"\ninterval_s = 0.05\n'
                       "max_age_s = 2.0\ntimeout_s = 0.5\n\n" for ch in ("T1", "T2"))
    return (f'cell = "xy"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            f'[metrics]\nlisten = "127.0.0.1:{metrics_port}"\n[model]\npath = "{model}"\n\n{axes}'
            f'[[hubs]]\nname = "dac"\nhost = "127.0.0.1"\nport = {modbus_port}\n'
            f"timeout_s = 0.5\n\n{channels}{extra}")


class XYCell:
    def __init__(self, root: Path, extra: str = "", values: dict[str, float] | None = None,
                 rmse_um: float | None = None) -> None:
        self.module = ThreadedModbus().start()
        self.port = free_port()
        self.metrics_port = free_port()
        plugins = install_file_plugin(root / "plugins")
        self.model = write_cell_model(root / "model.json", ("x", "y"), rmse_um=rmse_um)
        self.sensors = SensorFile(root / "sensors.json", {**TEMPS, **(values or {})})
        config = root / "xy.toml"
        config.write_text(cell_config(root, port=self.port, modbus_port=self.module.port, model=root / "model.json",
                                      sensors=self.sensors.path, metrics_port=self.metrics_port, extra=extra))
        self.daemon = Daemon(["--config", str(config)], root / "daemon.log", [plugins])
        self.daemon.wait_log("serving", timeout=30)
        self.client = Client(self.port, "xy")
        self.client.wait_alive()
        self.client.wait_ready(("T1", "T2"))

    def volts(self, axis: str) -> float:
        return self.module.registers(ADDRESSES[axis])[0] * SCALE_V

    def wait_registers(self, voltage_v: dict[str, float]) -> None:
        """Until every axis' register holds the count of its published voltage."""
        def held() -> bool:
            return all(abs(self.volts(axis) - v) <= SCALE_V / 2 for axis, v in voltage_v.items())

        wait_until(held, 5, f"registers at {voltage_v} V")

    def close(self) -> None:
        self.client.close()
        self.daemon.stop()
        self.module.stop()


@pytest.fixture(scope="module")
def serving(tmp_path_factory: pytest.TempPathFactory) -> Iterator[XYCell]:
    """One daemon for the tests that only send targets and read (no reload, no edit): each judges what changed
    since it began (commands, writes, counters), so their order does not matter."""
    served = XYCell(tmp_path_factory.mktemp("xy"))
    yield served
    served.close()


@pytest.fixture
def cell(tmp_path: Path) -> Iterator[XYCell]:
    """A daemon of the test's own, for a test that edits its config."""
    served = XYCell(tmp_path)
    yield served
    served.close()


def test_a_two_axis_target_is_one_command_and_both_registers_hold_its_voltages(serving: XYCell) -> None:
    cell = serving
    ok, command = cell.client.query({"x_um": 240, "y_um": 100, "id": 7})
    assert ok, command
    q = expected_cell_q({"x": 240.0, "y": 100.0}, TEMPS)
    assert list(command) == ["id", "x_um", "y_um", "q_um", "voltage_v", "q_sigma_um", "temperatures_c", "model", "t",
                             "extrapolating"]
    assert command["id"] == 7 and command["x_um"] == 240 and command["y_um"] == 100
    assert command["model"] == cell.model.id and command["extrapolating"] == []
    assert command["q_um"] == pytest.approx(q, abs=1e-9)
    assert command["voltage_v"] == pytest.approx({a: 0.02 * q[a] for a in q}, abs=1e-9)
    assert set(command["q_sigma_um"]) == {"x", "y"}
    published = cell.client.wait(lambda: [c for c in cell.client.commands if c.get("id") == 7], 5, "command 7")
    assert published == [command]  # published once, every axis in it
    cell.wait_registers(command["voltage_v"])  # what the module holds is what was published, to the count

    def verified() -> dict | None:  # the daemon claims a voltage once its readback confirmed it, just after the write
        doc = cell.client.status()
        last = {a: doc["axes"][a]["actuator"]["last_voltage_v"] for a in ("x", "y")}
        return doc if all(v is not None and abs(v - command["voltage_v"][a]) <= SCALE_V for a, v in last.items()) \
            else None

    status = wait_until(verified, 5, "both axes' written voltages verified")
    assert set(status["axes"]) == {"x", "y"}
    assert status["axes"]["y"]["max_um"] == 400.0 and status["axes"]["y"]["actuator"]["state"] == "ok"
    assert status["axes"]["x"]["actuator"]["last_voltage_v"] == pytest.approx(command["voltage_v"]["x"],
                                                                                abs=SCALE_V)
    with urllib.request.urlopen(f"http://127.0.0.1:{cell.metrics_port}/metrics", timeout=5) as page:
        metrics = page.read().decode()
    assert 'nanodrift_actuator_ok{axis="y",cell="xy",kind="modbus"} 1.0' in metrics, metrics
    assert 'nanodrift_actuator_state{axis="x",cell="xy",kind="modbus",state="ok"} 1.0' in metrics
    volts = re.search(r'nanodrift_actuator_voltage_volts\{axis="y",cell="xy"\} (\S+)', metrics)
    assert volts is not None and float(volts[1]) == pytest.approx(command["voltage_v"]["y"], abs=SCALE_V)


def test_a_partial_or_out_of_workspace_target_is_refused_whole_and_no_register_is_written(serving: XYCell) -> None:
    cell = serving
    errors_before = cell.client.status()["counters"]["errors"]
    published_before = len(cell.client.commands)
    ok, first = cell.client.query({"x_um": 100, "y_um": 50, "id": 1})
    assert ok, first
    cell.wait_registers(first["voltage_v"])
    writes_before = {a: len(cell.module.written(address)) for a, address in ADDRESSES.items()}

    ok, error = cell.client.query({"x_um": 1, "id": 2})
    assert not ok and error["kind"] == "bad_payload" and "'y_um'" in error["error"], error
    ok, error = cell.client.query({"x_um": 1, "y_um": 2, "z_um": 3, "id": 3})
    assert not ok and error["kind"] == "bad_payload" and "'z'" in error["error"], error
    ok, error = cell.client.query({"x_um": 300, "y_um": 450, "id": 4})  # y's workspace ends at 400
    assert not ok and error["kind"] == "out_of_workspace", error
    assert "axis y" in error["error"] and "x_um" not in error["error"], error

    # a later target is served: the refusals above were answered and passed; nothing reached the module
    ok, after = cell.client.query({"x_um": 100, "y_um": 50, "id": 5})
    assert ok, after
    published_ids = [c["id"] for c in cell.client.commands[published_before:]]
    assert 2 not in published_ids and 3 not in published_ids and 4 not in published_ids
    writes = {a: cell.module.written(address)[writes_before[a]:] for a, address in ADDRESSES.items()}
    expected = {a: [round(first["voltage_v"][a] / SCALE_V)] for a in ADDRESSES}
    assert all(w == [expected[a]] * len(w) for a, w in writes.items()), writes  # only command 5's (same) values
    errors = cell.client.status()["counters"]["errors"]
    added = {kind: n - errors_before.get(kind, 0) for kind, n in errors.items() if n != errors_before.get(kind, 0)}
    assert added == {"bad_payload": 2, "out_of_workspace": 1}, (errors_before, errors)


def cli(cell: XYCell, *args: str) -> subprocess.CompletedProcess[str]:
    return run_cli(*args, "-e", f"tcp/127.0.0.1:{cell.port}", "--cell", "xy")


def test_the_cli_sends_one_point_per_target_in_the_cells_axis_order_and_status_shows_each_axis(
        serving: XYCell) -> None:
    cell = serving
    result = cli(cell, "target", "240,100", "0,0", "--json")
    assert result.returncode == 0, result.stderr
    answers = [json.loads(line) for line in result.stdout.splitlines()]
    assert [(a["x_um"], a["y_um"]) for a in answers] == [(240.0, 100.0), (0.0, 0.0)]
    assert answers[0]["q_um"] == pytest.approx(expected_cell_q({"x": 240.0, "y": 100.0}, TEMPS), abs=1e-9)

    result = cli(cell, "target", "100,50", "300,450")
    assert result.returncode == 1
    assert result.stdout.startswith("x 100.0000 y 50.0000 µm -> q x ") and cell.model.id in result.stdout
    # σ per axis (this hand-made model has no covariance nor residual RMS: unknown) and °C, as one axis shows them
    assert re.search(r"σ x (\d+\.\d{4}|unknown) y (\d+\.\d{4}|unknown) µm; T1=21\.800 °C", result.stdout), result.stdout
    assert "300,450 µm refused: y_um 450 outside axis y's workspace [0, 400] µm" in result.stderr, result.stderr
    result = cli(cell, "target", "100")  # one number in an XY cell: refused by the daemon, naming y
    assert result.returncode == 1 and "'y_um'" in result.stderr, result.stderr
    result = cli(cell, "target", "1,2,3")
    assert result.returncode == 2 and "cell xy has axes x, y" in result.stderr, result.stderr

    cell.wait_registers({"x": 0.02 * expected_cell_q({"x": 100.0, "y": 50.0}, TEMPS)["x"]})
    result = cli(cell, "status")
    assert result.returncode == 0, result.stderr
    assert "x:modbus:ok y:modbus:ok" in result.stdout, result.stdout
    assert "xy axis y: [0, 400] µm, modbus ok at " in result.stdout, result.stdout


def test_a_reload_keeps_the_axes_and_carries_the_goal_to_the_reopened_outputs(cell: XYCell, tmp_path: Path) -> None:
    ok, command = cell.client.query({"x_um": 200, "y_um": 150, "id": 1})
    assert ok, command
    cell.wait_registers(command["voltage_v"])
    config = tmp_path / "xy.toml"
    good = config.read_text()

    # an edit that adds a z axis is refused whole (a restart is needed): the daemon keeps serving x and y
    z_axis = '[[axes]]\nname = "z"\n[axes.actuator]\nkind = "zenoh"\n\n'
    config.write_text(good.replace("[[hubs]]", z_axis + "[[hubs]]", 1))
    cell.daemon.signal(signal.SIGHUP)
    refused = cell.daemon.wait_log("reload_refused")
    assert any("the edited config has axes x, y, z, the daemon runs axes x, y: a reload never adds or removes axes"
               in p for p in refused["problems"]), refused
    # a one-axis model for this cell is refused with both sides named
    write_test_model(tmp_path / "one_axis.json")
    config.write_text(good.replace(str(tmp_path / "model.json"), str(tmp_path / "one_axis.json")))
    cell.daemon.signal(signal.SIGHUP)
    refused = cell.daemon.wait_log("reload_refused", count=2)
    assert any("serves axes x (one axis), the cell has axes x, y" in p for p in refused["problems"]), refused

    # a valid edit of y's output (another v_max) reopens the outputs: the goal is written to them again
    writes_before = len(cell.module.written(ADDRESSES["y"]))
    config.write_text(good.replace("v_max = 12.0", "v_max = 11.0"))
    cell.daemon.signal(signal.SIGHUP)
    applied = cell.daemon.wait_log("reload_applied")
    assert applied["drivers_restarted"] is True
    wait_until(lambda: len(cell.module.written(ADDRESSES["y"])) > writes_before, 5, "the goal rewritten to y")
    cell.wait_registers(command["voltage_v"])
    ok, after = cell.client.query({"x_um": 200, "y_um": 150, "id": 2})
    assert ok and after["q_um"] == pytest.approx(command["q_um"], abs=1e-9)


def test_each_axis_has_its_health_and_its_own_bias_correction(tmp_path: Path) -> None:
    sensor_file = tmp_path / "sensors.json"
    positions = "".join(f'[[sensors]]\nname = "ifm_{axis}"\nkind = "file"\npath = "{sensor_file}"\n'
                        f'role = "position"\naxis = "{axis}"\ninterval_s = 0.05\nmax_age_s = 2.0\n\n'
                        for axis in ("x", "y"))
    extra = positions + (f'[health]\nsettle_s = 0.05\nwindow_s = 0.3\nrecord_dir = "{tmp_path / "records"}"\n'
                         '[adapt]\nmode = "bias"\ntau_s = 1.0\nmax_um = 1.0\n')
    # the stage lands 0.3 um over the target on x, 0.2 um under it on y
    cell = XYCell(tmp_path, extra, {"ifm_x": 100.3, "ifm_y": 49.8}, rmse_um=0.02)
    try:
        ok, first = cell.client.query({"x_um": 100, "y_um": 50, "id": 1})
        assert ok and first["correction_um"] == {"x": 0.0, "y": 0.0}, first
        # nothing learnt yet: the model's own σ
        assert first["q_sigma_adapted_um"] == first["q_sigma_um"] == {"x": 0.02, "y": 0.02}, first

        def settled() -> dict[str, object] | None:
            health = cell.client.status()["health"]
            return health if all(health["axes"][a]["n"] >= 1 for a in ("x", "y")) else None

        health = wait_until(settled, 10, "a settled residual on both axes")
        assert health["axes"]["x"]["residual_mean_nm"] == pytest.approx(300.0, abs=1.0), health
        assert health["axes"]["y"]["residual_mean_nm"] == pytest.approx(-200.0, abs=1.0), health
        ok, second = cell.client.query({"x_um": 100, "y_um": 50, "id": 2})
        assert ok, second
        correction = second["correction_um"]
        assert correction["x"] < 0 < correction["y"], correction  # each axis pushed against its own residual
        # each axis' σ is what its own tracker leaves: the 0.3 (0.2) µm its one residual showed (tau_s 1 s:
        # learnt at once; a model without covariance has no wander to add)
        adapted = second["q_sigma_adapted_um"]
        assert adapted == pytest.approx({"x": 0.3, "y": 0.2}, abs=1e-6), second
        assert second["q_sigma_um"] == first["q_sigma_um"], second  # the model's own σ: same targets, temperatures
        with urllib.request.urlopen(f"http://127.0.0.1:{cell.metrics_port}/metrics", timeout=5) as page:
            metrics = page.read().decode()
        mean = re.search(r'nanodrift_health_residual_mean_meters\{axis="y",cell="xy"\} (\S+)', metrics)
        assert mean is not None and float(mean[1]) == pytest.approx(-200e-9, abs=1e-9), metrics
        assert 'nanodrift_health_state{axis="x",cell="xy",state="unknown"} 1.0' in metrics

        # the recorder: one row per target held on both axes, in the multi-axis CSV contract
        def rows() -> list[dict[str, str]]:
            return [row for path in sorted((tmp_path / "records").glob("records-*.csv"))
                    for row in csv.DictReader(path.open())]

        recorded = wait_until(rows, 10, "a recorded row")
        assert list(recorded[0]) == ["t_s", "x_um", "y_um", "q_x_um", "q_y_um", "target_x_um", "target_y_um",
                                     "residual_x_um", "residual_y_um", "valid", "T1", "T2"]
        assert float(recorded[0]["x_um"]) == pytest.approx(100.3) and float(recorded[0]["y_um"]) == pytest.approx(49.8)
        assert float(recorded[0]["q_y_um"]) == pytest.approx(first["q_um"]["y"], abs=1e-9)
        assert float(recorded[0]["residual_y_um"]) == pytest.approx(-0.2, abs=1e-9)
        data = read_csv(next((tmp_path / "records").glob("records-*.csv")))  # fit reads it back
        assert data.axes == ("x", "y") and list(data.channels) == ["T1", "T2"]
        shown = cli(cell, "status")
        assert "axis y: [0, 400] µm, modbus ok at " in shown.stdout, shown.stdout
        assert ", position ifm_y ok 49.800 µm, health unknown -200 nm" not in shown.stdout  # rms, not the mean
        assert re.search(r"position ifm_y ok 49\.800 µm, health unknown 200 nm", shown.stdout), shown.stdout
        q = expected_cell_q({"x": 100.0, "y": 50.0}, TEMPS)
        assert second["q_um"] == pytest.approx({a: q[a] + correction[a] for a in q}, abs=1e-9)
    finally:
        cell.close()


@pytest.mark.parametrize("target_id", [None, 7], ids=["no ids", "equal ids"])
def test_a_record_row_is_one_command_the_stage_held_on_every_axis(tmp_path: Path, target_id: int | None) -> None:
    """Issue 26.6: targets without ids (or with equal ids) that settle axis by axis. Command A settles on
    x only (y's interferometer lost its beam), B on y only (x's lost it), C on both. The rows were paired
    by the client's id, so one row held A's x and B's y: a place the stage never was, valid, which fit
    trains on. Paired by the daemon's own command number, the file holds C's row and nothing else."""
    records = tmp_path / "records"
    sensor_file = tmp_path / "sensors.json"
    positions = "".join(f'[[sensors]]\nname = "ifm_{axis}"\nkind = "file"\npath = "{sensor_file}"\n'
                        f'role = "position"\naxis = "{axis}"\ninterval_s = 0.05\nmax_age_s = 2.0\n\n'
                        for axis in ("x", "y"))
    extra = positions + f'[health]\nsettle_s = 0.05\nwindow_s = 0.3\nrecord_dir = "{records}"\n'
    cell = XYCell(tmp_path, extra, {"ifm_x": 100.0, "ifm_y": 100.0})

    def move(x_um: float, y_um: float) -> dict[str, object]:
        request: dict[str, object] = {"x_um": x_um, "y_um": y_um}
        if target_id is not None:
            request["id"] = target_id
        ok, command = cell.client.query(request)
        assert ok, command
        return command

    def settled(axis: str, n: int) -> bool:
        return bool(cell.client.status()["health"]["axes"][axis]["n"] == n)

    def rows() -> list[dict[str, str]]:
        return [row for path in sorted(records.glob("records-*.csv")) for row in csv.DictReader(path.open())]

    try:
        cell.sensors.write(fault={"ifm_y": "beam lost"})
        move(100.0, 100.0)  # A
        wait_until(lambda: settled("x", 1), 10, "command A settled on x")
        cell.sensors.write(values={**TEMPS, "ifm_x": 100.0, "ifm_y": 300.0}, fault={"ifm_x": "beam lost"})
        move(300.0, 300.0)  # B
        wait_until(lambda: settled("y", 1), 10, "command B settled on y")
        cell.sensors.write(values={**TEMPS, "ifm_x": 200.0, "ifm_y": 200.0}, fault={})
        move(200.0, 200.0)  # C
        wait_until(lambda: settled("x", 2) and settled("y", 2), 10, "command C settled on both axes")
        wait_until(lambda: len(rows()) >= 1, 10, "C's row")
    finally:
        cell.close()
    recorded = rows()
    assert [(float(r["target_x_um"]), float(r["target_y_um"])) for r in recorded] == [(200.0, 200.0)], recorded
    assert float(recorded[0]["x_um"]) == pytest.approx(200.0) and float(recorded[0]["y_um"]) == pytest.approx(200.0)
    assert float(recorded[0]["valid"]) == 1.0
