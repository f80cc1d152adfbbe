"""``[metrics] listen``: Prometheus metrics scraped over HTTP on 127.0.0.1 from a running daemon.

The daemon runs the harness' ``file`` plugin (two thermocouples and an interferometer) and test
model; targets (served and refused), a stale and a faulted sensor must show in the scraped counters,
histogram and gauges, in base units. A daemon driving a Modbus output module (the helpers' pymodbus
server, as a process) shows its actuator's state, ok then fault. The collector's handling of the
health fields is tested on documents that carry them, and two servers in one process keep their own
registries.

The server itself (issue 16: idle connections exhausted the daemon's file descriptors) runs on an
event loop on a thread of its own here, while the tests' blocking sockets play the clients: a flood of
idle connections holds at most the bound and a scrape still gets through, idle and trickling
connections are cut at the header timeout, and only ``GET /metrics`` (and ``/``) is answered.
"""

from __future__ import annotations

import asyncio
import json
import re
import select
import signal
import socket
import subprocess
import sys
import threading
import time
import urllib.request
from collections.abc import Callable, Coroutine, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
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

from nanodrift.config import ConfigError, parse_config
from nanodrift.drivers.base import State
from nanodrift.model.provenance import version
from nanodrift.service.metrics import ERROR_KINDS, LATENCY_BUCKETS_S, AnswerLatency
from nanodrift.service.metrics_server import INDEX_TEXT, MetricsServer

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


def test_every_error_kind_has_a_series_from_zero_and_the_build_is_labelled(metered: MeteredCell) -> None:
    """Issue 19: before any refusal, so that ``rate()`` and ``increase()`` see the first one."""
    samples = scrape(metered.url)  # the first test on this daemon: nothing has been refused yet
    c = metered.cell
    assert {kind: value(samples, "nanodrift_errors_total", cell=c, kind=kind) for kind in ERROR_KINDS} == dict.fromkeys(
        ERROR_KINDS, 0.0)
    assert value(samples, "nanodrift_build_info", cell=c, version=version()) == 1.0


def test_the_error_kinds_are_every_kind_the_daemon_refuses_with() -> None:
    """``Refusal("kind", ...)`` anywhere in the daemon, and a channel's state (stale, fault) for the others."""
    sources = "\n".join(path.read_text() for path in (TESTS.parent / "daemon").rglob("*.py"))
    literal = set(re.findall(r"Refusal\(\s*\"(\w+)\"", sources))
    assert {"out_of_workspace", "bad_payload", "internal"} <= literal  # the scan finds them
    assert literal | {state.value for state in State if state is not State.OK} == set(ERROR_KINDS)


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


class LoopThread:
    """An event loop on a thread of its own: the server under test serves there, as on the daemon's
    loop, while the tests' blocking sockets play the clients."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self.thread = threading.Thread(target=self.loop.run_forever, name="metrics-loop", daemon=True)
        self.thread.start()

    def run(self, coroutine: Coroutine[Any, Any, Any], timeout_s: float = 10.0) -> Any:
        return asyncio.run_coroutine_threadsafe(coroutine, self.loop).result(timeout_s)

    def call(self, function: Callable[[], Any]) -> Any:
        """``function()`` on the loop (the server's state is the loop's to read)."""

        async def call() -> Any:
            return function()

        return self.run(call())

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self.thread.join(10)
        self.loop.close()


@pytest.fixture
def loop() -> Iterator[LoopThread]:
    thread = LoopThread()
    try:
        yield thread
    finally:
        thread.close()


@contextmanager
def served(loop: LoopThread, status_doc: Callable[[], dict[str, Any]] | None = None,
           **bounds: Any) -> Iterator[tuple[MetricsServer, int]]:
    """A started server on 127.0.0.1 (a free port) with ``bounds`` (max_connections, header_timeout_s, ...)."""
    server = MetricsServer("127.0.0.1:0", status_doc or (lambda: fake_doc("bounded")), AnswerLatency(), **bounds)
    loop.run(server.start())
    try:
        yield server, int(server.url.rsplit(":", 1)[1].split("/")[0])
    finally:
        loop.run(server.stop())


class Peer:
    """One client connection that sends nothing unless told: ``closed()`` polls whether the server has
    closed it (end of stream or reset), keeping what it answered before."""

    def __init__(self, port: int) -> None:
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=10)
        self.opened = time.monotonic()
        self.received = b""
        self.closed_at: float | None = None

    def closed(self) -> bool:
        while self.closed_at is None:
            if not select.select([self.sock], [], [], 0)[0]:
                return False
            try:
                data = self.sock.recv(65536)  # readable: returns at once
            except ConnectionResetError:
                data = b""
            if not data:
                self.closed_at = time.monotonic()
            self.received += data
        return True

    def close(self) -> None:
        self.sock.close()


def exchange(port: int, request: bytes) -> bytes:
    """Send a raw request; everything the server answers until it closes."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(request)
        chunks = []
        while chunk := sock.recv(65536):
            chunks.append(chunk)
    return b"".join(chunks)


def test_a_flood_of_idle_connections_holds_at_most_the_bound_and_a_scrape_gets_through(loop: LoopThread) -> None:
    """Issue 16: 200 connections that never send a request. A thread-per-connection server keeps all 200
    (and would take 1000 descriptors from the daemon); this one keeps the 32 newest, closing the oldest
    idle one for each newcomer, and a scrape takes an idle one's place at once."""
    with served(loop, max_connections=32, header_timeout_s=60.0) as (server, port):  # no timeout in this test
        peers: list[Peer] = []
        try:
            for _ in range(200):
                peers.append(Peer(port))
            wait_until(lambda: sum(p.closed() for p in peers) >= 200 - 32, 15,
                       "the server closing all but 32 of 200 idle connections")
            assert [p.closed() for p in peers] == [True] * 168 + [False] * 32  # the oldest went, in order
            assert all(p.received == b"" for p in peers[:168])  # closed unread and unanswered
            assert loop.call(lambda: server.open_connections) == 32
            samples = scrape(server.url)  # while the flood's 32 are still open
            assert value(samples, "nanodrift_targets_total", cell="bounded") == 5
            assert [p.closed() for p in peers] == [True] * 169 + [False] * 31  # the oldest idle made room
            assert loop.call(lambda: (server.open_connections, server.peak_connections, server.evicted,
                                      server.refused)) == (31, 32, 169, 0)
        finally:
            for peer in peers:
                peer.close()
        wait_until(lambda: loop.call(lambda: server.open_connections) == 0, 10, "the server seeing them go")


def test_idle_connections_are_closed_at_the_header_timeout(loop: LoopThread) -> None:
    with served(loop, max_connections=32, header_timeout_s=0.5) as (server, port):
        peers = [Peer(port) for _ in range(20)]  # under the bound: none is closed to admit another
        try:
            wait_until(lambda: all(p.closed() for p in peers), 10, "every idle connection closed by the server")
            assert min(p.closed_at - p.opened for p in peers) >= 0.5  # not before the timeout
            assert all(p.received.startswith(b"HTTP/1.1 408 Request Timeout\r\n") for p in peers)
            assert loop.call(lambda: (server.open_connections, server.evicted)) == (0, 0)
        finally:
            for peer in peers:
                peer.close()


def test_a_request_head_trickled_in_is_cut_at_the_header_timeout(loop: LoopThread) -> None:
    """Slowloris: a header line every 50 ms never completes the head; bytes arriving do not extend the time."""
    with served(loop, header_timeout_s=0.5) as (_, port):
        peer = Peer(port)
        try:
            peer.sock.sendall(b"GET /metrics HTTP/1.1\r\nHost: 127.0.0.1\r\n")
            lines = 0
            while not peer.closed() and time.monotonic() - peer.opened < 10:  # bounded: 10 s at most
                try:
                    peer.sock.sendall(b"X-Slow: %d\r\n" % lines)
                except (BrokenPipeError, ConnectionResetError):
                    continue  # closed: closed() says so next
                lines += 1
                time.sleep(0.05)  # the trickle's pace
            assert peer.closed(), "still open after 10 s of trickled headers"
            assert 0.5 <= peer.closed_at - peer.opened < 3.0  # a thread-per-connection server: 100 lines (5 s)
            assert lines >= 3  # it was trickling when it was cut
            assert peer.received == b"" or peer.received.startswith(b"HTTP/1.1 408 ")  # a reset may eat the 408
        finally:
            peer.close()


def test_when_every_connection_is_being_answered_a_new_one_is_closed_unread(loop: LoopThread) -> None:
    release = threading.Event()

    def slow_doc() -> dict[str, Any]:
        release.wait(10)  # the state lock held elsewhere, say
        return fake_doc("busy")

    with served(loop, slow_doc, max_connections=2) as (server, port), ThreadPoolExecutor(2) as clients:
        scrapes = [clients.submit(scrape, server.url) for _ in range(2)]
        try:
            wait_until(lambda: loop.call(lambda: server.answering_connections) == 2, 10, "two scrapes in progress")
            third = Peer(port)
            wait_until(third.closed, 10, "the third connection closed")
            assert third.received == b""
            assert loop.call(lambda: (server.refused, server.evicted, server.open_connections)) == (1, 0, 2)
        finally:
            release.set()
        assert [value(f.result(10), "nanodrift_targets_total", cell="busy") for f in scrapes] == [5.0, 5.0]


def status_line(answer: bytes) -> str:
    return answer.split(b"\r\n", 1)[0].decode()


def header(answer: bytes, name: str) -> str | None:
    head = answer.split(b"\r\n\r\n", 1)[0].decode("latin-1").split("\r\n")[1:]
    return next((v.strip() for k, _, v in (line.partition(":") for line in head) if k.lower() == name.lower()), None)


def test_only_get_of_the_metrics_page_is_answered(loop: LoopThread) -> None:
    with served(loop, max_header_bytes=8192) as (_, port):
        page = exchange(port, b"GET /metrics HTTP/1.1\r\nHost: x\r\n\r\n")
        assert status_line(page) == "HTTP/1.1 200 OK" and header(page, "Connection") == "close"
        body = page.split(b"\r\n\r\n", 1)[1]
        assert int(header(page, "Content-Length")) == len(body)
        assert b'nanodrift_targets_total{cell="bounded"} 5.0' in body
        head_only = exchange(port, b"HEAD /metrics?x=1 HTTP/1.1\r\n\r\n")
        assert status_line(head_only) == "HTTP/1.1 200 OK" and head_only.endswith(b"\r\n\r\n")
        assert int(header(head_only, "Content-Length")) > 0
        index = exchange(port, b"GET / HTTP/1.0\r\n\r\n")
        assert status_line(index) == "HTTP/1.1 200 OK" and index.endswith(b"\r\n\r\n" + INDEX_TEXT)
        openmetrics = exchange(port, b"GET /metrics HTTP/1.1\r\nAccept: application/openmetrics-text; "
                                     b"version=1.0.0\r\n\r\n")
        assert header(openmetrics, "Content-Type").startswith("application/openmetrics-text")
        assert openmetrics.endswith(b"# EOF\n")
        post = exchange(port, b"POST /metrics HTTP/1.1\r\nContent-Length: 0\r\n\r\n")
        assert status_line(post) == "HTTP/1.1 405 Method Not Allowed" and header(post, "Allow") == "GET, HEAD"
        assert status_line(exchange(port, b"GET /admin HTTP/1.1\r\n\r\n")) == "HTTP/1.1 404 Not Found"
        assert status_line(exchange(port, b"hello there\r\n\r\n")) == "HTTP/1.1 400 Bad Request"
        assert status_line(exchange(port, b"GET /metrics HTTP/1.1\r\nno colon\r\n\r\n")) == "HTTP/1.1 400 Bad Request"
        huge = exchange(port, b"GET /metrics HTTP/1.1\r\nX-Big: " + b"a" * 9000 + b"\r\n\r\n")
        assert status_line(huge) == "HTTP/1.1 431 Request Header Fields Too Large"


def test_stop_closes_open_connections_and_a_second_stop_does_nothing(loop: LoopThread) -> None:
    server = MetricsServer("127.0.0.1:0", lambda: fake_doc("stopped"), AnswerLatency())
    loop.run(server.stop())  # before start: nothing to stop
    loop.run(server.start())
    port = int(server.url.rsplit(":", 1)[1].split("/")[0])
    peer = Peer(port)
    try:
        wait_until(lambda: loop.call(lambda: server.open_connections) == 1, 10, "the connection accepted")
        loop.run(server.stop())
        wait_until(peer.closed, 10, "the open connection closed by stop")
        loop.run(server.stop())
        assert loop.call(lambda: server.open_connections) == 0
        with socket.socket() as probe:
            assert probe.connect_ex(("127.0.0.1", port)) != 0
    finally:
        peer.close()


def test_two_servers_in_one_process_keep_their_own_registries(loop: LoopThread) -> None:
    first_latency = AnswerLatency()
    first_latency.observe(30e-6)
    first_latency.observe(3.0)
    first = MetricsServer("127.0.0.1:0", lambda: fake_doc("one"), first_latency)
    second = MetricsServer("127.0.0.1:0", lambda: fake_doc(
        "two", health={"state": "degraded", "residual_rms_nm": 150.0, "residual_mean_nm": -20.0,
                       "correction_um": 0.05},
        actuator={"kind": "modbus", "state": "fault"}), AnswerLatency())
    loop.run(first.start())
    loop.run(second.start())
    first_url = first.url
    try:
        one, two = scrape(first_url), scrape(second.url)
    finally:
        loop.run(first.stop())
        loop.run(second.stop())
    assert value(one, "nanodrift_answer_latency_seconds_count", cell="one") == 2
    assert value(one, "nanodrift_answer_latency_seconds_bucket", cell="one", le=repr(LATENCY_BUCKETS_S[1])) == 1
    assert value(one, "nanodrift_answer_latency_seconds_bucket", cell="one", le=repr(LATENCY_BUCKETS_S[-1])) == 1
    assert value(two, "nanodrift_answer_latency_seconds_count", cell="two") == 0
    assert not any(labels and dict(labels).get("cell") == "one" for _, labels in two)
    assert value(one, "nanodrift_errors_total", cell="one", kind="stale") == 1
    assert value(one, "nanodrift_errors_total", cell="one", kind="out_of_workspace") == 0  # from 0 (issue 19)
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


@pytest.mark.parametrize("host", ["a" * 64 + ".lab", ".".join(["a" * 63] * 4) + ".ab", "1.2.3.999", "[zz::1::]",
                                  "under_score", "-dash", "dash-.lab"])
def test_a_metrics_host_that_is_no_address_or_host_name_is_refused(host: str) -> None:
    with pytest.raises(ConfigError, match=r"metrics\.listen: .*is not an IP address .* or a host name") as error:
        parse_config({"metrics": {"listen": f"{host}:9464"}})
    assert len(str(error.value)) < 400  # a long host is shortened in the message


@pytest.mark.parametrize("listen", ["localhost:9464", "0.0.0.0:9464", "[::]:9464", "[::1]:9464",
                                    "prometheus-target.lab:1", "a" * 63 + ".lab:9464"])
def test_addresses_and_host_names_are_accepted(listen: str) -> None:
    assert parse_config({"metrics": {"listen": listen}}).metrics.listen == listen


#: what a daemon of the simulated cell imports and does before it serves, up to its metrics (in a fresh process)
START_METRICS = """
import asyncio, sys
{before}
from nanodrift.cli import build_parser
build_parser(only="run")  # imports nanodrift.commands.run: every module a daemon imports before it starts
from nanodrift.assembly import build_drivers
from nanodrift.config import parse_config
from nanodrift.errors import UserError
from nanodrift.service import Service
config = parse_config({{"simulation": {{}}, "metrics": {{"listen": {listen!r}}}}})
service = Service(config, build_drivers=build_drivers)
try:
    asyncio.run(service.start_metrics())
    asyncio.run(service.stop_metrics())
except UserError as error:
    print("UserError:", error)
print(sorted(m for m in sys.modules if m.split(".")[0] == "prometheus_client" or m.startswith("http.server")
             or m.startswith("nanodrift.service.metrics")))
"""


def start_metrics(listen: str, before: str = "") -> list[str]:
    code = START_METRICS.format(before=before, listen=listen)
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    return done.stdout.strip().splitlines()


def test_a_daemon_without_metrics_never_imports_prometheus_client() -> None:
    assert start_metrics("") == ["[]"]  # metrics off: ~40 ms less of every daemon's start


def test_a_daemon_with_metrics_but_no_prometheus_client_fails_at_start_with_one_sentence() -> None:
    lines = start_metrics(f"127.0.0.1:{free_port()}", before="sys.modules['prometheus_client'] = None")
    refused = [line for line in lines if line.startswith("UserError: ")]  # the CLI's run_failed line says it
    assert len(refused) == 1, lines
    assert refused[0].startswith("UserError: [metrics] listen = '127.0.0.1:"), lines
    assert "cannot serve metrics" in refused[0] and "prometheus_client" in refused[0], lines
