"""End-to-end harness: the daemon as a separate process, a real Zenoh client over 127.0.0.1.

- ``FILE_PLUGIN`` (kind ``file``): a test-only driver plugin whose readings come from a JSON file
  the test rewrites atomically. It is registered through a real entry point (a ``*.dist-info``
  directory put on the daemon's ``PYTHONPATH``), exactly as a lab's own driver package would be.
  The file ``{"values": {ch: degC}, "age": {ch: s}, "fault": {ch: reason}, "error": msg}`` lets a
  test make a channel stale (its readings are ``age`` seconds old), faulted, or the whole device fail.
- :class:`Daemon`: ``python -m nanodrift.cli run --config F`` with stderr (JSON log lines) in a file.
- :class:`Client`: a client-mode Zenoh session (multicast scouting off) that collects ``command``
  and ``error`` samples and sends targets by put or by query.
- :func:`run_cli`: a command that serves nothing (``target``, ``status``, ``check-config``,
  ``confirm-output``) run in the test's process: the daemon is the process a test needs, not its clients.

Every wait is bounded and polls a condition; nothing sleeps and hopes.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import zenoh

from helpers.file_plugin import PLUGIN as PLUGIN  # the file plugin, re-exported (see below)
from helpers.file_plugin import FileGroup as FileGroup
from helpers.file_plugin import FilePlugin as FilePlugin
from helpers.file_plugin import FileSensorConfig as FileSensorConfig
from helpers.modbus_helpers import free_port  # one definition for every helper (re-exported here)
from nanodrift.atomic import atomic_write_text
from nanodrift.bus.protocol import DEFAULT_PREFIX, key_prefix
from nanodrift.client import client_config as library_client_config
from nanodrift.model.model import FittedTerm, Model, Training, save_model
from nanodrift.model.terms import parse_term

REPO = Path(__file__).resolve().parents[2]
TESTS = Path(__file__).resolve().parents[1]


# --- the test-only driver plugin -----------------------------------------------------------------

# FileSensorConfig, FileGroup, FilePlugin and PLUGIN (imported above) live in helpers.file_plugin, the one module
# a daemon imports for them: this one's imports would cost each daemon's start a tenth of a second of CPU


def install_file_plugin(directory: Path) -> Path:
    """A dist-info declaring ``file = helpers.file_plugin:PLUGIN`` in ``nanodrift.drivers``; returns the dir."""
    info = directory / "nanodrift_test_drivers-0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: nanodrift-test-drivers\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text("[nanodrift.drivers]\nfile = helpers.file_plugin:PLUGIN\n")
    return directory


class SensorFile:
    """The JSON file the ``file`` plugin reads; every write is atomic."""

    def __init__(self, path: Path, values: dict[str, float]) -> None:
        self.path = path
        self.doc: dict[str, Any] = {"values": dict(values)}
        self.write()

    def write(self, **changes: Any) -> None:
        self.doc.update(changes)
        atomic_write_text(self.path, json.dumps(self.doc))

    def set(self, **values: float) -> None:
        self.write(values={**self.doc["values"], **values})


# --- a small known model -------------------------------------------------------------------------

TEMPS = {"T1": 21.8, "T2": 21.9}
MODEL_TERMS = {"x^3": 2.0e-8, "x^2": -1.0e-5, "x": 1.002, "T1": -0.6, "T2": -0.5, "1": 0.5}
MODEL_CHANNEL_RANGES = {"T1": (21.5, 22.1), "T2": (21.6, 22.05)}


def write_test_model(path: Path, terms: dict[str, float] | None = None) -> Model:
    model = Model(
        terms=[FittedTerm(parse_term(name), coef) for name, coef in (terms or MODEL_TERMS).items()],
        training=Training(x_range=(0.0, 480.0), channel_ranges=dict(MODEL_CHANNEL_RANGES), rows=100, t_span_s=3600.0),
        provenance={"source": "tests/helpers/daemon_harness.py"},
    )
    save_model(model, path)
    return model


def expected_q(x: float, temps: dict[str, float], terms: dict[str, float] | None = None) -> float:
    c = terms or MODEL_TERMS
    return c["x^3"] * x**3 + c["x^2"] * x**2 + c["x"] * x + c["T1"] * temps["T1"] + c["T2"] * temps["T2"] + c["1"]


# --- processes and sessions ----------------------------------------------------------------------


def wait_until(predicate: Callable[[], Any], timeout: float, what: str, interval: float = 0.01) -> Any:
    """Poll ``predicate`` until truthy; AssertionError naming ``what`` after ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
        time.sleep(interval)


def file_sensor_config(
    tmp: Path,
    *,
    cell: str,
    port: int,
    model_path: Path,
    sensor_file: Path,
    channels: Sequence[str] = ("T1", "T2"),
    max_age_s: float = 2.0,
    interval_s: float = 0.05,
    actuator: str | None = "",
    extra: str = "",
    zenoh_file: Path | None = None,
) -> str:
    """A cell config reading ``channels`` from the ``file`` plugin; ``actuator=None``: no ``[actuator]`` table (a
    cell of ``[[axes]]`` in ``extra``)."""
    sensors = "".join(
        f'\n[[sensors]]\nname = "{ch}"\nkind = "file"\npath = "{sensor_file}"\ninterval_s = {interval_s}\n'
        f"max_age_s = {max_age_s}\ntimeout_s = 0.5\n"
        for ch in channels
    )
    return (
        f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
        + (f'config_file = "{zenoh_file}"\n' if zenoh_file else "")
        + f'[model]\npath = "{model_path}"\n'
        + ("" if actuator is None else f"[actuator]\n{actuator}\n")
        + f"{extra}\n{sensors}"
    )


class Daemon:
    """``python -m nanodrift.cli run`` in its own process; its JSON log lines are parsed on demand."""

    def __init__(self, args: Sequence[str], log_path: Path, extra_pythonpath: Sequence[Path] = (),
                 env: dict[str, str] | None = None, cwd: Path = REPO) -> None:
        self.log_path = log_path
        environ = dict(os.environ)
        paths = [str(p) for p in extra_pythonpath] + [str(TESTS), str(REPO)]
        if environ.get("PYTHONPATH"):
            paths.append(environ["PYTHONPATH"])
        environ["PYTHONPATH"] = os.pathsep.join(paths)
        environ["PYTHONUNBUFFERED"] = "1"
        environ.update(env or {})
        self._log_file = open(log_path, "wb")
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "nanodrift.cli", "run", *args],
            stdout=subprocess.DEVNULL, stderr=self._log_file, env=environ, cwd=str(cwd),
        )

    def logs(self) -> list[dict[str, Any]]:
        out = []
        for line in self.log_path.read_text(errors="replace").splitlines():
            try:
                doc = json.loads(line)
            except ValueError:
                continue
            if isinstance(doc, dict):
                out.append(doc)
        return out

    def log_events(self, event: str) -> list[dict[str, Any]]:
        return [d for d in self.logs() if d.get("event") == event]

    def wait_log(self, event: str, timeout: float = 10.0, count: int = 1) -> dict[str, Any]:
        def found() -> Any:
            self.check_alive()
            events = self.log_events(event)
            return events[count - 1] if len(events) >= count else None

        return wait_until(found, timeout, f"log event {event!r} x{count}")

    def check_alive(self) -> None:
        if self.proc.poll() is not None:
            raise AssertionError(f"daemon exited with {self.proc.returncode}:\n{self.log_path.read_text()[-3000:]}")

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self, timeout: float = 10.0) -> int:
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            try:
                self.proc.wait(timeout)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(5)
        self._log_file.close()
        return self.proc.returncode


def run_cli(*args: str, pythonpath: Sequence[Path] = (), cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """``nanodrift <args>`` run by the console script's own ``main`` in this process: its exit code, stdout and
    stderr. A command that only talks to a daemon or writes a file needs no process of its own, and a Python
    start-up costs half a second of CPU. ``pythonpath``: directories of driver plugins the command's config names
    (``*.dist-info`` entry points, as :func:`install_file_plugin` writes), on the path for the call only.
    ``cwd``: the working directory for the call (relative paths in ``args``).
    (tests/conftest.py resets structlog per test, as a fresh process has it.)"""
    from nanodrift.cli import main  # the command line's imports, only where a test runs a command
    from nanodrift.drivers import registry

    paths = [str(p) for p in pythonpath]
    sys.path[:0] = paths
    registry.available.cache_clear()
    registry.load_plugin.cache_clear()
    out, err = io.StringIO(), io.StringIO()
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), contextlib.chdir(cwd or Path.cwd()):
            try:
                code = main(list(args))
            except SystemExit as exit_:  # argparse refusing the arguments, as the console script exits
                code = exit_.code if isinstance(exit_.code, int) else 2
    finally:
        for path in paths:
            sys.path.remove(path)
        registry.available.cache_clear()
        registry.load_plugin.cache_clear()
    return subprocess.CompletedProcess(["nanodrift", *args], code, out.getvalue(), err.getvalue())


def client_config(port: int) -> zenoh.Config:
    """A client-mode session towards the daemon on 127.0.0.1 (scouting off): the library's own config."""
    return library_client_config(f"tcp/127.0.0.1:{port}")


class Client:
    """A client session on the daemon's cell that records every command and error published (the raw
    answers, which many tests inspect; a lab's script uses :class:`nanodrift.Client`)."""

    def __init__(self, port: int, cell: str, prefix: str = DEFAULT_PREFIX) -> None:
        self.prefix = key_prefix(cell, prefix)
        self.session = zenoh.open(client_config(port))
        self._cond = threading.Condition()
        self.commands: list[dict[str, Any]] = []
        self.errors: list[dict[str, Any]] = []
        self.telemetry: dict[str, dict[str, Any]] = {}
        self._subs = [
            self.session.declare_subscriber(f"{self.prefix}/command", self._record(self.commands)),
            self.session.declare_subscriber(f"{self.prefix}/error", self._record(self.errors)),
            self.session.declare_subscriber(f"{self.prefix}/sensors/**", self._telemetry),
        ]
        self._target_pub = self.session.declare_publisher(
            f"{self.prefix}/target", congestion_control=zenoh.CongestionControl.BLOCK
        )

    def _record(self, into: list[dict[str, Any]]) -> Callable[[zenoh.Sample], None]:
        def callback(sample: zenoh.Sample) -> None:
            doc = json.loads(sample.payload.to_bytes())
            with self._cond:
                into.append(doc)
                self._cond.notify_all()

        return callback

    def _telemetry(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)[len(self.prefix) + len("/sensors/"):]
        with self._cond:
            self.telemetry[key] = json.loads(sample.payload.to_bytes())
            self._cond.notify_all()

    def wait(self, predicate: Callable[[], Any], timeout: float, what: str) -> Any:
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                value = predicate()
                if value:
                    return value
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"timed out after {timeout:g} s waiting for {what}")
                self._cond.wait(remaining)

    def answers_for(self, target_id: Any) -> list[tuple[str, dict[str, Any]]]:
        with self._cond:
            return [("command", c) for c in self.commands if c.get("id") == target_id] + [
                ("error", e) for e in self.errors if e.get("id") == target_id
            ]

    def put(self, payload: bytes | str) -> None:
        self._target_pub.put(payload)

    def query(self, payload: bytes | str | dict[str, Any], timeout: float = 5.0) -> tuple[bool, dict[str, Any]]:
        """One ``compensate`` query: (True, command) or (False, error object)."""
        if isinstance(payload, dict):
            payload = json.dumps(payload)
        replies = list(self.session.get(f"{self.prefix}/compensate", payload=payload, timeout=timeout))
        assert len(replies) == 1, f"expected exactly one reply, got {len(replies)}"
        reply = replies[0]
        if reply.ok is not None:
            return True, json.loads(reply.ok.payload.to_bytes())
        raw = reply.err.payload.to_bytes()
        try:
            return False, json.loads(raw)
        except ValueError:  # not the daemon's error object: zenoh's own ("Timeout")
            raise AssertionError(f"no answer from the daemon within {timeout:g} s: zenoh says {raw!r}") from None

    def status(self, timeout: float = 5.0) -> dict[str, Any]:
        replies = list(self.session.get(f"{self.prefix}/status", timeout=timeout))
        assert len(replies) == 1 and replies[0].ok is not None, f"status replies: {replies}"
        return json.loads(replies[0].ok.payload.to_bytes())

    def alive(self, timeout: float = 2.0) -> bool:
        return any(r.ok is not None for r in self.session.liveliness().get(f"{self.prefix}/alive", timeout=timeout))

    def wait_alive(self, timeout: float = 15.0) -> None:
        wait_until(lambda: self.alive(0.5), timeout, f"liveliness token {self.prefix}/alive")

    def wait_ready(self, channels: Sequence[str], timeout: float = 15.0) -> dict[str, Any]:
        """Until status shows every channel ok (the daemon has read its sensors)."""

        def ready() -> Any:
            try:
                status = self.status(1.0)
            except AssertionError:
                return None
            sensors = status["sensors"]
            return status if all(sensors.get(c, {}).get("state") == "ok" for c in channels) else None

        return wait_until(ready, timeout, f"channels {list(channels)} ok in status", interval=0.05)

    def close(self) -> None:
        self.session.close()


class Served:
    """A daemon on the ``file`` plugin with the test model, and a client connected to it."""

    def __init__(self, root: Path, cell: str, channels: Sequence[str] = ("T1", "T2"), actuator: str = "",
                 env: dict[str, str] | None = None, zenoh_file: Path | None = None) -> None:
        self.root = root
        self.cell = cell
        self.zenoh_file = zenoh_file  # a zenoh json5 for the daemon's session ([zenoh] config_file)
        self.port = free_port()
        self.plugin_dir = install_file_plugin(root / "plugins")
        self.model_path = root / "model.json"
        self.model = write_test_model(self.model_path)
        self.sensors = SensorFile(root / "sensors.json", TEMPS)
        self.config_path = root / "nanodrift.toml"
        self.write_config(channels=channels, actuator=actuator)
        self.daemon = Daemon(["--config", str(self.config_path)], root / "daemon.log", [self.plugin_dir], env=env)
        self.daemon.wait_log("serving", timeout=30)  # listening: a client-mode session can connect
        self.client = Client(self.port, cell)

    def write_config(self, channels: Sequence[str] = ("T1", "T2"), actuator: str = "", extra: str = "") -> None:
        self.config_path.write_text(
            file_sensor_config(self.root, cell=self.cell, port=self.port, model_path=self.model_path,
                               sensor_file=self.sensors.path, channels=channels, actuator=actuator, extra=extra,
                               zenoh_file=self.zenoh_file)
        )

    def start(self, channels: Sequence[str] = ("T1", "T2")) -> Served:
        self.client.wait_alive()
        self.client.wait_ready(channels)
        return self

    def close(self) -> int:
        self.client.close()
        return self.daemon.stop()


class HealthCell:
    """A daemon on a config, a client, and every ``health`` sample the client received."""

    def __init__(self, root: Path, cell: str, config: str, plugins: Path | None = None) -> None:
        self.port = free_port()
        self.config_path = root / "nanodrift.toml"
        self.config_path.write_text(config.replace("@PORT@", str(self.port)))
        self.daemon = Daemon(["--config", str(self.config_path)], root / "daemon.log",
                             [plugins] if plugins is not None else [])
        self.client: Client | None = None
        self.health_samples: list[dict[str, Any]] = []
        self._lock = threading.Lock()
        try:
            self.daemon.wait_log("serving", timeout=30)
            self.client = Client(self.port, cell)
            self._sub = self.client.session.declare_subscriber(f"nanodrift/{cell}/health", self._health)
        except BaseException:
            self.close()
            raise

    def _health(self, sample: Any) -> None:
        with self._lock:
            self.health_samples.append(json.loads(sample.payload.to_bytes()))

    def samples(self) -> list[dict[str, Any]]:
        with self._lock:
            return list(self.health_samples)

    def health(self) -> dict[str, Any]:
        assert self.client is not None
        return self.client.status()["health"]

    def settle(self, x: float, target_id: object) -> dict[str, Any]:
        """Serve ``x`` and wait until the health unit has its settled residual; the command."""
        assert self.client is not None
        before = self.health()["n"]
        ok, command = self.client.query({"x_um": x, "id": target_id})
        assert ok, command
        wait_until(lambda: self.health()["n"] > before, 15, f"the settled residual of target {target_id}",
                   interval=0.02)
        return command

    def close(self) -> int:
        if self.client is not None:
            self.client.close()
        return self.daemon.stop()
