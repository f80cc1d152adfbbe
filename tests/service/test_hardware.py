"""The daemon as a separate process reading thermocouples from a Modbus TCP server (another
process) and an interferometer emulated on a pty: the server is killed while the daemon runs ->
targets are refused naming the channel; the server comes back -> targets are served again; the
interferometer is unplugged -> its channel faults naming the port; plugged back -> ok again. The
daemon is never touched."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.daemon_harness import Client, Daemon, expected_q, free_port, wait_until, write_test_model
from helpers.serial_helpers import FakeInterferometer

TESTS = Path(__file__).resolve().parents[1]
TEMPS = {"T1": 21.8, "T2": 21.9}  # inside the test model's training ranges


class ModbusModuleProcess:
    """tests/helpers/modbus_helpers.py serving input registers 0.. as int16 x0.1 degC on 127.0.0.1:port."""

    def __init__(self, port: int, values: list[float]) -> None:
        self.port = port
        self.values = values
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, str(TESTS / "helpers" / "modbus_helpers.py"), "--port", str(self.port),
             "--values", ",".join(str(v) for v in self.values)],
            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # blocks until the server listens (or the process dies)
        assert "ready" in line, f"modbus server did not start: {line!r}"

    def kill(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.send_signal(signal.SIGKILL)
            self.proc.wait(10)


def config_text(cell: str, zenoh_port: int, modbus_port: int, model: Path, interferometer: str) -> str:
    sensors = "".join(
        f'\n[[sensors]]\nname = "{name}"\nkind = "modbus"\nhub = "adam"\naddress = {address}\n'
        f'input_type = "input"\ndata_type = "int16"\nscale = 0.1\nnan_value = -32768\n'
        f"interval_s = 0.05\nmax_age_s = 1.0\n"
        for address, name in enumerate(("T1", "T2", "T3", "T4"))
    )
    sensors += (f'\n[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "serial_line"\n'
                f'port = "{interferometer}"\nbaudrate = 115200\nquery = "POS?\\r"\n'
                f"pattern = 'P (?P<value>[-+0-9.]+) nm'\nscale = 0.001\ninterval_s = 0.05\nmax_age_s = 1.0\n"
                f"timeout_s = 0.3\n")
    return (f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zenoh_port}"]\n'
            f'multicast_scouting = false\n[model]\npath = "{model}"\n'
            f'[[hubs]]\nname = "adam"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {modbus_port}\ntimeout_s = 0.3\n'
            f"{sensors}")


def test_modbus_server_killed_and_restarted_while_the_daemon_runs(tmp_path: Path) -> None:
    module = ModbusModuleProcess(free_port(), [TEMPS["T1"], TEMPS["T2"], 22.0, 22.1])
    module.start()
    interferometer = FakeInterferometer(tmp_path / "ttyIFM")
    zenoh_port = free_port()
    model_path = tmp_path / "model.json"
    write_test_model(model_path)
    config = tmp_path / "lab.toml"
    config.write_text(config_text("hw", zenoh_port, module.port, model_path, interferometer.port))
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    client = None
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(zenoh_port, "hw")
        client.wait_alive()
        status = client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
        assert status["sensors"]["T4"]["value"] == pytest.approx(22.1)
        assert status["sensors"]["interferometer"]["value"] == pytest.approx(123.4567)

        ok, command = client.query({"x_um": 240.0, "id": "before"})
        assert ok, command
        assert command["temperatures_c"]["T1"] == pytest.approx(TEMPS["T1"])
        assert command["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-6)

        module.kill()

        def refused() -> dict | None:
            ok, answer = client.query({"x_um": 240.0, "id": "down"})
            return None if ok else answer

        error = wait_until(refused, timeout=10, what="targets refused while the module is down", interval=0.05)
        assert "T1" in error["error"] or "T2" in error["error"], error
        assert error["id"] == "down"

        module.start()  # same port, same values

        def served() -> dict | None:
            ok, answer = client.query({"x_um": 240.0, "id": "after"})
            return answer if ok else None

        command = wait_until(served, timeout=20, what="targets served again after the module is back", interval=0.1)
        assert command["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-6)

        interferometer.unplug()  # the serial instrument vanishes: its channel faults, naming the port

        def interferometer_fault() -> str | None:
            entry = client.status(2.0)["sensors"]["interferometer"]
            return entry["reason"] if entry["state"] == "fault" else None

        reason = wait_until(interferometer_fault, timeout=10, what="interferometer faulted after unplugging")
        assert interferometer.port in reason
        interferometer.position_nm = 5000.0
        interferometer.replug()

        def interferometer_back() -> bool:
            entry = client.status(2.0)["sensors"]["interferometer"]
            return entry["state"] == "ok" and entry["value"] == pytest.approx(5.0)

        wait_until(interferometer_back, timeout=20, what="interferometer served again after replugging",
                   interval=0.1)
        daemon.check_alive()
    finally:
        if client is not None:
            client.close()
        daemon.stop()
        module.kill()
        interferometer.close()
