"""Issue 10's reload reproductions, against the running daemon (a separate process, real Zenoh client).

(1) An emptied config on SIGHUP must never swap a hardware cell for the simulator or for the
package's default model; the real sensors stay. (3) Non-finite numbers in an edit are refused,
naming the field. (5) A deeply nested model JSON is refused on SIGHUP (logged, counted) and a daemon
started with it runs without a model. The hardware cell is the harness's ``file`` plugin: a
non-simulated driver found by entry point, as a lab's own would be.

Also: a deeply nested *config* on SIGHUP, a reload from the simulated cell to Modbus, and a
reload that fails in an unexpected way are refused, logged as ``reload_refused`` and counted, and
the daemon keeps serving with what it had; check-config says the same as the reload does; and a
model whose served sigma changed under the same id is applied.
"""

from __future__ import annotations

import asyncio
import re
import signal
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    Served,
    expected_q,
    file_sensor_config,
    free_port,
    install_file_plugin,
    run_cli,
    wait_until,
    write_test_model,
)
from helpers.log_capture import captured_logging, json_lines

import nanodrift.service.reload as reload_module
from nanodrift.assembly import build_drivers
from nanodrift.config import DEFAULT_MODEL_PATH, TOO_DEEP, load_config
from nanodrift.model.model import Model, load_model, save_model
from nanodrift.service.runner import Service

NESTED = "[" * 100_000 + "]" * 100_000
SIMULATED_CHANNELS = {"T3", "T4", "interferometer"}


def hup_and_wait(daemon: Daemon, *events: str) -> dict[str, Any]:
    """SIGHUP, then the first new log line among ``events`` (reload_applied / reload_refused)."""
    before = {e: len(daemon.log_events(e)) for e in events}
    daemon.signal(signal.SIGHUP)

    def outcome() -> dict[str, Any] | None:
        daemon.check_alive()
        for event in events:
            lines = daemon.log_events(event)
            if len(lines) > before[event]:
                return lines[before[event]]
        return None

    return wait_until(outcome, 15, f"one of {events} after SIGHUP")


def served_from_file(client: Client, served: Served, target_id: str) -> dict[str, Any]:
    """A target answered with the test model from the file's temperatures (not the simulator's)."""
    ok, command = client.query({"x_um": 240.0, "id": target_id})
    assert ok, command
    assert command["model"] == served.model.id, command
    assert command["temperatures_c"] == served.sensors.doc["values"], command
    return command


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = Served(tmp_path_factory.mktemp("reload_integrity"), "integrity")
    try:
        yield s.start()
    finally:
        assert s.close() == 0


@pytest.fixture
def restore(served: Served) -> Iterator[Served]:
    """Each test edits the running daemon's files; the good config and model are put back after it."""
    model_text = served.model_path.read_text()
    yield served
    served.write_config()
    served.model_path.write_text(model_text)
    line = hup_and_wait(served.daemon, "reload_applied", "reload_refused")
    assert line["event"] == "reload_applied", line
    served.client.wait_ready(["T1", "T2"])


def test_an_emptied_config_never_swaps_the_hardware_for_the_simulator_or_the_default_model(tmp_path: Path) -> None:
    s = Served(tmp_path, "emptied")
    default_model = load_model(DEFAULT_MODEL_PATH).id
    try:
        s.start()
        assert s.model.id != default_model
        s.config_path.write_text("")  # `: > nanodrift.toml`
        line = hup_and_wait(s.daemon, "reload_refused", "reload_applied")
        # an empty file's model is the hardware default path: refused when it is missing (this machine),
        # else for removing every sensor; either way refused, never applied
        if Path("/var/lib/nanodrift/model.json").exists():
            expected = "sensors: the edited config lists no sensors (an emptied file?)"
        else:
            expected = "model.path: /var/lib/nanodrift/model.json: no such model file"
        assert line["event"] == "reload_refused" and line["config"] == str(s.config_path), line
        assert len(line["problems"]) == 1 and line["problems"][0].startswith(expected), line["problems"]
        assert s.client.status()["counters"]["reload_failures"] == 1
        assert s.client.status()["counters"]["reloads"] == 0

        s.sensors.set(T1=21.95)  # the file driver is still polled: the new value shows up

        def t1_updated() -> dict[str, Any] | None:
            status = s.client.status()
            return status if status["sensors"].get("T1", {}).get("value") == 21.95 else None

        status = wait_until(t1_updated, 10, "T1 = 21.95 in status", interval=0.05)
        assert set(status["sensors"]) == {"T1", "T2"}, status["sensors"]  # the real sensors, still
        assert all(v["state"] == "ok" for v in status["sensors"].values()), status["sensors"]
        assert status["model"] is not None and status["model"]["id"] == s.model.id, status["model"]
        command = served_from_file(s.client, s, "after-empty")
        assert command["q_um"] == pytest.approx(expected_q(240.0, s.sensors.doc["values"]), abs=1e-9)
        assert not SIMULATED_CHANNELS & set(s.client.telemetry), s.client.telemetry  # never published
    finally:
        assert s.close() == 0


@pytest.mark.parametrize(
    ("edit", "field"),
    [({"max_age_s": "inf"}, "max_age_s"), ({"interval_s": "inf"}, "interval_s"), ({"max_age_s": "nan"}, "max_age_s")],
    ids=["max_age_s=inf", "interval_s=inf", "max_age_s=nan"],
)
def test_a_non_finite_number_in_an_edit_is_refused_naming_the_field(restore: Served, edit: dict[str, str],
                                                                    field: str) -> None:
    s = restore
    failures = s.client.status()["counters"]["reload_failures"]
    text = s.config_path.read_text()
    key, value = next(iter(edit.items()))
    first = text.index(f"{key} = ")  # the first sensor's line
    end = text.index("\n", first)
    s.config_path.write_text(f"{text[:first]}{key} = {value}{text[end:]}")
    line = hup_and_wait(s.daemon, "reload_refused", "reload_applied")
    assert line["event"] == "reload_refused", line
    # sensors[0].max_age_s, or with the sensor's name: sensors[0] (T1).max_age_s
    assert any(re.match(rf"sensors\[0\]( \(T1\))?\.{field}: ", p) for p in line["problems"]), line["problems"]
    assert s.client.status()["counters"]["reload_failures"] == failures + 1
    served_from_file(s.client, s, f"after-{key}")


def test_a_non_finite_simulation_speed_in_an_edit_is_refused_naming_the_field(tmp_path: Path) -> None:
    port = free_port()
    config = tmp_path / "sim.toml"
    good = (f'cell = "simspeed"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            '[simulation]\nscenario = "steady"\nspeed = 5.0\n')
    config.write_text(good)
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "simspeed")
        try:
            client.wait_ready(["T1", "T2", "T3", "T4"])
            for value in ("inf", "nan", "-inf"):
                config.write_text(good.replace("speed = 5.0", f"speed = {value}"))
                line = hup_and_wait(daemon, "reload_refused", "reload_applied")
                assert line["event"] == "reload_refused", line
                assert any(p.startswith("simulation.speed:") for p in line["problems"]), line["problems"]
            ok, command = client.query({"x_um": 100.0, "id": "still"})
            assert ok, command  # the simulated sensors kept their speed and never faulted
            assert all(v["state"] == "ok" for v in client.status()["sensors"].values())
            assert client.status()["counters"]["reload_failures"] == 3
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0


def test_a_deeply_nested_model_on_sighup_is_refused_logged_and_counted(restore: Served) -> None:
    s = restore
    failures = s.client.status()["counters"]["reload_failures"]
    s.model_path.write_text(NESTED)
    line = hup_and_wait(s.daemon, "reload_refused", "reload_applied")
    assert line["event"] == "reload_refused", line
    assert any(p.startswith("model.path:") and str(s.model_path) in p for p in line["problems"]), line
    assert s.client.status()["counters"]["reload_failures"] == failures + 1
    served_from_file(s.client, s, "after-nested")  # the daemon keeps serving with what it had
    stderr = s.daemon.log_path.read_text(errors="replace")
    assert "Traceback" not in stderr and "Task exception was never retrieved" not in stderr


def test_run_with_a_deeply_nested_model_starts_without_a_model(tmp_path: Path) -> None:
    s_root = tmp_path
    s_root.joinpath("model.json").write_text(NESTED)
    port = free_port()
    sensors = SensorFile(s_root / "sensors.json", TEMPS)
    config = s_root / "nanodrift.toml"
    config.write_text(file_sensor_config(s_root, cell="nested", port=port, model_path=s_root / "model.json",
                                         sensor_file=sensors.path))
    daemon = Daemon(["--config", str(config)], s_root / "daemon.log", [install_file_plugin(s_root / "plugins")])
    try:
        start = daemon.wait_log("starting", timeout=30)
        assert start["model"] is None and str(s_root / "model.json") in (start["model_problem"] or ""), start
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "nested")
        try:
            status = client.wait_ready(["T1", "T2"])
            assert status["model"] is None and status["model_problem"], status
            ok, error = client.query({"x_um": 240.0, "id": "no-model"})
            assert not ok and error["kind"] == "no_model" and error["id"] == "no-model", error
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0


# --- a simulated cell's daemon ----------------------------------------------------------------------


def sim_config(port: int, cell: str) -> str:
    return (f'cell = "{cell}"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            f'[model]\npath = "{DEFAULT_MODEL_PATH}"\n[simulation]\nscenario = "room"\nspeed = 5.0\n')


@contextmanager
def sim_daemon(root: Path, cell: str) -> Iterator[tuple[Daemon, Client, Path]]:
    """A daemon on the simulated cell (no [[sensors]]: T1..T4 and the interferometer), ready, and a client."""
    port = free_port()
    config = root / "sim.toml"
    config.write_text(sim_config(port, cell))
    daemon = Daemon(["--config", str(config)], root / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, cell)
        try:
            client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
            yield daemon, client, config
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0


def still_simulated(client: Client, target_id: str) -> None:
    """Still the simulated cell with the shipped model, answering a target."""
    status = client.status()
    assert set(status["sensors"]) == {"T1", "T2", "T3", "T4", "interferometer"}, status["sensors"]
    assert status["model"]["id"] == load_model(DEFAULT_MODEL_PATH).id
    ok, command = client.query({"x_um": 240.0, "id": target_id})
    assert ok and command["id"] == target_id, command


def test_a_deeply_nested_config_on_sighup_is_refused_logged_and_counted(tmp_path: Path) -> None:
    with sim_daemon(tmp_path, "deepcfg") as (daemon, client, config):
        config.write_text("x = " + NESTED)
        line = hup_and_wait(daemon, "reload_refused", "reload_applied")
        assert line["event"] == "reload_refused", line
        assert line["config"] == str(config) and line["problems"] == [TOO_DEEP], line
        assert client.status()["counters"]["reload_failures"] == 1
        still_simulated(client, "after-deep-config")
        check = run_cli("check-config", str(config))
        assert check.returncode == 2 and f"error: {config}: {TOO_DEEP}" in check.stderr, check.stderr
    stderr = daemon.log_path.read_text(errors="replace")
    assert "Traceback" not in stderr and "Task exception was never retrieved" not in stderr
    assert not daemon.log_events("uncaught_exception")


def test_a_reload_from_the_simulated_cell_to_modbus_is_refused_restart_needed(tmp_path: Path) -> None:
    with sim_daemon(tmp_path, "simtohw") as (daemon, client, config):
        text = config.read_text()
        hardware = text[:text.index("[simulation]")] + (
            f'[[hubs]]\nname = "adam"\nhost = "127.0.0.1"\nport = {free_port()}\n'
            + "".join(f'[[sensors]]\nname = "T{i + 1}"\nkind = "modbus"\nhub = "adam"\naddress = {i}\nscale = 0.1\n'
                      for i in range(4)))
        config.write_text(hardware)
        line = hup_and_wait(daemon, "reload_refused", "reload_applied")
        assert line["event"] == "reload_refused", line
        assert line["problems"] == [
            "the edited config describes hardware, the daemon runs the simulated cell: a reload never switches "
            "between them (systemctl restart nanodrift)"], line["problems"]
        counters = client.status()["counters"]
        assert (counters["reload_failures"], counters["reloads"]) == (1, 0), counters
        still_simulated(client, "after-modbus")


def test_check_config_and_the_reload_agree_on_a_sensorless_file(restore: Served) -> None:
    """The file an emptied install leaves (its model still there): both refuse it, for the same reason."""
    s = restore
    failures = s.client.status()["counters"]["reload_failures"]
    s.config_path.write_text(f'cell = "integrity"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{s.port}"]\n'
                             f'multicast_scouting = false\n[model]\npath = "{s.model_path}"\n')
    line = hup_and_wait(s.daemon, "reload_refused", "reload_applied")
    assert line["event"] == "reload_refused", line
    assert line["problems"][0].startswith("sensors: the edited config lists no sensors"), line["problems"]
    assert s.client.status()["counters"]["reload_failures"] == failures + 1
    check = run_cli("check-config", str(s.config_path))
    assert check.returncode == 2, check
    assert f"{s.config_path}: sensors: the config lists no sensors (an emptied file?)" in check.stderr, check.stderr
    assert "refuses it on reload" in check.stderr
    served_from_file(s.client, s, "after-sensorless")


# --- a model whose served content changed under the same id ------------------------------------------


def model_without_covariance(path: Path, rmse_um: float) -> Model:
    """The harness's model without a covariance block: every command's q_sigma_um is ``fit.rmse_um``,
    which the id does not cover (fit statistics describe how the model was made)."""
    model = write_test_model(path)
    model.fit = {"rmse_um": rmse_um}
    save_model(model, path)
    return load_model(path)


def test_a_model_whose_served_sigma_changed_is_applied_under_a_new_id(restore: Served) -> None:
    """Reload kept the old evaluator when the stored ids matched; a file without a covariance serves
    ``fit.rmse_um`` as its sigma, and the id did not cover it, so an edited RMS was never applied. The id
    covers it now (issue 26): the edited RMS is another model, served under its own id."""
    s = restore
    before = model_without_covariance(s.model_path, 0.01)
    line = hup_and_wait(s.daemon, "reload_applied", "reload_refused")
    assert line["event"] == "reload_applied" and line["model"] == before.id, line
    ok, command = s.client.query({"x_um": 470.0, "id": "sigma-1"})
    assert ok and command["model"] == before.id, command
    assert command["q_sigma_um"] == pytest.approx(0.01), command

    after = model_without_covariance(s.model_path, 0.25)
    assert after.id != before.id
    line = hup_and_wait(s.daemon, "reload_applied", "reload_refused")
    assert line["event"] == "reload_applied" and line["model"] == after.id, line
    ok, command = s.client.query({"x_um": 470.0, "id": "sigma-2"})
    assert ok and command["model"] == after.id, command
    assert command["q_sigma_um"] == pytest.approx(0.25), command  # the new RMS, not the kept evaluator's


# --- a reload that fails in an unexpected way -----------------------------------------------------------


def test_an_unexpected_error_in_a_reload_is_refused_logged_counted_and_the_old_drivers_keep_running(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """In-process: a driver plugin's bug (not a DriverSetupError) while the new drivers are built, then
    a failure after the running drivers were stopped. No real part fails there today; ``build`` stands
    in for a lab plugin's bug and the patched Compensator for a failure during the swap."""
    path = tmp_path / "sim.toml"
    sensors = '[[sensors]]\nname = "T1"\nkind = "simulated"\ninterval_s = {interval}\nmax_age_s = 5.0\n'
    path.write_text('cell = "bug"\n[simulation]\nscenario = "room"\n' + sensors.format(interval=0.05))
    built: list[int] = []

    def build(config: Any, context: Any) -> Any:
        built.append(len(built))
        if len(built) == 2:
            raise ValueError("a driver plugin's bug")
        return build_drivers(config, context)

    async def readings_arrive(service: Service) -> None:
        seen = service.state.table.version
        for _ in range(500):  # a new reading within 5 s: the drivers are polling
            await asyncio.sleep(0.01)
            if service.state.table.version > seen and service.state.table.entries["T1"].value is not None:
                return
        raise AssertionError("no new T1 reading within 5 s")

    async def body(log: Any) -> None:
        loop = asyncio.get_running_loop()
        unhandled: list[dict[str, Any]] = []
        loop.set_exception_handler(lambda _loop, context: unhandled.append(context))
        service = Service(load_config(path), config_path=path, build_drivers=build)
        await service.start_drivers(service.build_drivers(service.state.config, None))
        try:
            await readings_arrive(service)
            path.write_text('cell = "bug"\n[simulation]\nscenario = "room"\n' + sensors.format(interval=0.1))

            service.request_reload()  # the SIGHUP handler: build raises ValueError
            for _ in range(500):
                if service.state.counters.reload_failures:
                    break
                await asyncio.sleep(0.01)
            assert service.state.counters.reload_failures == 1

            def broken(*args: Any, **kwargs: Any) -> Any:
                raise RuntimeError("swap failed")

            monkeypatch.setattr(reload_module, "serving_state", broken)  # after the running drivers stopped
            assert await service.reloader.reload() is False
            assert service.state.counters.reload_failures == 2 and service.state.counters.reloads == 0
            assert service.state.config.sensors[0].interval_s == 0.05  # the old setup, still
            await readings_arrive(service)  # the stopped drivers were started again
        finally:
            await service.stop_drivers(final=True)
        assert unhandled == []

    with captured_logging() as stream:
        asyncio.run(asyncio.wait_for(body(None), 60))
        refused = [d for d in json_lines(stream) if d["event"] == "reload_refused"]
    assert [d["problems"] for d in refused] == [["internal error: ValueError: a driver plugin's bug"],
                                                ["internal error: RuntimeError: swap failed"]], refused
    assert all(d["config"] == str(path) and "Traceback" in d["exception"] for d in refused), refused
    assert built == [0, 1, 2]
