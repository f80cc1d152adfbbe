"""``done`` and ``stop`` over real Zenoh (127.0.0.1), the daemon a separate process driving a Modbus module.

One served command, one ``done``: ``reached`` once the register holds the command's count (verify = true:
read back), ``superseded`` for a flood during a slow ramp, ``stopped`` by a ``stop`` (as a query, answered
with the value held, and as a put) and by the daemon's own stop, ``failed`` when the module refuses a
write. Asserted on what the module's registers received (every write stamped as it lands), for a one-axis
cell and an XY cell whose two outputs are two registers of one module. A cell with no output
(``kind = "zenoh"``) says ``reached`` right after the publish. Every wait is on a received sample, a log
line or a register, with a deadline.
"""

from __future__ import annotations

import itertools
import json
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers.cell_helpers import ThreadedModbus, write_cell_model
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    Served,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)

from nanodrift.drivers.testing.modbus_server import ModbusTestDevice

SCALE_V = 0.001  # volts per count
VOLTS_PER_UM = 0.02
RATE = 100.0  # um/s: 300 um take 3 s
ADDRESSES = {"x": 10, "y": 11}
Y_SHARE = 0.5  # y's target is half x's


def signed(raw: int) -> int:
    return raw - 65536 if raw >= 32768 else raw


class Watch:
    """Every ``done`` of a cell, in arrival order, on a client's session."""

    def __init__(self, session: zenoh.Session, prefix: str) -> None:
        self.prefix = prefix
        self.session = session
        self.dones: list[dict[str, Any]] = []
        self._cond = threading.Condition()
        self._sub = session.declare_subscriber(f"{prefix}/done", self._done)

    def _done(self, sample: zenoh.Sample) -> None:
        with self._cond:
            self.dones.append(json.loads(sample.payload.to_bytes()))
            self._cond.notify_all()

    def of(self, target_id: Any) -> list[dict[str, Any]]:
        with self._cond:
            return [d for d in self.dones if d["id"] == target_id]

    def wait(self, target_id: Any, timeout: float = 20.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout
        with self._cond:
            while True:
                mine = [d for d in self.dones if d["id"] == target_id]
                if mine:
                    return mine[0]
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"no done for {target_id!r} within {timeout:g} s: {self.dones[-5:]}")
                self._cond.wait(remaining)

    def stop(self, payload: bytes | str = b"", timeout: float = 10.0) -> tuple[bool, dict[str, Any]]:
        """A ``stop`` query: (True, reply) or (False, reply error)."""
        replies = list(self.session.get(f"{self.prefix}/stop", payload=payload, timeout=timeout))
        assert len(replies) == 1, f"expected exactly one reply to stop, got {len(replies)}"
        if replies[0].ok is not None:
            return True, json.loads(replies[0].ok.payload.to_bytes())
        return False, json.loads(replies[0].err.payload.to_bytes())

    def stop_put(self, payload: bytes | str = b"") -> None:
        self.session.put(f"{self.prefix}/stop", payload)


class ModbusCell:
    """``nanodrift run`` driving one register per axis of a Modbus module, with a slew limit; a client."""

    def __init__(self, root: Path, axes: tuple[str, ...]) -> None:
        self.axes = axes
        self.device = ModbusTestDevice(device_id=1, holding_ranges=((0, 64),))
        self.landed: list[tuple[float, int, int]] = []  # (time.monotonic(), address, raw) per stored write
        self.device.on_write = lambda address, values: self.landed.extend(
            (time.monotonic(), address + i, signed(v)) for i, v in enumerate(values))
        self.module = ThreadedModbus(self.device).start()
        self.cell = f"done{free_port()}"
        self.port = free_port()
        plugins = install_file_plugin(root / "plugins")
        sensors = SensorFile(root / "sensors.json", TEMPS)
        model = root / "model.json"
        config = root / "cell.toml"
        hub = (f'[[hubs]]\nname = "dac"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {self.module.port}\n'
               "timeout_s = 0.5\n")
        output = (f'kind = "modbus"\nhub = "dac"\nscale = {SCALE_V}\nvolts_per_um = {VOLTS_PER_UM}\n'
                  f"max_slew_um_per_s = {RATE}\n")
        if axes == ("x",):
            write_test_model(model)
            text = file_sensor_config(root, cell=self.cell, port=self.port, model_path=model,
                                      sensor_file=sensors.path, actuator=f"{output}address = 10\n", extra=hub)
        else:
            write_cell_model(model, axes)
            text = file_sensor_config(root, cell=self.cell, port=self.port, model_path=model,
                                      sensor_file=sensors.path, extra=hub).replace("[actuator]\n", "")
            text += "".join(f'\n[[axes]]\nname = "{a}"\nmin_um = 0.0\nmax_um = 480.0\n[axes.actuator]\n{output}'
                            f"address = {ADDRESSES[a]}\n" for a in axes)
        config.write_text(text)
        self.config, self.config_text, self.hub = config, text, hub
        self.daemon = Daemon(["--config", str(config)], root / "daemon.log", [plugins])
        self.daemon.wait_log("serving", timeout=30)
        self.client = Client(self.port, self.cell)
        self.client.wait_alive()
        self.client.wait_ready(("T1", "T2"))
        self.watch = Watch(self.client.session, self.client.prefix)

    def payload(self, x_um: float, target_id: Any) -> dict[str, Any]:
        doc: dict[str, Any] = {"x_um": x_um, "id": target_id}
        if "y" in self.axes:
            doc["y_um"] = x_um * Y_SHARE
        return doc

    def query(self, x_um: float, target_id: Any) -> dict[str, Any]:
        ok, command = self.client.query(self.payload(x_um, target_id))
        assert ok, command
        return command

    def put(self, x_um: float, target_id: Any) -> None:
        self.client.put(json.dumps(self.payload(x_um, target_id)))

    def command(self, target_id: Any) -> dict[str, Any]:
        return self.client.wait(lambda: next((c for c in self.client.commands if c["id"] == target_id), None), 10,
                                f"the command of {target_id!r}")

    def per_axis(self, value: Any) -> dict[str, float]:
        """A payload's voltage per axis (a one-axis cell's is a number)."""
        if self.axes == ("x",):
            assert isinstance(value, int | float), value
            return {"x": float(value)}
        assert isinstance(value, dict) and list(value) == list(self.axes), value
        return {a: float(v) for a, v in value.items()}

    def edit_hub(self) -> None:
        """An edit of the module's hub (its timeout): a reload restarts the drivers."""
        self.config.write_text(self.config_text.replace(self.hub, self.hub.replace("timeout_s = 0.5",
                                                                                   "timeout_s = 0.6")))

    def register_v(self, axis: str) -> float:
        return signed(self.module.registers(ADDRESSES[axis])[0]) * SCALE_V

    def landed_v(self, axis: str, since: int = 0) -> list[float]:
        return [raw * SCALE_V for _, address, raw in self.landed[since:] if address == ADDRESSES[axis]]

    def close(self) -> int:
        self.client.close()
        code = self.daemon.stop()
        self.module.stop()
        return code


def close_to(a: float, b: float) -> bool:
    return abs(a - b) <= SCALE_V / 2 + 1e-9  # one count of the module


@pytest.fixture(params=[("x",), ("x", "y")], ids=["one-axis", "xy"])
def cell(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[ModbusCell]:
    made = ModbusCell(tmp_path, request.param)
    yield made
    made.close()


def test_every_served_command_gets_one_done_saying_how_it_ended(cell: ModbusCell) -> None:
    watch, axes = cell.watch, cell.axes

    # reached: the register holds the command's count (read back by the driver: verify = true)
    first = cell.query(10.0, 1)
    done = watch.wait(1)
    assert list(done) == ["id", "state", "t", "voltage_v", "error"]
    assert done["state"] == "reached" and done["error"] is None and abs(done["t"] - time.time()) < 60
    wanted = cell.per_axis(first["voltage_v"])
    held = cell.per_axis(done["voltage_v"])
    assert all(close_to(held[a], wanted[a]) and close_to(cell.register_v(a), wanted[a]) for a in axes)

    # superseded: a flood of puts during a slow ramp (10 -> 320 um: 3 s); every one but the last is superseded
    for i in range(2, 22):
        cell.put(300.0 + i, i)
    for i in range(2, 21):
        assert watch.wait(i)["state"] == "superseded", watch.of(i)
    last = cell.command(21)
    assert not watch.of(21), "the last of the flood ended before its ramp could"

    # stopped, by a query: answered with what each output holds once the ramp has ended
    ok, reply = watch.stop(json.dumps({"id": "halt-1"}))
    assert ok and reply["id"] == "halt-1" and reply["held"] is True, reply
    done = watch.wait(21)
    assert done["state"] == "stopped" and done["error"] is None
    held = cell.per_axis(reply["voltage_v"])
    assert cell.per_axis(done["voltage_v"]) == held
    goal = cell.per_axis(last["voltage_v"])
    since = len(cell.landed)
    for axis in axes:  # held where the ramp was, well short of the goal
        assert close_to(cell.register_v(axis), held[axis]) and held[axis] < goal[axis] - 0.1

    # the next target moves again, from where the outputs were held
    after = cell.query(100.0, 22)
    assert watch.wait(22)["state"] == "reached"
    wanted = cell.per_axis(after["voltage_v"])
    for axis in axes:
        moved = cell.landed_v(axis, since)
        assert len(moved) >= 3 and close_to(moved[-1], wanted[axis]), moved  # a ramp, not a jump
        # the first step within the slew of the time since the axis' previous write (on a loaded machine the
        # ramp's pause grows with the device's write time, so a step may cover more than a few ramp periods)
        [t_prev, *_] = [t for t, address, _ in reversed(cell.landed[:since]) if address == ADDRESSES[axis]]
        [t_first, *_] = [t for t, address, _ in cell.landed[since:] if address == ADDRESSES[axis]]
        assert abs(moved[0] - held[axis]) <= RATE * VOLTS_PER_UM * (t_first - t_prev) + SCALE_V, (held[axis], moved[:3])
        direction = 1.0 if wanted[axis] > held[axis] else -1.0
        assert all(direction * (b - a) >= 0 for a, b in itertools.pairwise([held[axis], *moved]))
        assert all(not close_to(v, goal[axis]) for v in cell.landed_v(axis)), "the stopped goal was reached"

    # a stop when nothing moves: a no-op that still answers, with the same values
    ok, reply = watch.stop()
    assert ok and reply["id"] is None and reply["held"] is True
    assert all(close_to(cell.per_axis(reply["voltage_v"])[a], wanted[a]) for a in axes)

    # failed: the module refuses the write; the goal is still written once it takes writes again
    cell.device.refuse_writes = 1
    failing = cell.query(150.0, 23)
    done = watch.wait(23)
    assert done["state"] == "failed" and done["error"], done
    cell.daemon.wait_log("actuator_recovered", timeout=20)
    wanted = cell.per_axis(failing["voltage_v"])
    wait_until(lambda: all(close_to(cell.register_v(a), wanted[a]) for a in axes), 20, "the goal after the fault")

    # a reload mid-ramp (150 -> 350 um: 2 s): the command is carried over to the new drivers and ends once
    before = len(cell.landed)
    carried = cell.query(350.0, 24)
    wait_until(lambda: len(cell.landed) >= before + 3 * len(axes), 10, "the ramp under way", interval=0.02)
    cell.edit_hub()
    cell.daemon.signal(signal.SIGHUP)
    assert cell.daemon.wait_log("reload_applied", timeout=20)["drivers_restarted"] is True
    done = watch.wait(24)
    assert done["state"] == "reached", done
    wanted = cell.per_axis(carried["voltage_v"])
    slack_v = SCALE_V + RATE * VOLTS_PER_UM * 0.100  # a count, and 100 ms of stamping jitter on a loaded machine
    for axis in axes:
        assert close_to(cell.per_axis(done["voltage_v"])[axis], wanted[axis])
        ramp = [(t, raw * SCALE_V) for t, address, raw in cell.landed[before:] if address == ADDRESSES[axis]]
        assert close_to(ramp[-1][1], wanted[axis]) and len(ramp) > 10
        for (t0, v0), (t1, v1) in itertools.pairwise(ramp):  # across the reload too: never faster than the slew
            assert abs(v1 - v0) <= RATE * VOLTS_PER_UM * (t1 - t0) + slack_v, f"{v1 - v0:.4f} V in {t1 - t0:.4f} s"

    # stopped, by a put, mid-ramp (350 -> 450 um: 1 s)
    before = len(cell.landed)
    cell.put(450.0, 25)
    wait_until(lambda: len(cell.landed) >= before + 3 * len(axes), 10, "the ramp under way", interval=0.02)
    watch.stop_put(json.dumps({"id": 2}))
    done = watch.wait(25)
    assert done["state"] == "stopped"
    held = cell.per_axis(done["voltage_v"])
    assert all(close_to(cell.register_v(a), held[a]) for a in axes)

    # a target sent once a stop is served moves as usual (a stop is no latch). Sent as a query: zenoh does not
    # order a session's puts on two keys against each other (a stop put and a target put right after it
    # reached the daemon target first in loaded runs, and the stop then rightly ended the target)
    ok, _ = watch.stop(b"")
    assert ok
    cell.put(420.0, "after")
    assert watch.wait("after")["state"] == "reached"

    # a bad stop: a put is logged and ignored, a query gets a reply error
    watch.stop_put(b"{not json")
    refused = cell.daemon.wait_log("stop_refused")
    assert "not valid JSON" in refused["reason"]
    ok, error = watch.stop(b"[1]")
    assert not ok and error["kind"] == "bad_payload" and "JSON object" in error["error"]

    # the daemon stops mid-ramp: the command in flight ends stopped before the session closes
    before = len(cell.landed)
    cell.put(0.0, 26)
    wait_until(lambda: len(cell.landed) >= before + 3 * len(axes), 10, "the ramp under way", interval=0.02)
    cell.daemon.signal(signal.SIGTERM)
    assert watch.wait(26)["state"] == "stopped"
    assert cell.daemon.proc.wait(20) == 0

    for i in [*range(1, 27), "after"]:  # exactly one done per served command
        assert len(watch.of(i)) == 1, (i, watch.of(i))
    assert len(watch.dones) == 27


def test_with_no_output_each_command_is_reached_right_after_its_publish(tmp_path: Path) -> None:
    served = Served(tmp_path, f"zenoh{free_port()}").start()  # [actuator] kind = "zenoh": no device
    try:
        watch = Watch(served.client.session, served.client.prefix)
        commands: dict[int, dict[str, Any]] = {}
        for i in range(1, 6):
            ok, commands[i] = served.client.query({"x_um": 50.0 * i, "id": i})
            assert ok, commands[i]
            done = watch.wait(i)
            assert done == {**done, "id": i, "state": "reached", "error": None}
            assert done["voltage_v"] == commands[i]["voltage_v"]
        ok, reply = watch.stop(json.dumps({"id": "s"}))
        assert ok and reply == {"id": "s", "voltage_v": commands[5]["voltage_v"], "held": True}
        assert [d["id"] for d in watch.dones] == [1, 2, 3, 4, 5]
    finally:
        assert served.close() == 0
