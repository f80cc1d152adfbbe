"""``nanodrift.Client`` against real daemons (``nanodrift run`` subprocesses, real Zenoh over 127.0.0.1), and
``[zenoh] prefix``: a cell under its own key tree, nothing of it left under ``nanodrift/``.

The daemon's ``done`` and ``stop`` at length (a move that waits for ``reached``, a stop that ends a ramp)
are in ``test_client_done.py``; the client's waiting logic on a stand-in cell in ``test_client_fake_cell.py``.
Every wait is on an event (a reply, a sample) or a bounded poll of one, never a bare sleep.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers.daemon_harness import (
    REPO,
    TEMPS,
    Daemon,
    SensorFile,
    Served,
    client_config,
    expected_q,
    file_sensor_config,
    free_port,
    install_file_plugin,
    run_cli,
    wait_until,
    write_test_model,
)

import nanodrift
from nanodrift import Client, Command, MoveEnded, Refused
from nanodrift.config import ConfigError, load_config

PREFIX = "femto/lab3/stages"


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = Served(tmp_path_factory.mktemp("client"), "libcell").start()
    yield s
    s.close()


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


class PrefixedCell:
    """A daemon (file plugin, the harness' model) whose config says ``[zenoh] prefix``."""

    def __init__(self, root: Path, cell: str, prefix: str, connect: str | None = None) -> None:
        self.cell = cell
        self.port = free_port()
        plugins = install_file_plugin(root / "plugins")
        self.model = write_test_model(root / "model.json")
        self.sensors = SensorFile(root / "sensors.json", TEMPS)
        text = file_sensor_config(root, cell=cell, port=self.port, model_path=root / "model.json",
                                  sensor_file=self.sensors.path)
        text = text.replace("[zenoh]\n", f'[zenoh]\nprefix = "{prefix}"\n', 1)
        if connect:
            text = text.replace("[zenoh]\n", f'[zenoh]\nconnect = ["{connect}"]\n', 1)
        self.config = root / "nanodrift.toml"
        self.config.write_text(text)
        self.daemon = Daemon(["--config", str(self.config)], root / "daemon.log", [plugins])
        self.daemon.wait_log("serving", timeout=30)

    def close(self) -> int:
        return self.daemon.stop()


def wait_ready(cell: Client, timeout_s: float = 30.0) -> dict[str, Any]:
    """Until the cell's status shows every temperature channel ok (polled, bounded: the harness' way)."""
    def ready() -> dict[str, Any] | None:
        try:
            doc = cell.status(timeout_s=1.0)
        except TimeoutError:
            return None
        temperatures = [s for s in doc["sensors"].values() if s.get("role") == "temperature"]
        return doc if temperatures and all(s.get("state") == "ok" for s in temperatures) else None

    return wait_until(ready, timeout_s, f"cell {cell.cell}'s temperatures ok", interval=0.1)


# --- the package's surface --------------------------------------------------------------------------


def test_import_nanodrift_loads_neither_zenoh_nor_numpy_until_a_name_is_used() -> None:
    code = ("import sys, nanodrift, nanodrift.model.terms\n"
            "assert 'zenoh' not in sys.modules, 'zenoh'\n"
            "print(sorted(n for n in nanodrift.__all__))\n"
            "nanodrift.read_csv\n"
            "assert 'zenoh' not in sys.modules, 'zenoh after read_csv'\n"
            "nanodrift.Client\n"
            "assert 'zenoh' in sys.modules\n")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert result.returncode == 0, result.stderr
    assert {"Client", "MoveEnded", "Refused", "load_model", "read_csv", "write_csv"} <= set(eval(result.stdout))
    with pytest.raises(AttributeError, match="no attribute 'nothing'"):
        nanodrift.nothing  # noqa: B018


def test_load_model_predicts_a_data_table_one_axis_and_two(tmp_path: Path) -> None:
    one = nanodrift.load_model(REPO / "daemon" / "data" / "default_model.json")
    xy = nanodrift.load_model(REPO / "daemon" / "data" / "default_model_xy.json")
    data = nanodrift.read_csv(REPO / "daemon" / "data" / "sample_calibration.csv")
    q = one.predict(data)
    assert q.shape == (len(data),) and abs(float(q[0]) - float(data.q[0])) < 1.0  # the model of this cell
    nanodrift.write_csv(data, tmp_path / "copy.csv", {"q_pred_um": q})
    again = nanodrift.read_csv(tmp_path / "copy.csv")
    assert list(again.extra["q_pred_um"]) == list(q)
    assert set(xy.axes) == {"x", "y"}


# --- moves, refusals, status ------------------------------------------------------------------------


def test_move_without_waiting_returns_the_answered_command(served: Served) -> None:
    with Client(endpoint(served.port), cell=served.cell) as cell:
        first = cell.move(240.0, wait=False)
        second = cell.move(120.5, wait=False, timeout_s=5.0)
    assert isinstance(first, Command) and first.done is None
    assert first.q_um == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)
    assert first.target == 240.0 and first.payload["x_um"] == 240.0 and first.model == served.model.id
    assert isinstance(first.voltage_v, float) and first.extrapolating == [] and first.q_sigma_um is None
    assert isinstance(first.id, str) and first.id != second.id and first.payload["id"] == first.id
    with Client(endpoint(served.port), cell=served.cell) as other:  # another client never reuses an id
        assert other.move(10.0, wait=False).id not in (first.id, second.id)


def test_a_refused_target_raises_refused_with_kind_error_and_id(served: Served) -> None:
    with Client(endpoint(served.port), cell=served.cell) as cell:
        for wait in (False, True):
            with pytest.raises(Refused) as caught:
                cell.move(750.0, wait=wait, timeout_s=5.0)
            refused = caught.value
            assert refused.kind == "out_of_workspace", refused.payload
            assert "x_um 750 outside the workspace [0, 500] µm" in refused.error
            assert isinstance(refused.id, str) and refused.payload["id"] == refused.id


def test_status_is_the_cells_payload_naming_it(served: Served) -> None:
    with Client([endpoint(served.port)], cell=served.cell) as cell:
        doc = cell.status()
    assert doc["cell"] == served.cell and set(doc["sensors"]) == {"T1", "T2"}


def test_a_cell_nobody_serves_is_a_timeout_naming_the_cells_that_answer(served: Served) -> None:
    with Client(endpoint(served.port), cell="nosuchcell") as cell:
        with pytest.raises(TimeoutError, match=f"no daemon serves cell 'nosuchcell'.*{served.cell}"):
            cell.move(1.0, timeout_s=0.5)
        with pytest.raises(TimeoutError, match="nanodrift/nosuchcell/status"):
            cell.status(timeout_s=0.5)


def test_no_daemon_at_the_endpoint_is_a_connection_error_naming_it() -> None:
    port = free_port()
    with pytest.raises(ConnectionError, match=f"nobody is listening at tcp/127.0.0.1:{port}"):
        Client(endpoint(port), cell="cell0")
    with pytest.raises(FileNotFoundError, match=r"zenoh_config nowhere\.json5: no such file"):
        Client(endpoint(port), cell="cell0", zenoh_config="nowhere.json5")
    with pytest.raises(ValueError, match="prefix: 'a/\\*' has a wildcard"):
        Client(endpoint(port), cell="cell0", prefix="a/*")


def test_close_is_idempotent_and_a_closed_client_says_so(served: Served) -> None:
    cell = Client(endpoint(served.port), cell=served.cell)
    cell.close()
    cell.close()
    assert cell.closed
    with pytest.raises(RuntimeError, match="closed"):
        cell.move(1.0)


def test_a_waiting_move_is_safe_from_several_threads(served: Served) -> None:
    """Four threads share one client; each gets its own answer (ids never mixed)."""
    answers: dict[int, Command] = {}
    with Client(endpoint(served.port), cell=served.cell) as cell:
        def send(k: int) -> None:
            answers[k] = cell.move(float(10 * k), wait=False)

        threads = [threading.Thread(target=send, args=(k,)) for k in range(4)]
        for thread in threads:
            thread.start()
        for thread in threads:
            thread.join(30)
    assert sorted(answers) == [0, 1, 2, 3]
    assert all(answers[k].target == 10.0 * k for k in answers)
    assert len({c.id for c in answers.values()}) == 4


# --- the network's cells ----------------------------------------------------------------------------


def test_cells_finds_two_daemons_with_different_cells(served: Served, tmp_path: Path) -> None:
    other = PrefixedCell(tmp_path, "second", "nanodrift", connect=endpoint(served.port))
    try:
        def both() -> list[dict[str, Any]] | None:
            docs = Client.cells(endpoint(served.port), timeout_s=1.0)
            return docs if {d["cell"] for d in docs} >= {served.cell, "second"} else None

        docs = next((d for d in (both() for _ in range(30)) if d), None)
        assert docs is not None, "the two cells never both answered"
        assert [d["cell"] for d in docs] == sorted(d["cell"] for d in docs)
        assert Client.cells(endpoint(served.port), prefix="other/tree", timeout_s=0.5) == []
    finally:
        assert other.close() == 0


# --- [zenoh] prefix ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def prefixed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[PrefixedCell]:
    cell = PrefixedCell(tmp_path_factory.mktemp("prefixed"), "lab3cell", PREFIX)
    yield cell
    cell.close()


def test_a_prefixed_daemon_answers_under_its_prefix_and_nothing_under_nanodrift(prefixed: PrefixedCell) -> None:
    session = zenoh.open(client_config(prefixed.port))
    seen: dict[str, list[str]] = {"nanodrift": [], "prefix": []}
    lock = threading.Condition()

    def record(tree: str) -> Any:
        def callback(sample: zenoh.Sample) -> None:
            with lock:
                seen[tree].append(str(sample.key_expr))
                lock.notify_all()
        return callback

    subscribers = [session.declare_subscriber("nanodrift/**", record("nanodrift")),
                   session.declare_subscriber(f"{PREFIX}/**", record("prefix"))]
    try:
        with Client(endpoint(prefixed.port), cell=prefixed.cell, prefix=PREFIX) as cell:
            wait_ready(cell)
            command = cell.move(240.0, timeout_s=10.0)  # its done, under the prefix too
            assert command.q_um == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)
            assert command.done is not None and command.done["state"] == "reached"
            assert cell.stop()["held"] is True
            assert cell.status()["cell"] == prefixed.cell
            key = f"{PREFIX}/{prefixed.cell}/command"
            with lock:  # the command, then a telemetry sample published after it: the daemon has spoken since
                assert lock.wait_for(lambda: key in seen["prefix"], 10), seen["prefix"][-5:]
                after = len(seen["prefix"])
                assert lock.wait_for(lambda: any("/sensors/" in k for k in seen["prefix"][after:]), 10)
            with Client(endpoint(prefixed.port), cell=prefixed.cell) as default_prefix:
                with pytest.raises(TimeoutError, match=f"no daemon serves cell '{prefixed.cell}'"):
                    default_prefix.move(240.0, timeout_s=0.5)
        alive = [r.ok for r in session.liveliness().get(f"{PREFIX}/{prefixed.cell}/alive", timeout=2.0)]
        assert any(s is not None for s in alive)
        assert list(session.liveliness().get("nanodrift/**", timeout=1.0)) == []
        with lock:
            assert seen["nanodrift"] == []
            assert f"{PREFIX}/{prefixed.cell}/sensors/temperature/T1" in seen["prefix"]
    finally:
        for subscriber in subscribers:
            subscriber.undeclare()
        session.close()


def cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift ARGS`` in this process (a subprocess would cost each call half a second of CPU)."""
    return run_cli(*args)


def test_target_and_status_take_prefix(prefixed: PrefixedCell) -> None:
    with Client(endpoint(prefixed.port), cell=prefixed.cell, prefix=PREFIX) as cell:
        wait_ready(cell)
    ep = endpoint(prefixed.port)
    result = cli("target", "240", "--json", "-e", ep, "--cell", prefixed.cell, "--prefix", PREFIX)
    assert result.returncode == 0, result.stderr
    assert json.loads(result.stdout)["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)
    result = cli("status", "--json", "-e", ep, "--prefix", PREFIX)
    assert result.returncode == 0, result.stderr
    assert [d["cell"] for d in json.loads(result.stdout)] == [prefixed.cell]
    result = cli("status", "-e", ep, "--timeout", "0.5")  # the default prefix: nothing there
    assert result.returncode == 1 and "no cell answered on nanodrift/*/status" in result.stderr
    result = cli("status", "-e", ep, "--prefix", "bad//prefix")
    assert result.returncode == 2 and "argument --prefix: 'bad//prefix' has an empty chunk" in result.stderr


def test_a_reload_never_changes_the_prefix(tmp_path: Path) -> None:
    cell = PrefixedCell(tmp_path, "reloaded", PREFIX)
    try:
        cell.config.write_text(cell.config.read_text().replace(f'prefix = "{PREFIX}"', 'prefix = "other/tree"'))
        cell.daemon.signal(signal.SIGHUP)
        line = cell.daemon.wait_log("reload_needs_restart")
        assert "prefix" in line["detail"]
        cell.daemon.wait_log("reload_applied")
        with Client(endpoint(cell.port), cell="reloaded", prefix=PREFIX) as client:
            assert client.move(240.0, wait=False).q_um == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)
    finally:
        assert cell.close() == 0


@pytest.mark.parametrize(("prefix", "expected"), [
    ("femto/*", "wildcard or special character '*'"),
    ("lab/$x", "wildcard or special character '$'"),
    ("/lab", "starts or ends with '/'"),
    ("lab/", "starts or ends with '/'"),
    ("a//b", "empty chunk"),
    ("", "empty"),
    ("lab 3", "character(s) ' '"),
])
def test_a_bad_prefix_is_a_config_error_naming_the_field(tmp_path: Path, prefix: str, expected: str) -> None:
    path = tmp_path / "bad.toml"
    path.write_text(f'cell = "c"\n[zenoh]\nprefix = "{prefix}"\n')
    with pytest.raises(ConfigError) as caught:
        load_config(path)
    text = str(caught.value)
    assert "zenoh.prefix" in text and expected in text and "chunks of letters, digits" in text, text


def test_a_good_prefix_is_taken_and_the_default_keeps_every_key(tmp_path: Path) -> None:
    path = tmp_path / "good.toml"
    path.write_text(f'cell = "c"\n[zenoh]\nprefix = "{PREFIX}"\n')
    assert load_config(path).zenoh.prefix == PREFIX
    path.write_text('cell = "c"\n')
    assert load_config(path).zenoh.prefix == "nanodrift"


# --- a cell of several axes -------------------------------------------------------------------------


def xy_config(port: int, cell: str = "xy0") -> str:
    return (f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            '[simulation]\naxes = "xy"\nscenario = "room"\nspeed = 1.0\nseed = 0\n')


@pytest.fixture(scope="module")
def xy_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[int, str]]:
    root = tmp_path_factory.mktemp("xy")
    port = free_port()
    (root / "xy.toml").write_text(xy_config(port))
    daemon = Daemon(["--config", str(root / "xy.toml")], root / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        yield port, "xy0"
    finally:
        daemon.stop()


def test_an_xy_cell_moves_with_a_mapping_and_answers_per_axis(xy_cell: tuple[int, str]) -> None:
    port, name = xy_cell
    with Client(endpoint(port), cell=name) as cell:
        wait_ready(cell)
        command = cell.move({"x": 240.0, "y": 100.0}, wait=False)
        assert command.target == {"x": 240.0, "y": 100.0}
        assert isinstance(command.q_um, dict) and set(command.q_um) == {"x", "y"}
        assert isinstance(command.voltage_v, dict) and set(command.voltage_v) == {"x", "y"}
        assert isinstance(command.q_sigma_um, dict) and isinstance(command.extrapolating, list)
        assert abs(command.q_um["x"] - 240.0) < 5.0 and abs(command.q_um["y"] - 100.0) < 5.0
        with pytest.raises(Refused) as caught:
            cell.move(240.0, wait=False)  # one number for a cell of two axes: the daemon says which is missing
        assert caught.value.kind == "bad_payload" and "y_um" in caught.value.error
        with pytest.raises(Refused) as caught:
            cell.move({"x": 240.0, "y": 900.0}, wait=False)
        assert "y" in caught.value.error


def test_move_ended_carries_state_error_and_command() -> None:
    command = Command.from_payload({"id": "a-1", "x_um": 1.0, "q_um": 1.1, "voltage_v": 0.02, "temperatures_c": {},
                                    "model": "m", "t": 1.0, "extrapolating": ["T1"], "q_sigma_um": 0.01})
    ended = MoveEnded("failed", "PI error 7", command)
    assert (ended.state, ended.error, ended.command.id) == ("failed", "PI error 7", "a-1")
    assert "ended failed: PI error 7" in str(ended)
    assert command.extrapolating == ["T1"] and command.q_sigma_um == 0.01
