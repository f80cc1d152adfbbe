"""``[metrics] listen``: Prometheus metrics scraped over HTTP on 127.0.0.1 from a running daemon.

The daemon runs the harness' ``file`` plugin (two thermocouples and an interferometer) and test
model; targets (served and refused), a stale and a faulted sensor must show in the scraped counters,
histogram and gauges, in base units. A daemon driving a Modbus output module (the helpers' pymodbus
server, as a process) shows its actuator's state, ok then fault. The collector's handling of the
health fields is tested on documents that carry them, and two servers in one process keep their own
registries.
"""

from __future__ import annotations

import json
import signal
import socket
import subprocess
import sys
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    TEMPS,
    TESTS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)
from prometheus_client.parser import text_string_to_metric_families

from daemon.config import ConfigError, parse_config
from daemon.service.metrics import LATENCY_BUCKETS_S, AnswerLatency, MetricsServer

Samples = dict[tuple[str, tuple[tuple[str, str], ...]], float]


def scrape(url: str) -> Samples:
    with urllib.request.urlopen(url, timeout=10) as response:
        assert response.status == 200
        text = response.read().decode()
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def value(samples: Samples, name: str, **labels: str) -> float | None:
    return samples.get((name, tuple(sorted(labels.items()))))


POSITION_UM = 240.5


def position_sensor(path: Path) -> str:
    """An interferometer channel on the ``file`` plugin (it reads µm for role = "position")."""
    return (f'\n[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "file"\npath = "{path}"\n'
            "interval_s = 0.05\nmax_age_s = 2.0\ntimeout_s = 0.5\n")


class MeteredCell:
    def __init__(self, root: Path, cell: str = "metered") -> None:
        self.cell = cell
        self.port, self.metrics_port = free_port(), free_port()
        self.sensors = SensorFile(root / "sensors.json", {**TEMPS, "interferometer": POSITION_UM})
        model = root / "model.json"
        write_test_model(model)
        config = root / "nanodrift.toml"
        config.write_text(file_sensor_config(root, cell=cell, port=self.port, model_path=model,
                                             sensor_file=self.sensors.path,
                                             extra=f'[metrics]\nlisten = "127.0.0.1:{self.metrics_port}"\n'
                                                   + position_sensor(self.sensors.path)))
        self.config = config
        self.plugins = install_file_plugin(root / "plugins")
        self.daemon = Daemon(["--config", str(config)], root / "daemon.log", [self.plugins])
        self.daemon.wait_log("serving", timeout=30)
        self.url = self.daemon.wait_log("metrics_listening")["url"]
        self.client = Client(self.port, cell)
        self.client.wait_ready(["T1", "T2"])

    def close(self) -> int:
        self.client.close()
        return self.daemon.stop()


@pytest.fixture(scope="module")
def metered(tmp_path_factory: pytest.TempPathFactory) -> Iterator[MeteredCell]:
    cell = MeteredCell(tmp_path_factory.mktemp("metrics"))
    try:
        yield cell
    finally:
        assert cell.close() == 0


def test_targets_commands_errors_and_latency_are_counted(metered: MeteredCell) -> None:
    assert metered.url == f"http://127.0.0.1:{metered.metrics_port}/metrics"
    before = scrape(metered.url)
    c = metered.cell
    targets0 = value(before, "nanodrift_targets_total", cell=c) or 0.0
    for index in range(4):
        assert metered.client.query({"x_um": 100.0 + index, "id": index})[0]
    for index in range(3):
        assert not metered.client.query({"x_um": 9999.0, "id": f"far{index}"})[0]
    after = scrape(metered.url)
    assert value(after, "nanodrift_targets_total", cell=c) == targets0 + 7
    assert value(after, "nanodrift_commands_total", cell=c) >= 4
    assert value(after, "nanodrift_errors_total", cell=c, kind="out_of_workspace") >= 3
    count = value(after, "nanodrift_answer_latency_seconds_count", cell=c)
    assert count == value(after, "nanodrift_targets_total", cell=c)
    assert 0 < value(after, "nanodrift_answer_latency_seconds_sum", cell=c) < count * 1.0
    assert value(after, "nanodrift_answer_latency_seconds_bucket", cell=c, le="+Inf") == count
    assert value(after, "nanodrift_healthy", cell=c) == 1.0
    assert value(after, "nanodrift_model_info", cell=c, model=metered.client.status()["model"]["id"]) == 1.0


def sensor_states(samples: Samples, cell: str, channel: str) -> dict[str, float | None]:
    return {state: value(samples, "nanodrift_sensor_state", cell=cell, channel=channel, state=state)
            for state in ("ok", "stale", "fault")}


def test_sensor_readings_in_base_units_age_and_state_per_channel(metered: MeteredCell) -> None:
    c = metered.cell
    samples = scrape(metered.url)
    assert value(samples, "nanodrift_temperature_celsius", cell=c, channel="T1") == pytest.approx(TEMPS["T1"])
    assert value(samples, "nanodrift_temperature_celsius", cell=c, channel="T2") == pytest.approx(TEMPS["T2"])
    assert value(samples, "nanodrift_position_meters", cell=c, channel="interferometer") == pytest.approx(
        POSITION_UM * 1e-6)
    assert value(samples, "nanodrift_temperature_celsius", cell=c, channel="interferometer") is None
    assert not any(name.startswith("nanodrift_sensor_value") for name, _ in samples)
    assert 0.0 <= value(samples, "nanodrift_sensor_age_seconds", cell=c, channel="T2") < 2.0
    assert sensor_states(samples, c, "T1") == {"ok": 1.0, "stale": 0.0, "fault": 0.0}


def test_stale_and_fault_are_different_series(metered: MeteredCell) -> None:
    c = metered.cell
    metered.sensors.write(fault={"T1": "burnout"}, age={"T2": 30.0})  # T2's readings are 30 s old
    try:
        wait_until(lambda: sensor_states(scrape(metered.url), c, "T1") == {"ok": 0.0, "stale": 0.0, "fault": 1.0},
                   15, "nanodrift_sensor_state{channel=T1,state=fault} 1 after a burnout", interval=0.1)
        wait_until(lambda: sensor_states(scrape(metered.url), c, "T2") == {"ok": 0.0, "stale": 1.0, "fault": 0.0},
                   15, "nanodrift_sensor_state{channel=T2,state=stale} 1 for old readings", interval=0.1)
        samples = scrape(metered.url)
        assert value(samples, "nanodrift_sensor_age_seconds", cell=c, channel="T2") >= 30.0
        assert sensor_states(samples, c, "interferometer")["ok"] == 1.0
    finally:
        metered.sensors.write(fault={}, age={})
    wait_until(lambda: sensor_states(scrape(metered.url), c, "T1")["ok"] == 1.0
               and sensor_states(scrape(metered.url), c, "T2")["ok"] == 1.0, 15, "T1 and T2 ok again", interval=0.1)


def test_a_taken_metrics_port_stops_the_daemon_with_one_sentence(metered: MeteredCell, tmp_path: Path) -> None:
    text = metered.config.read_text().replace(f"127.0.0.1:{metered.port}", f"127.0.0.1:{free_port()}")
    config = tmp_path / "same-metrics-port.toml"
    config.write_text(text)
    second = Daemon(["--config", str(config)], tmp_path / "second.log", [metered.plugins])
    try:
        second.proc.wait(timeout=60)
    finally:
        second.stop()
    assert second.proc.returncode != 0
    last = json.loads((tmp_path / "second.log").read_text().strip().splitlines()[-1])  # not a terminal: JSON
    assert (last["event"], last["level"]) == ("run_failed", "error"), last
    assert last["error"] == (f"[metrics] listen = '127.0.0.1:{metered.metrics_port}': "
                             "cannot serve metrics there (already in use)")
    metered.client.wait_alive()  # the first daemon is untouched


def fake_doc(cell: str, **extra: Any) -> dict[str, Any]:
    return {"cell": cell, "uptime_s": 12.0, "healthy": True, "model": {"id": "m-1"}, "extrapolating": [],
            "sensors": {"T1": {"role": "temperature", "value": 21.5, "unit": "degC", "age_s": 0.2, "state": "ok"}},
            "counters": {"targets": 5, "commands": 4, "errors": {"stale": 1}, "reloads": 0, "reload_failures": 0},
            **extra}


class OutputModuleProcess:
    """tests/helpers/modbus_helpers.py as a process: a Modbus TCP module whose holding registers take writes."""

    def __init__(self, port: int) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(TESTS / "helpers" / "modbus_helpers.py"), "--port", str(port)],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # blocks until the server listens (or the process dies)
        assert "ready" in line, f"modbus module did not start: {line!r}"

    def kill(self) -> None:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
        self.proc.wait(10)
        if self.proc.stdout is not None:
            self.proc.stdout.close()


def test_a_live_daemon_shows_its_device_actuators_state(tmp_path: Path) -> None:
    """``[actuator] kind = "modbus"``: the state comes from the actuation (not the config), ok then fault."""
    cell, port, metrics_port, modbus_port = "driven", free_port(), free_port(), free_port()
    module = OutputModuleProcess(modbus_port)
    sensors = SensorFile(tmp_path / "sensors.json", TEMPS)
    model = tmp_path / "model.json"
    write_test_model(model)
    config = tmp_path / "nanodrift.toml"
    config.write_text(file_sensor_config(
        tmp_path, cell=cell, port=port, model_path=model, sensor_file=sensors.path,
        actuator='kind = "modbus"\nhub = "out"\ndevice_id = 1\naddress = 10\nscale = 0.001\nvolts_per_um = 0.02\n',
        extra=(f'[[hubs]]\nname = "out"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {modbus_port}\ntimeout_s = 0.3\n'
               f'[metrics]\nlisten = "127.0.0.1:{metrics_port}"\n')))
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log", [install_file_plugin(tmp_path / "plugins")])
    client = None
    try:
        daemon.wait_log("serving", timeout=30)
        url = daemon.wait_log("metrics_listening")["url"]
        client = Client(port, cell)
        client.wait_ready(["T1", "T2"])
        assert client.query({"x_um": 100.0, "id": 1})[0]
        wait_until(lambda: client.status()["actuator"]["writes"] >= 1, 15, "the first write to the module")
        samples = scrape(url)
        assert value(samples, "nanodrift_actuator_state", cell=cell, kind="modbus", state="ok") == 1.0
        assert value(samples, "nanodrift_actuator_state", cell=cell, kind="modbus", state="fault") == 0.0
        assert value(samples, "nanodrift_actuator_ok", cell=cell, kind="modbus") == 1.0
        module.kill()
        assert client.query({"x_um": 200.0, "id": 2})[0]  # answered at once; its write then fails
        wait_until(lambda: value(scrape(url), "nanodrift_actuator_state", cell=cell, kind="modbus",
                                 state="fault") == 1.0, 15, "nanodrift_actuator_state{state=fault} 1", interval=0.1)
        samples = scrape(url)
        assert value(samples, "nanodrift_actuator_state", cell=cell, kind="modbus", state="ok") == 0.0
        assert value(samples, "nanodrift_actuator_ok", cell=cell, kind="modbus") == 0.0
    finally:
        if client is not None:
            client.close()
        module.kill()
        assert daemon.stop() == 0


def test_two_servers_in_one_process_keep_their_own_registries() -> None:
    first_latency = AnswerLatency()
    first_latency.observe(30e-6)
    first_latency.observe(3.0)
    first = MetricsServer("127.0.0.1:0", lambda: fake_doc("one"), first_latency)
    second = MetricsServer("127.0.0.1:0", lambda: fake_doc(
        "two", health={"state": "degraded", "residual_rms_nm": 150.0, "residual_mean_nm": -20.0,
                       "correction_um": 0.05},
        actuator={"kind": "modbus", "state": "fault"}), AnswerLatency())
    first.start()
    second.start()
    first_url = first.url
    try:
        one, two = scrape(first_url), scrape(second.url)
    finally:
        first.stop()
        second.stop()
    assert value(one, "nanodrift_answer_latency_seconds_count", cell="one") == 2
    assert value(one, "nanodrift_answer_latency_seconds_bucket", cell="one", le=repr(LATENCY_BUCKETS_S[1])) == 1
    assert value(one, "nanodrift_answer_latency_seconds_bucket", cell="one", le=repr(LATENCY_BUCKETS_S[-1])) == 1
    assert value(two, "nanodrift_answer_latency_seconds_count", cell="two") == 0
    assert not any(labels and dict(labels).get("cell") == "one" for _, labels in two)
    assert value(one, "nanodrift_errors_total", cell="one", kind="stale") == 1
    assert not any(name.startswith(("nanodrift_health_", "nanodrift_actuator_")) for name, _ in one)
    assert value(two, "nanodrift_health_residual_rms_meters", cell="two") == pytest.approx(150e-9)
    assert value(two, "nanodrift_health_residual_mean_meters", cell="two") == pytest.approx(-20e-9)
    assert value(two, "nanodrift_health_correction_meters", cell="two") == pytest.approx(0.05e-6)
    assert value(two, "nanodrift_health_state", cell="two", state="degraded") == 1
    assert value(two, "nanodrift_actuator_ok", cell="two", kind="modbus") == 0
    assert value(two, "nanodrift_actuator_state", cell="two", kind="modbus", state="fault") == 1
    assert value(two, "nanodrift_actuator_state", cell="two", kind="modbus", state="ok") == 0
    with socket.socket() as probe:  # stopped: nobody listens there any more
        assert probe.connect_ex(("127.0.0.1", int(first_url.rsplit(":", 1)[1].split("/")[0]))) != 0


@pytest.mark.parametrize("listen", ["9464", "127.0.0.1", "127.0.0.1:0", "127.0.0.1:70000", "http://x:1"])
def test_metrics_listen_is_validated(listen: str) -> None:
    with pytest.raises(ConfigError, match=r"metrics\.listen: .*HOST:PORT"):
        parse_config({"metrics": {"listen": listen}})


def test_metrics_are_off_by_default() -> None:
    assert parse_config({}).metrics.listen == ""
