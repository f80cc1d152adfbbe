"""The shipped secure Zenoh config, over real sessions on 127.0.0.1 (issue 10, reproduction 4).

The daemon runs ``config/zenoh-secure.json5`` as shipped (only its credentials-file path is moved
to a temporary folder) with the shipped ``config/zenoh-credentials.example.txt``; clients use the
shipped ``config/zenoh-client.example.json5`` with ``-e`` pointing at the test port. A rogue is an
*authenticated* client (the lab's shared client password leaked, or a student's script) trying to
spoof the daemon: put on ``command``/``error``/``health``/``sensors``, answer ``compensate``,
announce a cell. Every "never" is checked after a sentinel target sent by the rogue *after* its
attempts has been answered: its messages travel the same link in order, so anything the daemon's
instance let through would have arrived first. The control test runs the same rogue against the
same config with ``access_control`` disabled and sees it succeed, so these tests can fail.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import threading
import time
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
    expected_q,
    file_sensor_config,
    free_port,
    install_file_plugin,
    run_cli,
    wait_until,
    write_test_model,
)

from nanodrift.bus.session import session_config as daemon_session_config
from nanodrift.config import load_config

CONFIG = REPO / "config"
SHIPPED_DICTIONARY = "/etc/nanodrift/zenoh-credentials.txt"
CELL = "secure"


class SecureCell:
    """The daemon on the ``file`` plugin with the shipped secure zenoh config."""

    def __init__(self, root: Path, *, access_control: bool = True, scheme: str = "tcp", transport: str = "",
                 client_transport: str = "") -> None:
        root.mkdir(parents=True, exist_ok=True)
        self.root = root
        self.port = free_port()
        credentials = root / "zenoh-credentials.txt"
        credentials.write_text((CONFIG / "zenoh-credentials.example.txt").read_text())
        text = (CONFIG / "zenoh-secure.json5").read_text()
        assert text.count(SHIPPED_DICTIONARY) == 1 and text.count("enabled: true") == 1
        text = text.replace(SHIPPED_DICTIONARY, str(credentials))
        if not access_control:
            text = text.replace("enabled: true", "enabled: false")
        text = text.replace("  transport: {\n", "  transport: {\n" + transport, 1)
        (root / "zenoh-secure.json5").write_text(text)
        self.model = write_test_model(root / "model.json")
        sensors = SensorFile(root / "sensors.json", TEMPS)
        toml = file_sensor_config(root, cell=CELL, port=self.port, model_path=root / "model.json",
                                  sensor_file=sensors.path)
        # relative to the .toml, as README's install step writes it
        toml = toml.replace("[zenoh]\n", '[zenoh]\nconfig_file = "zenoh-secure.json5"\n', 1)
        toml = toml.replace(f"tcp/127.0.0.1:{self.port}", f"{scheme}/127.0.0.1:{self.port}")
        (root / "nanodrift.toml").write_text(toml)
        self.daemon = Daemon(["--config", str(root / "nanodrift.toml")], root / "daemon.log",
                             [install_file_plugin(root / "plugins")])
        try:
            self.daemon.wait_log("serving", timeout=30)
            self.client_config = client_file(root, "client.json5", transport=client_transport)
            watcher = open_session(self.client_config, self.port, scheme)
            try:
                wait_until(lambda: status_ok(watcher), 20, "status with T1, T2 ok over an authenticated session",
                           interval=0.05)
            finally:
                watcher.close()
        except BaseException:
            self.daemon.stop()  # never leave a daemon behind a failed start
            raise

    def close(self) -> int:
        return self.daemon.stop()


def client_file(root: Path, name: str, *, password: str | None = None, credentials: bool = True,
                transport: str = "") -> Path:
    """The shipped client example, verbatim or with the password changed or the credentials removed."""
    text = (CONFIG / "zenoh-client.example.json5").read_text()
    text = text.replace("  transport: {\n", "  transport: {\n" + transport, 1)
    shipped = 'password: "CHANGE-ME-client-password"'
    assert shipped in text
    if password is not None:
        text = text.replace(shipped, f'password: "{password}"')
    if not credentials:
        start, end = text.index("  transport: {"), text.rindex("}")
        text = text[:start] + text[end:]
    path = root / name
    path.write_text(text)
    return path


def session_config(path: Path, port: int, mode: str | None = None, scheme: str = "tcp") -> zenoh.Config:
    conf = zenoh.Config.from_file(str(path))
    host = "localhost" if scheme == "tls" else "127.0.0.1"  # TLS checks the name in the certificate
    conf.insert_json5("connect/endpoints", json.dumps([f"{scheme}/{host}:{port}"]))
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    return conf


def open_session(path: Path, port: int, scheme: str = "tcp") -> zenoh.Session:
    return zenoh.open(session_config(path, port, scheme=scheme))


def status_ok(session: zenoh.Session) -> bool:
    for reply in session.get(f"nanodrift/{CELL}/status", timeout=1.0):
        if reply.ok is not None:
            sensors = json.loads(reply.ok.payload.to_bytes())["sensors"]
            return all(sensors.get(c, {}).get("state") == "ok" for c in TEMPS)
    return False


def nanodrift_target(config: Path, port: int, endpoint: str = "tcp/127.0.0.1") -> subprocess.CompletedProcess[str]:
    """``nanodrift target 240`` as a lab's client runs it, with its zenoh config file."""
    return run_cli("target", "240", "--cell", CELL, "--json", "--timeout", "3", "--zenoh-config", str(config),
                   "-e", f"{endpoint}:{port}")


ROGUE_COMMAND = {"id": "rogue", "x_um": 240.0, "q_um": 1000.0, "voltage_v": 1000.0, "temperatures_c": {},
                 "model": "rogue", "t": 0.0}
SPOOFED_KEYS = ["command", "error", "done", "health", "sensors/position", "sensors/temperature/T1"]


class Spoof:
    """An authenticated rogue session and an authenticated listener on the same daemon."""

    def __init__(self, cell: SecureCell) -> None:
        self.prefix = f"nanodrift/{CELL}"
        self.lock = threading.Condition()
        self.samples: list[tuple[str, dict[str, Any]]] = []
        self.listener = open_session(cell.client_config, cell.port)
        self.rogue = open_session(cell.client_config, cell.port)
        self._declared = [self.listener.declare_subscriber("nanodrift/**", self._record)]

    def _record(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), json.loads(sample.payload.to_bytes())))
            self.lock.notify_all()

    def rogue_samples(self) -> list[tuple[str, dict[str, Any]]]:
        with self.lock:
            return [(k, doc) for k, doc in self.samples if doc.get("model") == "rogue" or doc.get("rogue")]

    def sentinel(self, name: str) -> dict[str, Any]:
        """The rogue sends a target after its attempts; the daemon's command for it is the barrier.

        Sent again every half second until answered: right after the sessions open, the first put
        can precede the routes (declarations still propagating) and reach no one."""
        sent = [0.0]

        def answered() -> dict[str, Any] | None:
            with self.lock:
                found = next((doc for k, doc in self.samples
                              if k == f"{self.prefix}/command" and doc.get("id") == name), None)
            if found is None and time.monotonic() - sent[0] > 0.5:
                self.rogue.put(f"{self.prefix}/target", json.dumps({"x_um": 100.0, "id": name}))
                sent[0] = time.monotonic()
            return found

        return wait_until(answered, 10, f"the daemon's command for target {name!r}")

    def put_everywhere(self) -> None:
        """Puts on the daemon's keys, on a wildcard covering them, and on another (fake) cell."""
        payload = json.dumps({**ROGUE_COMMAND, "rogue": True})
        for key in SPOOFED_KEYS:
            self.rogue.put(f"{self.prefix}/{key}", payload)
        self.rogue.put("nanodrift/**", payload)
        self.rogue.put("nanodrift/ghost/command", payload)

    def answer_compensate(self) -> None:
        """Queryables a rogue would use to answer targets, and an alive token for a fake cell."""
        rogue_reply = json.dumps({**ROGUE_COMMAND, "rogue": True})

        def reply(query: zenoh.Query) -> None:
            query.reply(f"{self.prefix}/compensate", rogue_reply)

        self._declared += [
            self.rogue.declare_queryable(f"{self.prefix}/compensate", reply),
            self.rogue.declare_queryable("nanodrift/*/compensate", reply),
            self.rogue.liveliness().declare_token("nanodrift/ghost/alive"),
        ]

    def compensate_replies(self) -> list[dict[str, Any]]:
        """Every reply to one compensate query, from every queryable, none merged away by consolidation."""
        replies = self.listener.get(f"{self.prefix}/compensate", payload=json.dumps({"x_um": 240.0, "id": "q"}),
                                    target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                                    timeout=3.0)
        return [json.loads(r.ok.payload.to_bytes()) for r in replies if r.ok is not None]

    def alive_cells(self) -> list[str]:
        return sorted(str(r.ok.key_expr) for r in self.listener.liveliness().get("nanodrift/*/alive", timeout=2.0)
                      if r.ok is not None)

    def close(self) -> None:
        self.listener.close()
        self.rogue.close()


@pytest.fixture(scope="module")
def cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SecureCell]:
    served = SecureCell(tmp_path_factory.mktemp("secure"))
    yield served
    assert served.close() == 0


@pytest.fixture
def spoof(cell: SecureCell) -> Iterator[Spoof]:
    s = Spoof(cell)
    yield s
    s.close()


def test_an_authenticated_client_gets_its_target_served(cell: SecureCell) -> None:
    result = nanodrift_target(cell.client_config, cell.port)
    assert result.returncode == 0, result.stderr
    [answer] = [json.loads(line) for line in result.stdout.splitlines()]
    assert answer["id"] == 0 and answer["model"] == cell.model.id
    assert answer["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)


def test_an_authenticated_client_hears_done_and_can_stop(cell: SecureCell) -> None:
    session = open_session(cell.client_config, cell.port)
    try:
        dones: list[dict[str, Any]] = []
        heard = threading.Event()

        def done(sample: zenoh.Sample) -> None:  # only this test's command: the previous test's may end late
            doc = json.loads(sample.payload.to_bytes())
            if doc.get("id") == "d":
                dones.append(doc)
                heard.set()

        subscriber = session.declare_subscriber(f"nanodrift/{CELL}/done", done)
        wait_until(lambda: status_ok(session), 20, "status over an authenticated session", interval=0.05)
        replies = list(session.get(f"nanodrift/{CELL}/compensate", payload=json.dumps({"x_um": 120.0, "id": "d"}),
                                   timeout=5.0))
        assert len(replies) == 1 and replies[0].ok is not None
        command = json.loads(replies[0].ok.payload.to_bytes())
        assert heard.wait(10), "no done through the access control"
        assert dones == [{**dones[0], "state": "reached", "voltage_v": command["voltage_v"], "error": None}]
        replies = list(session.get(f"nanodrift/{CELL}/stop", payload=json.dumps({"id": "s"}), timeout=5.0))
        assert len(replies) == 1 and replies[0].ok is not None, replies
        assert json.loads(replies[0].ok.payload.to_bytes()) == {"id": "s", "voltage_v": command["voltage_v"],
                                                                "held": True}
        subscriber.undeclare()
    finally:
        session.close()


@pytest.mark.parametrize("who", ["no credentials", "wrong password"])
def test_a_client_without_credentials_or_with_a_wrong_password_gets_no_answer(cell: SecureCell, who: str) -> None:
    config = (client_file(cell.root, "anonymous.json5", credentials=False) if who == "no credentials"
              else client_file(cell.root, "wrong.json5", password="not-the-password"))
    result = nanodrift_target(config, cell.port)
    assert result.returncode != 0
    assert "q_um" not in result.stdout and "cannot open a zenoh session" in result.stderr
    # a peer opens without its connection and then waits in vain: no reply, no token, no telemetry
    outsider = zenoh.open(session_config(config, cell.port, mode="peer"))
    try:
        heard: list[str] = []
        subscriber = outsider.declare_subscriber("nanodrift/**", lambda s: heard.append(str(s.key_expr)))
        replies = list(outsider.get(f"nanodrift/{CELL}/compensate", payload=json.dumps({"x_um": 240.0}),
                                    timeout=2.0))
        assert replies == []
        assert list(outsider.liveliness().get(f"nanodrift/{CELL}/alive", timeout=1.0)) == []
        assert heard == []  # sensors are published every 50 ms to whoever may hear them
        subscriber.undeclare()
    finally:
        outsider.close()
    # the daemon was serving all along
    assert nanodrift_target(cell.client_config, cell.port).returncode == 0


def test_an_authenticated_client_cannot_put_on_the_daemons_keys(spoof: Spoof) -> None:
    spoof.sentinel("ready")  # the listener's subscription is in place: it hears the daemon
    spoof.put_everywhere()
    spoof.answer_compensate()  # (also declares the ghost cell's alive token)
    command = spoof.sentinel("after-puts")
    assert command["model"] != "rogue" and command["q_um"] == pytest.approx(expected_q(100.0, TEMPS), abs=1e-9)
    assert spoof.rogue_samples() == []
    assert spoof.alive_cells() == [f"nanodrift/{CELL}/alive"]  # no fake cell announced

    def telemetry_heard() -> set[str] | None:  # the daemon's own samples do reach clients
        with spoof.lock:
            keys = {k for k, _ in spoof.samples}
        return keys if f"nanodrift/{CELL}/sensors/temperature/T1" in keys else None

    keys = wait_until(telemetry_heard, 10, "the daemon's telemetry at the listener")
    assert f"nanodrift/{CELL}/command" in keys and spoof.rogue_samples() == []
    assert f"nanodrift/{CELL}/target" not in keys  # nor does a client receive other clients' targets


def test_an_authenticated_client_cannot_answer_compensate(cell: SecureCell, spoof: Spoof) -> None:
    spoof.answer_compensate()
    spoof.sentinel("after-declare")  # the rogue's declarations reached the daemon's instance first
    replies = spoof.compensate_replies()
    assert [r.get("rogue", False) for r in replies] == [False]
    assert replies[0]["model"] == cell.model.id
    result = nanodrift_target(cell.client_config, cell.port)
    assert result.returncode == 0, result.stderr
    [answer] = [json.loads(line) for line in result.stdout.splitlines()]
    assert "rogue" not in answer and answer["model"] == cell.model.id
    assert answer["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)


def test_control_without_access_control_the_same_rogue_succeeds(tmp_path: Path) -> None:
    """The tests above can fail: with ``access_control`` disabled the authenticated rogue spoofs it all."""
    open_cell = SecureCell(tmp_path / "open", access_control=False)
    spoof = Spoof(open_cell)
    try:
        spoof.sentinel("ready")
        spoof.put_everywhere()
        spoof.answer_compensate()
        spoof.sentinel("after")
        keys = {k for k, _ in spoof.rogue_samples()}
        assert {f"nanodrift/{CELL}/command", f"nanodrift/{CELL}/error"} <= keys
        with spoof.lock:
            assert f"nanodrift/{CELL}/target" in {k for k, _ in spoof.samples}
        assert "nanodrift/ghost/alive" in spoof.alive_cells()
        assert any(r.get("rogue") for r in spoof.compensate_replies())
    finally:
        spoof.close()
        assert open_cell.close() == 0


def readme_tls_steps() -> tuple[list[str], str, str]:
    """The README's TLS recipe: its openssl commands, the daemon's and the client's ``link`` blocks."""
    section = (REPO / "README.md").read_text().split("### Securing the network", 1)[1].split("\n## ", 1)[0]
    tls = section.split("**TLS**", 1)[1]
    blocks = re.findall(r"```(sh|json5)\n(.*?)```", tls, re.DOTALL)
    [commands] = [body for kind, body in blocks if kind == "sh"]
    daemon_link, client_link = [body for kind, body in blocks if kind == "json5"]
    return [c for c in commands.splitlines() if c.startswith("openssl") or c.startswith("printf")], \
        daemon_link, client_link


@pytest.mark.skipif(shutil.which("openssl") is None, reason="the README's TLS recipe needs the openssl command")
def test_tls_with_client_certificates_as_the_readme_says(tmp_path: Path) -> None:
    commands, daemon_link, client_link = readme_tls_steps()
    certs = tmp_path / "tls"
    certs.mkdir()
    for command in commands:  # the README's commands, for this host's name and address
        command = command.replace("nanodrift-host.lab", "localhost").replace("192.168.1.10", "127.0.0.1")
        subprocess.run(command, shell=True, cwd=certs, check=True, capture_output=True, timeout=60)
    made = {p.name for p in certs.iterdir()}
    assert {"ca.pem", "server.pem", "server-key.pem", "client.pem", "client-key.pem"} <= made
    daemon_link = daemon_link.replace("/etc/nanodrift/tls/", f"{certs}/")
    client_link = client_link.replace("/home/NAME/.config/nanodrift/", f"{certs}/")

    cell = SecureCell(tmp_path / "daemon", scheme="tls", transport=daemon_link, client_transport=client_link)
    try:
        client = cell.client_config
        served = nanodrift_target(client, cell.port, "tls/localhost")
        assert served.returncode == 0, served.stderr
        assert json.loads(served.stdout)["model"] == cell.model.id
        # the right password without a client certificate, or in clear text: no session
        no_cert = client_file(tmp_path, "no-cert.json5",
                              transport=client_link.replace("enable_mtls: true", "enable_mtls: false"))
        for config, endpoint in ((no_cert, "tls/localhost"), (client, "tcp/127.0.0.1")):
            refused = nanodrift_target(config, cell.port, endpoint)
            assert refused.returncode != 0 and "cannot open a zenoh session" in refused.stderr
    finally:
        assert cell.close() == 0


@pytest.mark.parametrize("name", ["lab.toml", "sim.toml"])
def test_shipped_configs_listen_on_loopback_only_without_multicast_scouting(name: str) -> None:
    config = load_config(CONFIG / name)
    assert config.zenoh.listen == ["tcp/127.0.0.1:7447"] and config.zenoh.connect == []
    assert config.zenoh.multicast_scouting is False and config.zenoh.config_file is None
    conf = daemon_session_config(config.zenoh)
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    if name == "lab.toml":  # and says how to open it safely
        assert 'config_file = "zenoh-secure.json5"' in (CONFIG / name).read_text()
