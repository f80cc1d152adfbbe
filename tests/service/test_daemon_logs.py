"""What ``nanodrift run`` logs (issue 13, reproduction 2 and 6): every target and its answer at debug,
nothing per target at info, and one ``sensor_state`` line when a device takes all its channels down;
issue 16: with stderr not a terminal, its start-up and usage errors are JSON lines too."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    REPO,
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


def start(root: Path, level: str, channels: tuple[str, ...] = ("T1", "T2")) -> tuple[Daemon, Client, SensorFile]:
    port = free_port()
    sensors = SensorFile(root / "sensors.json", {**TEMPS, "T3": 22.0})
    model = root / "model.json"
    write_test_model(model)
    config = root / "nanodrift.toml"
    config.write_text(file_sensor_config(root, cell=f"logs{level}", port=port, model_path=model,
                                         sensor_file=sensors.path, channels=channels))
    daemon = Daemon(["--config", str(config), "--log-level", level], root / "daemon.log",
                    [install_file_plugin(root / "plugins")])
    daemon.wait_log("serving", timeout=30)
    client = Client(port, f"logs{level}")
    client.wait_ready(list(channels))
    return daemon, client, sensors


def test_debug_logs_each_target_and_its_answer(tmp_path: Path) -> None:
    daemon, client, _ = start(tmp_path, "debug")
    try:
        ok, command = client.query({"x_um": 240.0, "id": "dbg-1"})
        assert ok
        refused, _ = client.query({"x_um": 9999.0, "id": "dbg-2"})
        assert not refused

        def answered() -> list[dict]:
            lines = {d.get("id"): d for d in daemon.log_events("target_answered")}
            return [lines[i] for i in ("dbg-1", "dbg-2")] if {"dbg-1", "dbg-2"} <= set(lines) else []

        served, error = wait_until(answered, 10, "target_answered lines for both targets")
        assert served["level"] == "debug" and served["x_um"] == 240.0
        assert served["q_um"] == pytest.approx(command["q_um"], abs=1e-6)
        assert served["voltage_v"] == pytest.approx(command["voltage_v"], abs=1e-6)
        assert 0 < served["latency_us"] < 1e6
        assert error["error"] == "out_of_workspace" and error["latency_us"] > 0
    finally:
        client.close()
        assert daemon.stop() == 0


def test_info_stays_quiet_and_a_device_failure_is_one_sensor_state_line(tmp_path: Path) -> None:
    daemon, client, sensors = start(tmp_path, "info", channels=("T1", "T2", "T3"))
    try:
        for index in range(20):
            assert client.query({"x_um": 100.0, "id": index})[0]
        before = len(daemon.log_events("sensor_state"))  # the channels' first ok (start-up)
        sensors.write(error="hub unplugged")  # the one device behind T1, T2 and T3 fails
        line = daemon.wait_log("sensor_state", count=before + 1)
        assert line["channels"] == ["T1", "T2", "T3"] and line["state"] == "fault"
        assert "hub unplugged" in line["reason"] and line["was"] == "ok"
        sensors.write(error="")
        back = daemon.wait_log("sensor_state", count=before + 2)
        assert back["channels"] == ["T1", "T2", "T3"] and back["state"] == "ok"
        client.wait_ready(["T1", "T2", "T3"])
        assert len(daemon.log_events("sensor_state")) == before + 2  # not one per channel
        assert not daemon.log_events("target_answered")
        assert not [d for d in daemon.logs() if d.get("level") == "debug"]
    finally:
        client.close()
        assert daemon.stop() == 0


# --- issue 16 (problem 11): every stderr line of `nanodrift run` is JSON when stderr is not a terminal ----

def run_with_stderr_piped(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "nanodrift.cli", *args], stdin=subprocess.DEVNULL,
                          capture_output=True, text=True, cwd=REPO, timeout=60)


def json_stderr(result: subprocess.CompletedProcess[str]) -> list[dict[str, Any]]:
    """Every line of stderr as a JSON object (the README's ``journalctl -o cat | jq`` recipe)."""
    lines = result.stderr.splitlines()
    assert lines, "nothing on stderr"
    parsed = []
    for line in lines:
        try:
            parsed.append(json.loads(line))
        except json.JSONDecodeError:
            pytest.fail(f"a stderr line of nanodrift run is not JSON: {line!r}\n{result.stderr}")
    assert all(isinstance(p, dict) and {"event", "level", "timestamp"} <= p.keys() for p in parsed), parsed
    return parsed


def test_a_start_up_failure_of_run_is_a_json_line(tmp_path: Path) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text('cell = "c0"\n[actuator]\nmax_slew_um_per_s = 1e-300\n')
    result = run_with_stderr_piped("run", "--config", str(bad))
    assert result.returncode == 2 and result.stdout == "", result.stderr
    last = json_stderr(result)[-1]
    assert (last["event"], last["level"]) == ("run_failed", "error"), last
    assert last["error"].startswith(f"{bad}:3: actuator.max_slew_um_per_s: "), last


@pytest.mark.parametrize("args", [["--log-level", "loud"], ["--bogus"], ["--config"]],
                         ids=["bad-choice", "unknown-option", "missing-value"])
def test_a_usage_error_of_run_is_a_json_line(args: list[str]) -> None:
    result = run_with_stderr_piped("run", *args)
    assert result.returncode == 2 and result.stdout == "", result.stderr
    lines = json_stderr(result)
    assert len(lines) == 1 and lines[0]["event"] == "usage_error" and lines[0]["level"] == "error", lines
    assert lines[0]["usage"].startswith("usage: nanodrift"), lines


def test_other_commands_keep_their_plain_error_lines(tmp_path: Path) -> None:
    """check-config and the procedures speak to a terminal or a script: ``nanodrift CMD: error: ...``."""
    bad = tmp_path / "bad.toml"
    bad.write_text('cell = 3\n')
    result = run_with_stderr_piped("check-config", str(bad))
    assert result.returncode == 2
    assert result.stderr == f"nanodrift check-config: error: {bad}:1: cell: Input should be a valid string\n"
