"""Issue 10's reload reproductions, against the running daemon (a separate process, real Zenoh client).

(1) An emptied config on SIGHUP must never swap a hardware cell for the simulator or for the
package's default model; the real sensors stay. (3) Non-finite numbers in an edit are refused,
naming the field. (5) A deeply nested model JSON is refused on SIGHUP (logged, counted) and a daemon
started with it runs without a model. The hardware cell is the harness's ``file`` plugin: a
non-simulated driver found by entry point, as a lab's own would be.
"""

from __future__ import annotations

import re
import signal
from collections.abc import Iterator
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
    wait_until,
)

from daemon.config import DEFAULT_MODEL_PATH
from daemon.model.model import load_model

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
        assert line.get("model") != default_model, f"the emptied config swapped in the package's default model: {line}"

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
