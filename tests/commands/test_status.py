"""``nanodrift status``: three daemons of different cells on one loopback network, one client.

Cell ``alpha`` listens on a port; ``beta`` and ``gamma`` listen on their own and connect to it (peers
gossip the rest), and the client connects to ``alpha`` only: every cell must still answer the
wildcard query. Every wait polls a condition under a deadline.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import subprocess
import sys
import types
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    REPO,
    TEMPS,
    TESTS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    run_cli,
    wait_until,
    write_test_model,
)

from nanodrift.commands import status as status_command
from nanodrift.commands.status import COLUMNS, rates, table

CELLS = ("alpha", "beta", "gamma")


class Network:
    """Three daemons (file plugin, the harness' test model) meshed over 127.0.0.1."""

    def __init__(self, root: Path) -> None:
        self.root = root
        plugins = install_file_plugin(root / "plugins")
        self.ports = {cell: free_port() for cell in CELLS}
        self.sensors: dict[str, SensorFile] = {}
        self.daemons: dict[str, Daemon] = {}
        self.model_ids: dict[str, str] = {}
        hub = f"tcp/127.0.0.1:{self.ports['alpha']}"
        for cell in CELLS:
            folder = root / cell
            folder.mkdir()
            model = folder / "model.json"
            self.model_ids[cell] = write_test_model(model).id
            self.sensors[cell] = SensorFile(folder / "sensors.json", TEMPS)
            config = folder / "nanodrift.toml"
            config.write_text(file_sensor_config(folder, cell=cell, port=self.ports[cell], model_path=model,
                                                 sensor_file=self.sensors[cell].path))
            args = ["--config", str(config)] + ([] if cell == "alpha" else ["-e", hub])
            self.daemons[cell] = Daemon(args, folder / "daemon.log", [plugins])
        for daemon in self.daemons.values():
            daemon.wait_log("serving", timeout=30)
        self.endpoint = hub

    def status(self, *args: str) -> subprocess.CompletedProcess[str]:
        """``nanodrift status ARGS`` in this process: the waits poll it many times, and a subprocess would cost each
        poll half a second of CPU. What the whole process writes on stderr is checked through
        :meth:`status_process`."""
        return run_cli("status", *args)

    def status_process(self, *args: str, timeout: float = 60) -> subprocess.CompletedProcess[str]:
        """``nanodrift status ARGS`` in a process of its own: every line it writes on stderr, zenoh's included."""
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(TESTS), str(REPO)]))
        return subprocess.run([sys.executable, "-m", "nanodrift.cli", "status", *args], capture_output=True,
                              text=True, timeout=timeout, env=env, cwd=str(self.root))

    def close(self) -> None:
        for daemon in self.daemons.values():
            assert daemon.stop() == 0


@pytest.fixture(scope="module")
def network(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Network]:
    net = Network(tmp_path_factory.mktemp("status"))
    try:
        yield net
    finally:
        net.close()


def parse_table(text: str) -> dict[str, dict[str, str]]:
    """cell -> {column: value}, cut at the header's column positions (values may contain spaces)."""
    lines = text.splitlines()
    header = lines[0]
    starts = [header.index(name) for name in COLUMNS]
    rows = {}
    for line in lines[1:]:
        if not line or line.startswith("("):
            continue
        cells = [line[a:b].strip() for a, b in zip(starts, [*starts[1:], None], strict=True)]
        rows[cells[0]] = dict(zip(COLUMNS, cells, strict=True))
    return rows


def all_ok(net: Network, cells: tuple[str, ...] = CELLS) -> list[dict[str, Any]] | None:
    result = net.status("-e", net.endpoint, "--json")
    if result.returncode != 0:
        return None
    docs = json.loads(result.stdout)
    seen = {d["cell"]: d for d in docs}
    ok = set(cells) <= set(seen) and all(
        all(s["state"] == "ok" for s in seen[c]["sensors"].values()) for c in cells)
    return docs if ok else None


def test_status_lists_every_cell_on_the_network_as_json(network: Network) -> None:
    docs = wait_until(lambda: all_ok(network), 60, "all three cells answering with sensors ok", interval=0.2)
    assert [d["cell"] for d in docs] == sorted(CELLS)
    assert all(d["model"]["id"] for d in docs) and all(d["healthy"] for d in docs)


def test_status_table_has_one_row_per_cell(network: Network) -> None:
    wait_until(lambda: all_ok(network), 60, "all three cells ok", interval=0.2)
    result = network.status("-e", network.endpoint)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    rows = parse_table(result.stdout)
    assert set(rows) == set(CELLS)
    for cell in CELLS:
        row = rows[cell]
        assert row["STATE"] == "ok" and row["SENSORS"] == "2/2", row
        assert row["MODEL"] == network.model_ids[cell] and row["ACTUATOR"] == "zenoh ok"
        assert row["HEALTH"] == "unknown"  # the daemon's health unit, without a position sensor to judge by
        assert row["MODEL AGE"] == "-" and float(row["TARGETS/MIN"]) >= 0.0  # the test model has no date
    assert "(3 cells;" in lines[-1]


def test_status_for_one_cell_and_a_fault_shows_degraded(network: Network) -> None:
    network.sensors["beta"].write(fault={"T2": "burnout"})
    try:
        def degraded() -> Any:
            result = network.status("-e", network.endpoint, "--cell", "beta")
            return result if result.returncode == 0 and " degraded " in result.stdout else None

        result = wait_until(degraded, 30, "beta degraded in the table", interval=0.2)
        rows = parse_table(result.stdout)
        assert list(rows) == ["beta"] and rows["beta"]["SENSORS"] == "1/2"
    finally:
        network.sensors["beta"].write(fault={})


def test_watch_prints_a_block_per_refresh_off_a_terminal(network: Network) -> None:
    wait_until(lambda: all_ok(network), 60, "all three cells ok", interval=0.2)
    result = network.status("-e", network.endpoint, "--watch", "0.2", "--count", "2")
    assert result.returncode == 0, result.stderr
    assert "\x1b[" not in result.stdout  # not a terminal: no escape codes
    blocks = [b for b in result.stdout.split("--- ") if b.strip()]
    assert len(blocks) == 2 and all(b.count("\n") >= 4 for b in blocks)
    assert "over the last interval" in blocks[1]


def test_no_cell_answers_exits_non_zero_with_a_hint(network: Network) -> None:
    result = network.status_process("-e", network.endpoint, "--cell", "nosuchcell", "--timeout", "0.5")
    assert result.returncode == 1
    assert result.stderr.count("\n") == 1 and "no cell answered on nanodrift/nosuchcell/status" in result.stderr
    assert "-e tcp/HOST:PORT" in result.stderr


def test_nobody_listening_is_one_sentence_without_rust_paths(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(REPO))
    result = subprocess.run([sys.executable, "-m", "nanodrift.cli", "status", "-e", f"tcp/127.0.0.1:{free_port()}"],
                            capture_output=True, text=True, timeout=60, env=env, cwd=str(tmp_path))
    assert result.returncode == 2
    assert "nobody is listening at tcp/127.0.0.1:" in result.stderr
    assert ".rs:" not in result.stderr and "/root/.cargo" not in result.stderr


def test_rates_from_two_samples_and_from_uptime() -> None:
    first = {"cell": "c", "uptime_s": 60.0, "counters": {"targets": 30, "errors_total": 6}}
    second = {"cell": "c", "uptime_s": 90.0, "counters": {"targets": 90, "errors_total": 6}}
    assert rates(first).targets_per_min == pytest.approx(30.0) and rates(first).refused_per_min == pytest.approx(6.0)
    two = rates(second, first)
    assert two.since == "last" and two.targets_per_min == pytest.approx(120.0) and two.refused_per_min == 0.0
    restarted = {"cell": "c", "uptime_s": 10.0, "counters": {"targets": 1, "errors_total": 0}}
    assert rates(restarted, second).since == "start"  # a restarted daemon: counters went back


def test_table_shows_health_and_actuator_state_when_the_document_has_them() -> None:
    doc = {"cell": "c", "healthy": True, "uptime_s": 60.0, "sensors": {"T1": {"state": "ok"}},
           "model": {"id": "m-1", "created": "2026-01-01T00:00:00+00:00"}, "counters": {"targets": 0, "errors": {}},
           "health": {"state": "degraded", "residual_rms_nm": 123.4}, "actuator": {"kind": "modbus", "state": "fault"}}
    text = table([doc])
    row = parse_table(text)["c"]
    assert row["HEALTH"] == "degraded 123 nm" and row["ACTUATOR"] == "modbus fault" and row["MODEL AGE"].endswith(" d")


def test_table_shows_how_the_daemon_proved_where_the_output_was_at_its_start() -> None:
    doc = {"cell": "c", "healthy": True, "uptime_s": 60.0, "sensors": {}, "model": None, "counters": {"targets": 0},
           "actuator": {"kind": "modbus", "state": "ok", "proved_by": "position_sensor"}}
    assert parse_table(table([doc]))["c"]["ACTUATOR"] == "modbus ok (proved: position_sensor)"
    xy = {**doc, "actuator": {"kind": "axes", "state": "ok"}, "axes": {
        axis: {"min_um": 0.0, "max_um": 480.0, "actuator": {"kind": "modbus", "state": "ok", "proved_by": "state",
                                                            "last_voltage_v": 8.0}} for axis in ("x", "y")}}
    text = table([xy])
    assert parse_table(text)["c"]["ACTUATOR"] == "x:modbus:ok y:modbus:ok"  # each axis' proof on its own line
    assert "  c axis y: [0, 480] µm, modbus ok at 8.00000 V (proved: state)" in text, text


def test_table_says_how_many_held_targets_went_unrecorded() -> None:
    """Issue 26.9: held targets the position poll cannot fill were dropped silently with health ok."""
    doc = {"cell": "c", "healthy": True, "uptime_s": 60.0, "sensors": {}, "model": None, "counters": {"targets": 12},
           "health": {"state": "ok", "residual_rms_nm": 20.0, "holds_unrecorded": 7}}
    assert parse_table(table([doc]))["c"]["HEALTH"] == "ok 20 nm (7 unrecorded)"
    doc["health"] = {"state": "ok", "residual_rms_nm": 20.0, "holds_unrecorded": 0}
    assert parse_table(table([doc]))["c"]["HEALTH"] == "ok 20 nm"


def test_refusals_show_up_as_a_rate_for_their_cell_only(network: Network) -> None:
    wait_until(lambda: all_ok(network), 60, "all three cells ok", interval=0.2)
    client = Client(network.ports["gamma"], "gamma")
    try:
        for index in range(5):
            ok, answer = client.query({"x_um": 9999.0, "id": index})
            assert not ok and answer["id"] == index
    finally:
        client.close()
    rows = parse_table(network.status("-e", network.endpoint).stdout)
    assert float(rows["gamma"]["REFUSED/MIN"]) > 0.0 and float(rows["gamma"]["TARGETS/MIN"]) > 0.0
    assert float(rows["alpha"]["REFUSED/MIN"]) == 0.0


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_watch_redraws_in_place_on_a_terminal() -> None:
    samples = iter([
        [{"cell": "c", "uptime_s": 60.0, "healthy": True, "sensors": {}, "model": None,
          "counters": {"targets": 10, "errors_total": 0}}],
        [{"cell": "c", "uptime_s": 61.0, "healthy": True, "sensors": {}, "model": None,
          "counters": {"targets": 12, "errors_total": 1}}],
    ])
    network = types.SimpleNamespace(statuses=lambda cell, timeout_s: next(samples))
    out = Terminal()
    args = argparse.Namespace(json=False, watch=0.01, count=2, cell=None, timeout=1.0, prefix="nanodrift")
    assert status_command.watch(network, args, out, sleep=lambda s: None) == 0
    screens = out.getvalue().split(status_command.CLEAR)
    assert screens[0] == "" and len(screens) == 3  # each refresh starts by clearing the screen
    second = parse_table(screens[2].split("\n", 1)[1])["c"]
    assert second["TARGETS/MIN"] == "120.0" and second["REFUSED/MIN"] == "60.0"  # over the last 1 s


def test_table_shows_the_adaptations_correction() -> None:
    base = {"cell": "c", "healthy": True, "uptime_s": 60.0, "sensors": {}, "model": {"id": "m-1"},
            "counters": {"targets": 0, "errors": {}}}
    adapting = {**base, "health": {"state": "ok", "residual_rms_nm": 20.0, "correction_um": -0.0124}}
    off = {**base, "cell": "d", "health": {"state": "ok", "residual_rms_nm": 20.0, "correction_um": None}}
    rows = parse_table(table([adapting, off]))
    assert rows["c"]["CORRECTION"] == "-12 nm" and rows["d"]["CORRECTION"] == "-"
    assert rows["c"]["HEALTH"] == "ok 20 nm"  # the column sits beside HEALTH, which keeps its own value
