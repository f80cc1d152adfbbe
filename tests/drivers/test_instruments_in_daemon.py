"""The daemon as a separate process reading DCON thermocouples from a module emulated on a pty and an attocube
IDS emulated behind TCP on 127.0.0.1: targets are served from the module's line; an open thermocouple refuses
targets naming its channel while the module's other channels still read; a stopped IDS measurement faults the
interferometer naming the device's axis; both recover with nothing done to the daemon."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import Client, Daemon, expected_q, free_port, wait_until, write_test_model

from nanodrift.drivers.testing import DconBusEmulator, DconModule, IdsEmulator

TEMPS = {"T1": 21.8, "T2": 21.9}  # inside the test model's training ranges


def config_text(zenoh_port: int, model: Path, rs485: str, ids_port: int) -> str:
    sensors = "".join(f'\n[[sensors]]\nname = "T{c + 1}"\nkind = "dcon"\nhub = "rs485"\naddress = 1\nchannel = {c}\n'
                      "interval_s = 0.05\nmax_age_s = 1.0\n" for c in range(4))
    sensors += ('\n[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "attocube_ids"\n'
                f'host = "127.0.0.1"\nport = {ids_port}\nids_axis = 1\ninterval_s = 0.05\nmax_age_s = 1.0\n'
                'timeout_s = 0.3\n')
    return (f'cell = "instruments"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zenoh_port}"]\n'
            f'multicast_scouting = false\n[model]\npath = "{model}"\n'
            f'[[hubs]]\nname = "rs485"\ntype = "serial"\nport = "{rs485}"\ntimeout_s = 0.3\n{sensors}')


def test_the_daemon_serves_from_dcon_and_ids_and_names_what_faults(tmp_path: Path) -> None:
    module = DconModule(1, [TEMPS["T1"], TEMPS["T2"], 22.0, 22.1])
    bus = DconBusEmulator(tmp_path / "ttyRS485", [module])
    ids = IdsEmulator()
    ids.axes[1].displacement_pm = 240_012_345.0
    zenoh_port = free_port()
    write_test_model(tmp_path / "model.json")
    config = tmp_path / "lab.toml"
    config.write_text(config_text(zenoh_port, tmp_path / "model.json", bus.port, ids.port))
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    client = None

    def sensor(name: str) -> dict[str, Any]:
        entry: dict[str, Any] = client.status(2.0)["sensors"][name]  # type: ignore[union-attr]
        return entry

    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(zenoh_port, "instruments")
        client.wait_alive()
        status = client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
        assert status["sensors"]["T4"]["value"] == pytest.approx(22.1)
        assert status["sensors"]["interferometer"]["value"] == pytest.approx(240.012345, abs=1e-9)

        ok, command = client.query({"x_um": 240.0, "id": "before"})
        assert ok, command
        assert command["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-6)

        module.open_channels.add(1)  # T2's thermocouple opens: the module reads +9999 on channel 1

        def refused() -> dict[str, Any] | None:
            ok, answer = client.query({"x_um": 240.0, "id": "open"})  # type: ignore[union-attr]
            return None if ok else answer

        error = wait_until(refused, timeout=10, what="targets refused with T2 open", interval=0.05)
        assert "T2" in error["error"] and error["id"] == "open"
        t2 = sensor("T2")
        assert t2["state"] == "fault" and "channel 1" in t2["reason"] and "+9999" in t2["reason"]
        assert sensor("T1")["state"] == "ok" and sensor("T3")["state"] == "ok"  # one line, the others still read

        ids.measurement_running = False
        reason = wait_until(lambda: sensor("interferometer")["state"] == "fault" and sensor("interferometer")["reason"],
                            timeout=10, what="interferometer faulted with the measurement stopped")
        assert "axis 1" in reason and "system idle" in reason and f"127.0.0.1:{ids.port}" in reason

        module.open_channels.clear()
        ids.measurement_running = True

        def served() -> dict[str, Any] | None:
            ok, answer = client.query({"x_um": 240.0, "id": "after"})  # type: ignore[union-attr]
            return answer if ok else None

        command = wait_until(served, timeout=20, what="targets served again", interval=0.1)
        assert command["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-6)
        wait_until(lambda: sensor("interferometer")["state"] == "ok", timeout=10, what="interferometer ok again")
        # the device-side record: every channel came from #01 (all channels), never a per-channel #01N
        assert {line for line in bus.requests if line.startswith("#")} == {"#01"}
        daemon.check_alive()
    finally:
        if client is not None:
            client.close()
        daemon.stop()
        bus.close()
        ids.stop()
