"""The daemon drives the stage: latest command wins, slew ramps (from where the stage is), faults refuse
targets, safe voltage on stop, and a lab's own output plugin.

Real peers: ``nanodrift run`` as a process (the ``file`` sensor plugin for temperatures) with
``[actuator] kind = "modbus"`` writing to pymodbus' own TCP server on 127.0.0.1, which runs on an
asyncio loop in a thread of this process and stamps every write as it lands; ``kind = "serial_line"``
talking GCS to a PI controller emulated on a pty; ``kind = "labout"``, a plugin defined here (not part
of nanodrift) and registered through an entry point as a lab's package would be. Every wait polls a
condition with a deadline.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import math
import os
import re
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Coroutine, Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import pytest
from helpers.daemon_harness import (
    REPO,
    TEMPS,
    TESTS,
    Client,
    Daemon,
    FilePlugin,
    SensorFile,
    expected_q,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer
from helpers.serial_helpers import FakeGcsController
from pydantic import Field

from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator, ActuatorOptions, DeviceError, DriverContext
from nanodrift.motion import RAMP_PERIOD_S
from nanodrift.service.actuation import Actuation

SCALE = 0.001  # volts per count
ADDRESS = 10
VOLTS_PER_UM = 0.02


# --- Actuation in process: order and coalescing --------------------------------------------------


class RecordingActuator(Actuator):
    """Records every write (and when it started); ``holds`` is what ``read_back`` answers (None: the device
    cannot say); ``broken`` fails ``open``, ``unreadable`` fails ``read_back``."""

    def __init__(self, write_s: float = 0.0, description: str = "recording actuator",
                 holds: tuple[Literal["voltage_v", "q_um"], float] | None = None) -> None:
        self.written: list[tuple[float, float, float | None]] = []
        self.started: list[float] = []  # time.monotonic() as each write began
        self.write_s = write_s
        self.description = description
        self.holds = holds
        self.broken = self.unreadable = False

    async def open(self) -> None:
        if self.broken:
            raise DeviceError(f"{self.description}: port gone")

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        if self.unreadable:
            raise DeviceError(f"{self.description}: no answer to the readback")
        return self.holds

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        self.started.append(time.monotonic())
        await asyncio.sleep(self.write_s)
        self.written.append((q_um, voltage_v, x_um))

    async def close(self) -> None:
        return None


class Silent:
    def __getattr__(self, name: str) -> Any:
        return lambda *a, **k: None


class Events:
    """A logger keeping every line as (level, event, fields)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str, dict[str, Any]]] = []

    def __getattr__(self, level: str) -> Callable[..., None]:
        return lambda event, **fields: self.lines.append((level, event, fields))

    def named(self, event: str) -> list[dict[str, Any]]:
        return [fields for _, name, fields in self.lines if name == event]


async def until(condition: Callable[[], Any], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        await asyncio.sleep(0.005)


def command(actuation: Actuation, config: ActuatorConfig, q_um: float) -> None:
    """What the target path does for a served target."""
    if actuation.offer(q_um, config.voltage(q_um)):
        actuation.wake()


def test_the_device_gets_served_commands_in_order_and_the_latest_always() -> None:
    async def main() -> None:
        actuation = Actuation(Silent())
        device = RecordingActuator(write_s=0.005)
        config = ActuatorConfig()
        await actuation.start(device, config)
        for i in range(200):
            q = float(i)
            if actuation.offer(q, config.voltage(q), x_um=q + 0.5):
                actuation.wake()
            await asyncio.sleep(0.001 if i % 20 else 0.08)  # bursts, and pauses the stage catches up in
        deadline = time.monotonic() + 5
        while not device.written or device.written[-1][0] != 199.0:
            assert time.monotonic() < deadline, device.written[-5:]
            await asyncio.sleep(0.01)
        await actuation.stop()
        qs = [q for q, _, _ in device.written]
        assert qs == sorted(set(qs)), "written out of order or twice"
        assert len(qs) < 200, "nothing was coalesced"
        assert all(x == q + 0.5 and v == config.voltage(q) for q, v, x in device.written)

    asyncio.run(main())


SLEW = 2000.0  # um/s: a ramp step of 40 um every RAMP_PERIOD_S, so the in-process ramps take a fraction of a second


def ramp_of(device: RecordingActuator) -> list[float]:
    return [q for q, _, _ in device.written]


def assert_never_faster(device: RecordingActuator, rate: float) -> None:
    """Each write is no further from the previous one than the rate allows for the time between them."""
    slack_s = 0.002  # the daemon times a step just before it calls the device, the device a moment later
    for (t0, (q0, _, _)), (t1, (q1, _, _)) in itertools.pairwise(zip(device.started, device.written, strict=True)):
        assert abs(q1 - q0) <= rate * (t1 - t0 + slack_s) + 1e-9, f"{q1 - q0:.3f} um in {t1 - t0:.4f} s"


@pytest.mark.parametrize(("holds", "safe_v", "start_q", "known_from"), [
    (("voltage_v", 1.0), math.nan, 50.0, "read back"),  # the output register holds 1 V: 50 um
    (("q_um", 70.0), math.nan, 70.0, "read back"),  # a closed-loop controller answers the command
    (None, 2.0, 100.0, "safe_voltage_v"),  # cannot say; a clean stop left it at safe_voltage_v
    (None, math.nan, None, "unknown"),
])
def test_the_first_move_after_start_ramps_from_where_the_stage_is(
        holds: tuple[Literal["voltage_v", "q_um"], float] | None, safe_v: float, start_q: float | None,
        known_from: str) -> None:
    log = Events()
    config = ActuatorConfig(max_slew_um_per_s=SLEW, safe_voltage_v=safe_v)
    device = RecordingActuator(holds=holds)

    async def main() -> None:
        actuation = Actuation(log)
        await actuation.start(device, config)
        command(actuation, config, 480.0)
        await until(lambda: device.written and device.written[-1][0] == 480.0, 10, "the target written")
        await actuation.stop()

    asyncio.run(main())
    voltage = None if start_q is None else config.voltage(start_q)
    assert log.named("actuator_open") == [{"device": "recording actuator", "voltage_v": voltage,
                                           "known_from": known_from}]
    assert device.limits_v == (config.v_min, config.v_max)  # the device knows the operator's limits
    if start_q is None:  # nothing known: the one move is written as is, and the log says so once
        assert ramp_of(device) == [480.0]
        [told] = log.named("actuator_unramped")
        assert told["voltage_v"] == config.voltage(480.0) and "this move is not ramped" in told["reason"]
        return
    qs = ramp_of(device)
    assert qs[0] == pytest.approx(start_q + SLEW * RAMP_PERIOD_S)  # one ramp step from where the stage was
    assert all(0 < b - a for a, b in itertools.pairwise(qs))  # towards the target, never back
    assert len(qs) <= math.ceil((480.0 - start_q) / (SLEW * RAMP_PERIOD_S))  # steps cover the time they took
    assert_never_faster(device, SLEW)
    assert not log.named("actuator_unramped")


def test_an_edit_to_another_device_forgets_the_old_devices_voltage_and_the_same_device_remembers_it() -> None:
    log = Events()
    config = ActuatorConfig(max_slew_um_per_s=SLEW)

    async def main() -> tuple[RecordingActuator, RecordingActuator, RecordingActuator]:
        actuation = Actuation(log)
        first = RecordingActuator(description="output A", holds=("voltage_v", 8.0))  # 400 um
        await actuation.start(first, config)
        command(actuation, config, 400.0)
        await until(lambda: first.written, 5, "written to A")
        await actuation.stop()  # an [actuator] edit: the daemon restarts the actuation ...
        other = RecordingActuator(description="output B")  # ... on another output that cannot be read back
        await actuation.start(other, config)
        assert actuation.doc()["last_voltage_v"] is None  # A's voltage is not B's
        command(actuation, config, 10.0)
        await until(lambda: other.written, 5, "written to B")
        await actuation.stop()
        again = RecordingActuator(description="output B")  # a reload that keeps B: its last voltage is known
        await actuation.start(again, config)
        command(actuation, config, 130.0)
        await until(lambda: again.written and again.written[-1][0] == 130.0, 5, "written to B again")
        await actuation.stop()
        return first, other, again

    first, other, again = asyncio.run(main())
    assert ramp_of(first) == [400.0]  # read back at 8 V: already there
    assert ramp_of(other) == [10.0]  # not ramped down from A's 400 um: where B's stage is is unknown
    assert len(log.named("actuator_unramped")) == 1
    qs = ramp_of(again)  # ramped from the 10 um last written to B
    assert qs[-1] == 130.0 and 10.0 < qs[0] <= 10.0 + SLEW * RAMP_PERIOD_S + 1e-9
    assert all(0 < b - a for a, b in itertools.pairwise(qs))
    assert_never_faster(again, SLEW)
    assert [e["known_from"] for e in log.named("actuator_open")] == ["read back", "unknown", "last written"]


def test_a_fault_at_start_ends_only_when_the_device_opens_and_reads_back_again() -> None:
    log = Events()
    config = ActuatorConfig()
    device = RecordingActuator(holds=("voltage_v", 1.0))
    device.broken = True

    async def main() -> None:
        actuation = Actuation(log)
        await actuation.start(device, config)
        assert "open failed: recording actuator: port gone" in (actuation.fault_reason or "")
        device.broken, device.unreadable = False, True  # it opens, but does not answer
        await until(lambda: "reopen failed" in (actuation.fault_reason or ""), 5, "a reopen attempt")
        await until(lambda: actuation.write_failures >= 3, 10, "more reopen attempts")
        assert "no answer to the readback" in (actuation.fault_reason or "")  # still in fault: nothing proved it works
        device.unreadable = False
        await until(lambda: actuation.fault_reason is None, 10, "the fault ends")
        await actuation.stop()

    asyncio.run(main())
    assert device.written == []  # nothing was commanded: nothing was written to end the fault
    [failed] = log.named("actuator_failed")
    [recovered] = log.named("actuator_recovered")
    assert failed["device"] == "recording actuator" and recovered["failures"] >= 3


# --- a Modbus output module on a thread ----------------------------------------------------------


class OutputModule:
    """pymodbus' TCP server on its own loop thread; ``stamps`` is every write of the output register."""

    def __init__(self) -> None:
        self.device = ModbusTestDevice(1, holding_ranges=((0, 32),))
        self.server = ModbusTestServer([self.device])
        self.stamps: list[tuple[float, int, int]] = []  # (time.monotonic(), address, raw)
        self.mangle = False  # store 7 counts more than written (a module that mangles its writes)
        self.device.on_write = self._landed
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="modbus-output", daemon=True)
        self._thread.start()
        self.call(self.server.start())

    def _landed(self, address: int, values: list[int]) -> None:
        now = time.monotonic()
        if self.mangle:
            values[:] = [(v + 7) & 0xFFFF for v in values]
        self.stamps.extend((now, address + i, _signed(v)) for i, v in enumerate(values))

    def call(self, coro: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def register(self, address: int = ADDRESS) -> int:
        return _signed(self.call(self.server.get_registers(1, address, 1))[0])

    def hold(self, raw: int, address: int = ADDRESS) -> None:
        """Put ``raw`` in the register (what an earlier run left there); not one of ``stamps``."""
        self.call(self.server.set_registers(1, address, [raw & 0xFFFF], input_type="holding"))
        self.stamps.clear()
        self.device.writes.clear()

    def stop(self) -> None:
        self.call(self.server.stop())

    def start(self) -> None:
        self.call(self.server.start())

    def close(self) -> None:
        self.call(self.server.stop())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5)


def _signed(raw: int) -> int:
    """An int16 register as the output module reads it."""
    return raw - 65536 if raw >= 32768 else raw


@pytest.fixture
def module() -> Iterator[OutputModule]:
    out = OutputModule()
    yield out
    out.close()


def raw_for(voltage_v: float) -> int:
    return round(voltage_v / SCALE)


class Cell:
    """``nanodrift run`` with file sensors and an output (a Modbus module by default; ``keys``: another
    kind's ``[actuator]`` keys), and a client."""

    def __init__(self, root: Path, port_modbus: int | None, *, address: int = ADDRESS, actuator: str = "",
                 keys: str | None = None, pythonpath: Sequence[Path] = ()) -> None:
        self.root = root
        self.cell = f"act{free_port()}"
        self.port = free_port()
        self.port_modbus = port_modbus
        self.keys = keys
        self.plugins = install_file_plugin(root / "plugins")
        self.model_path = root / "model.json"
        write_test_model(self.model_path)
        self.sensors = SensorFile(root / "sensors.json", TEMPS)
        self.config_path = root / "nanodrift.toml"
        self.write_config(address=address, actuator=actuator)
        self.daemon = Daemon(["--config", str(self.config_path)], root / "daemon.log", [self.plugins, *pythonpath])
        self.daemon.wait_log("serving", timeout=30)
        self.client = Client(self.port, self.cell)
        self.client.wait_alive()
        self.client.wait_ready(("T1", "T2"))
        self._ids = itertools.count(1)

    def write_config(self, *, address: int, actuator: str) -> None:
        device = self.keys or f'kind = "modbus"\nhub = "out"\ndevice_id = 1\naddress = {address}\nscale = {SCALE}\n'
        keys = f"{device}volts_per_um = {VOLTS_PER_UM}\n{actuator}"
        hub = ("" if self.port_modbus is None else f'[[hubs]]\nname = "out"\ntype = "tcp"\nhost = "127.0.0.1"\n'
               f"port = {self.port_modbus}\ntimeout_s = 0.3\n")
        self.config_path.write_text(file_sensor_config(
            self.root, cell=self.cell, port=self.port, model_path=self.model_path, sensor_file=self.sensors.path,
            actuator=keys, extra=hub))

    def target(self, x_um: float) -> tuple[bool, dict[str, Any]]:
        return self.client.query({"x_um": x_um, "id": next(self._ids)})

    def actuator_status(self) -> dict[str, Any]:
        return self.client.status()["actuator"]

    def close(self) -> int:
        if self.client is not None:
            self.client.close()
            self.client = None  # type: ignore[assignment]
        return self.daemon.stop()


@pytest.fixture
def cells() -> Iterator[list[Cell]]:
    made: list[Cell] = []
    yield made
    for cell in made:
        cell.close()


def test_the_register_holds_each_command_a_dead_module_refuses_targets_and_recovery_serves_again(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    cell = Cell(tmp_path, module.server.port)
    cells.append(cell)
    for x in (100.0, 250.0):
        ok, command = cell.target(x)
        assert ok, command
        assert command["q_um"] == pytest.approx(expected_q(x, TEMPS))
        wait_until(lambda v=command["voltage_v"]: module.register() == raw_for(v), 10, f"register = {x} um")
    # the register changes before the daemon has the module's answer (and its verify read): wait for that too
    # status shows what the register received: the command's voltage as a whole count
    sent_v = raw_for(command["voltage_v"]) * SCALE
    wait_until(lambda: cell.actuator_status()["last_voltage_v"] == pytest.approx(sent_v), 10, "the write recorded")
    actuator = cell.actuator_status()
    assert list(actuator)[:9] == ["volts_per_um", "offset_v", "v_min", "v_max", "x_min_um", "x_max_um", "kind",
                                  "max_slew_um_per_s", "safe_voltage_v"]
    assert actuator["state"] == "ok" and actuator["reason"] is None and actuator["output"] == "device"
    assert actuator["last_voltage_v"] == pytest.approx(sent_v) and actuator["writes"] >= 2
    assert actuator["failures"] == 0 and "holding register 10" in actuator["device"]
    held = module.register()

    module.stop()  # the module is gone: the next write fails, then targets are refused

    def refused() -> dict[str, Any] | None:
        ok, answer = cell.target(300.0)
        return answer if not ok and answer.get("kind") == "actuator_fault" else None

    error = wait_until(refused, 15, "a target refused with kind actuator_fault", interval=0.05)
    assert error["error"].startswith("actuator fault: ")
    assert error["error"].endswith("; the stage holds its last position")
    faulted = wait_until(lambda: (s := cell.actuator_status())["failures"] >= 3 and s, 15,
                         "reopen attempts counted in status", interval=0.1)
    assert faulted["state"] == "fault" and faulted["reason"]
    assert cell.client.status()["counters"]["errors"]["actuator_fault"] >= 1
    assert len(cell.daemon.log_events("actuator_failed")) == 1, "one actuator_failed line per episode"

    module.start()
    recovered = cell.daemon.wait_log("actuator_recovered", timeout=20)
    assert recovered["failures"] >= 3
    assert module.register() != held  # the command answered before the fault was noticed got written
    ok, command = cell.target(50.0)
    assert ok, command
    wait_until(lambda: module.register() == raw_for(command["voltage_v"]), 10, "register after recovery")
    status = cell.actuator_status()
    assert status["state"] == "ok" and status["reason"] is None


def test_a_large_jump_is_ramped_under_the_slew_limit_and_answered_at_once(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 100.0
    cell = Cell(tmp_path, module.server.port, actuator=f"max_slew_um_per_s = {rate}\nverify = false")
    cells.append(cell)
    ok, first = cell.target(0.0)
    assert ok, first
    wait_until(lambda: module.register() == raw_for(first["voltage_v"]), 10, "register at 0 um")
    # verify = false, safe_voltage_v = nan: where the stage was is unknown, the first move is not ramped
    unramped = cell.daemon.wait_log("actuator_unramped")
    assert unramped["voltage_v"] == first["voltage_v"]
    assert cell.daemon.log_events("actuator_open")[0]["known_from"] == "unknown"
    start = len(module.stamps)
    sent = time.monotonic()
    ok, jump = cell.target(480.0)
    answered = time.monotonic()
    assert ok, jump
    assert answered - sent < 1.0, "the answer waited for the ramp"
    target_raw = raw_for(jump["voltage_v"])
    wait_until(lambda: module.register() == target_raw, 20, "the ramp's end at 480 um", interval=0.05)
    stamps = [(t, raw) for t, address, raw in module.stamps[start - 1:] if address == ADDRESS]
    assert stamps[0][1] == raw_for(first["voltage_v"]) and stamps[-1][1] == target_raw
    assert len(stamps) > 100, f"{len(stamps)} writes: no ramp"
    q = [(t, (raw * SCALE) / VOLTS_PER_UM) for t, raw in stamps]
    assert all(b >= a for (_, a), (_, b) in itertools.pairwise(q)), "the ramp went backwards"
    # one count, and 50 ms of stamping jitter: the server's thread stamps arrivals, and a loaded machine delays
    # one write against the next (10 ms failed once under load). A ramp 10 % too fast still fails within 1 s.
    slack_um = SCALE / VOLTS_PER_UM + rate * 0.050
    for (t0, q0), (t1, q1) in itertools.combinations(q, 2):
        assert q1 - q0 <= rate * (t1 - t0) + slack_um, f"{q1 - q0:.3f} um in {t1 - t0:.4f} s"
    duration = q[-1][0] - q[0][0]
    assert duration >= (q[-1][1] - q[0][1]) / rate - 0.05
    assert len(cell.daemon.log_events("actuator_unramped")) == 1  # once: after the first write the stage is known


@pytest.mark.parametrize("safe", ["1.5", "nan"])
def test_an_actuator_edit_reopens_it_and_sigterm_writes_a_finite_safe_voltage(
        tmp_path: Path, module: OutputModule, cells: list[Cell], safe: str) -> None:
    cell = Cell(tmp_path, module.server.port, actuator=f"safe_voltage_v = {safe}")
    cells.append(cell)
    ok, command = cell.target(100.0)
    assert ok, command
    wait_until(lambda: module.register() == raw_for(command["voltage_v"]), 10, "register 10")

    cell.write_config(address=12, actuator=f"safe_voltage_v = {safe}")  # [actuator] edited: rebuilt, reopened
    cell.daemon.signal(1)  # SIGHUP
    applied = cell.daemon.wait_log("reload_applied", timeout=15)
    assert applied["drivers_restarted"] is True
    ok, command = cell.target(200.0)
    assert ok, command
    wait_until(lambda: module.register(12) == raw_for(command["voltage_v"]), 10, "register 12 after the reload")
    assert cell.actuator_status()["device"].endswith("holding register 12)")
    before_10 = module.register(10)

    assert cell.close() == 0
    if safe == "nan":
        assert module.register(12) == raw_for(command["voltage_v"]), "nan: the stage stays where it was"
        assert not cell.daemon.log_events("actuator_safe")
    else:
        assert module.register(12) == raw_for(float(safe))
        assert cell.daemon.log_events("actuator_safe")[0]["voltage_v"] == float(safe)
    assert module.register(10) == before_10  # the old output is no longer written


def wait_refused(cell: Cell, x_um: float = 300.0, timeout: float = 15.0) -> dict[str, Any]:
    """Send targets until one is refused with kind actuator_fault; that error."""

    def refused() -> dict[str, Any] | None:
        ok, answer = cell.target(x_um)
        return answer if not ok and answer.get("kind") == "actuator_fault" else None

    return wait_until(refused, timeout, "a target refused with kind actuator_fault", interval=0.05)


def wait_served(cell: Cell, x_um: float, timeout: float = 20.0) -> dict[str, Any]:
    """Send targets until one is served (after a fault, the first ones may still be refused); its command."""

    def served() -> dict[str, Any] | None:
        ok, answer = cell.target(x_um)
        return answer if ok else None

    return wait_until(served, timeout, f"a target of {x_um} um served", interval=0.05)


def test_the_first_target_after_start_is_ramped_from_the_voltage_the_register_holds(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 300.0  # 1.6 s for 0 -> 480 um (the 100 um/s case is the slew test above)
    held_raw = raw_for(VOLTS_PER_UM * expected_q(0.0, TEMPS))  # an earlier run left the stage at 0 um
    module.hold(held_raw)
    cell = Cell(tmp_path, module.server.port, actuator=f"max_slew_um_per_s = {rate}")  # verify = true: readable
    cells.append(cell)
    opened = cell.daemon.log_events("actuator_open")
    assert opened[0]["known_from"] == "read back" and opened[0]["voltage_v"] == pytest.approx(held_raw * SCALE)
    assert module.stamps == []  # nothing written at start
    ok, jump = cell.target(480.0)
    assert ok, jump
    target_raw = raw_for(jump["voltage_v"])
    wait_until(lambda: module.register() == target_raw, 20, "the ramp's end at 480 um", interval=0.05)
    q = [(t, raw * SCALE / VOLTS_PER_UM) for t, address, raw in module.stamps if address == ADDRESS]
    held_q = held_raw * SCALE / VOLTS_PER_UM
    # one count, and 100 ms of stamping jitter: the server's thread stamps arrivals, and a loaded machine delays
    # one write against the next (10 ms failed once under load). A ramp 20 % too fast still fails over its 1.7 s.
    slack_um = SCALE / VOLTS_PER_UM + rate * 0.100
    assert held_q < q[0][1] <= held_q + rate * RAMP_PERIOD_S + slack_um  # one ramp step from the register's value
    # a ramp, however many steps a loaded machine's loop managed (each step covers the time since the last)
    assert len(q) >= 3 and q[-1][1] == target_raw * SCALE / VOLTS_PER_UM
    assert all(b >= a for (_, a), (_, b) in itertools.pairwise(q)), "the ramp went backwards"
    for (t0, q0), (t1, q1) in itertools.combinations(q, 2):
        assert q1 - q0 <= rate * (t1 - t0) + slack_um, f"{q1 - q0:.3f} um in {t1 - t0:.4f} s"
    assert not cell.daemon.log_events("actuator_unramped")


def test_a_module_that_mangles_its_writes_refuses_targets_until_it_stores_what_it_is_sent(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    cell = Cell(tmp_path, module.server.port)  # verify = true (the default)
    cells.append(cell)
    ok, command = cell.target(100.0)
    assert ok, command
    wait_until(lambda: module.register() == raw_for(command["voltage_v"]), 10, "register at 100 um")

    module.mangle = True  # from now on the module stores 7 counts more than it is sent
    ok, answered = cell.target(200.0)  # answered at once; its write is read back wrong
    assert ok, answered
    error = wait_refused(cell)
    # the faulted write is 200 um's or, coalesced, a newer target's (wait_refused sends more): whichever, the
    # module held 7 counts more than it was sent
    found = re.search(r"wrote raw (\d+) \(([-\d.]+) V\), read back raw (\d+) \(([-\d.]+) V\)", error["error"])
    assert error["kind"] == "actuator_fault" and found, error
    wrote = int(found[1])
    assert int(found[3]) == wrote + 7 and abs(float(found[2]) - wrote * SCALE) <= SCALE / 2 + 1e-4  # the sent V
    reason = found[0]
    status = cell.actuator_status()
    assert status["state"] == "fault" and reason in status["reason"] and status["failures"] >= 1
    assert cell.client.status()["counters"]["errors"]["actuator_fault"] >= 1

    module.mangle = False  # the module takes writes again: the latest command is written and verified
    recovered = cell.daemon.wait_log("actuator_recovered", timeout=20)
    assert recovered["device"].endswith("holding register 10)")
    command = wait_served(cell, 150.0)
    wait_until(lambda: module.register() == raw_for(command["voltage_v"]), 10, "register after recovery")
    assert cell.actuator_status()["state"] == "ok"


def test_a_gcs_controller_that_answers_errors_or_goes_silent_refuses_targets_and_recovers(
        tmp_path: Path, cells: list[Cell]) -> None:
    controller = FakeGcsController(tmp_path / "ttyPI")
    try:
        keys = (f'kind = "serial_line"\nport = "{controller.port}"\nreadback = "SVA? 1\\n"\nerror_query = "ERR?\\n"\n'
                "timeout_s = 0.3\n")
        cell = Cell(tmp_path, None, keys=keys)
        cells.append(cell)
        assert cell.daemon.log_events("actuator_open")[0]["known_from"] == "read back"
        ok, command = cell.target(100.0)
        assert ok, command
        wait_until(lambda: controller.voltage == round(command["voltage_v"], 4), 10, "SVA of 100 um")
        assert cell.actuator_status()["device"] == f"controller on {controller.port}"

        # an error code for every query: the readback (idle verification) or the ERR? after the target's
        # write meets it first, whichever the daemon asks first; either way the fault quotes the '7'
        answering_7 = ("unexpected answer '7' to 'SVA? 1\\n'", "the controller reports error '7' after 'SVA 1 ")
        for trouble, reasons in ((("answer", b"7"), answering_7),
                                 (("silent", True), ("no answer to 'SVA? 1\\n' within 0.3 s",))):
            name, value = trouble
            setattr(controller, name, value)
            cell.target(250.0)  # served before the trouble is noticed: its write fails
            error = wait_refused(cell)
            assert any(reason in error["error"] for reason in reasons), error
            status = cell.actuator_status()
            assert status["state"] == "fault" and any(reason in status["reason"] for reason in reasons), status
            setattr(controller, name, None if name == "answer" else False)  # the controller answers properly again
            episodes = len(cell.daemon.log_events("actuator_recovered")) + 1
            cell.daemon.wait_log("actuator_recovered", timeout=20, count=episodes)
            command = wait_served(cell, 50.0 * episodes)
            wait_until(lambda c=command: controller.voltage == round(c["voltage_v"], 4), 10, "SVA after recovery")
            assert cell.actuator_status()["state"] == "ok"
        assert len(cell.daemon.log_events("actuator_failed")) == 2  # one line per episode
    finally:
        for cell in cells:
            cell.close()
        cells.clear()
        controller.close()


# --- a lab's own output: a plugin that is not part of nanodrift ---------------------------------


class LabOutputConfig(ActuatorOptions):
    """``[actuator] kind = "labout"``: one channel of a lab's own output box, here a file of JSON lines."""

    kind: Literal["labout"] = "labout"
    path: str
    channel: int = Field(default=1, ge=1, le=4)
    full_scale_v: float = Field(default=10.0, gt=0)

    def voltage_range_problem(self, v_min: float, v_max: float, volts_per_um: float) -> str | None:
        if v_min < 0.0 or v_max > self.full_scale_v:
            return f"channel {self.channel} puts out 0..{self.full_scale_v:g} V, not [{v_min:g}, {v_max:g}] V"
        return None


class LabOutput(Actuator):
    """Appends ``{"channel", "voltage_v"}`` per command; the last line is where the output is."""

    def __init__(self, config: LabOutputConfig) -> None:
        self.config = config
        self.path = Path(config.path)
        self.description = f"lab output box channel {config.channel}"

    async def open(self) -> None:
        self.path.touch()

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        lines = self.path.read_text().splitlines()
        return ("voltage_v", float(json.loads(lines[-1])["voltage_v"])) if lines else None

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        with self.path.open("a") as out:
            out.write(json.dumps({"channel": self.config.channel, "voltage_v": voltage_v}) + "\n")

    async def close(self) -> None:
        return None


class LabPlugin(FilePlugin):
    """The harness' ``file`` sensor plugin plus an output: what a lab's own driver package declares."""

    name = "labout"
    actuator_model = LabOutputConfig

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        assert isinstance(config, LabOutputConfig)
        return LabOutput(config)


LAB_PLUGIN = LabPlugin()


def install_lab_plugin(directory: Path) -> list[Path]:
    """A dist-info declaring ``labout = test_actuation:LAB_PLUGIN``; the PYTHONPATH entries that find it."""
    info = directory / "nanodrift_lab_output-0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: nanodrift-lab-output\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text("[nanodrift.drivers]\nlabout = test_actuation:LAB_PLUGIN\n")
    return [directory, Path(__file__).resolve().parent]


def test_a_labs_own_output_plugin_is_validated_by_its_own_model_and_driven_by_the_daemon(
        tmp_path: Path, cells: list[Cell]) -> None:
    pythonpath = install_lab_plugin(tmp_path / "lab")
    box = tmp_path / "box.jsonl"
    box.write_text(json.dumps({"channel": 2, "voltage_v": 2.0}) + "\n")  # where an earlier run left it
    limits = "v_min = 0.0\nv_max = 10.0\n"

    def check(keys: str) -> subprocess.CompletedProcess[str]:
        config = tmp_path / "check.toml"
        config.write_text(file_sensor_config(tmp_path, cell="lab", port=free_port(), model_path=tmp_path / "m.json",
                                             sensor_file=tmp_path / "s.json", actuator=keys))
        env = {**os.environ, "PYTHONPATH": os.pathsep.join(
            [str(p) for p in (*pythonpath, install_file_plugin(tmp_path / "plugins"), TESTS, REPO)])}
        return subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(config)],
                              capture_output=True, text=True, env=env, cwd=str(REPO), timeout=60)

    refused = check(f'kind = "labout"\npath = "{box}"\nchanel = 2\nchannel = 9\n{limits}')
    assert refused.returncode != 0
    assert "actuator.chanel" in refused.stderr and "actuator.channel" in refused.stderr, refused.stderr
    too_wide = check(f'kind = "labout"\npath = "{box}"\nchannel = 2\nv_min = 0.0\nv_max = 12.0\n')
    assert too_wide.returncode != 0
    assert "channel 2 puts out 0..10 V, not [0, 12] V" in too_wide.stderr, too_wide.stderr

    cell = Cell(tmp_path, None, keys=f'kind = "labout"\npath = "{box}"\nchannel = 2\n',
                actuator=f"{limits}max_slew_um_per_s = 5000.0\n", pythonpath=pythonpath)
    cells.append(cell)
    opened = cell.daemon.log_events("actuator_open")[0]
    assert opened == {**opened, "device": "lab output box channel 2", "voltage_v": 2.0, "known_from": "read back"}
    status = cell.actuator_status()
    assert status["kind"] == "labout" and status["device"] == "lab output box channel 2" and status["state"] == "ok"
    for x in (100.0, 250.0):
        ok, command = cell.target(x)
        assert ok, command

        def last(want: float = command["voltage_v"]) -> bool:
            line = box.read_text().splitlines()[-1]
            return json.loads(line) == {"channel": 2, "voltage_v": want}

        wait_until(last, 10, f"the box at {x} um")
    voltages = [json.loads(line)["voltage_v"] for line in box.read_text().splitlines()[1:]]
    assert len(voltages) > 2 and all(0.0 <= v <= 10.0 for v in voltages)  # ramped from 2 V, inside the limits
    assert cell.actuator_status()["writes"] == len(voltages)


class RoundsOutward(RecordingActuator):
    """A device whose representation of a voltage lands 0.05 V above it (a template that rounds up)."""

    def sent_voltage(self, voltage_v: float) -> float:
        return voltage_v + 0.05


def test_what_the_device_would_receive_is_checked_against_the_limits_not_what_was_asked() -> None:
    """Issue 16.8: the value after the device's own rounding must lie inside [v_min, v_max], or nothing is sent."""
    log = Events()
    config = ActuatorConfig(v_max=10.0)
    device = RoundsOutward()

    async def main() -> None:
        actuation = Actuation(log)
        await actuation.start(device, config)
        command(actuation, config, 100.0)  # 2.0 V, sent as 2.05 V: inside
        await until(lambda: len(device.written) == 1, 5, "the first command written")
        command(actuation, config, 499.0)  # 9.98 V would be sent as 10.03 V: outside
        await until(lambda: actuation.fault_reason is not None, 5, "the refusal")
        await actuation.stop()

    asyncio.run(main())
    assert [v for _, v, _ in device.written] == [2.0]  # nothing sent for 9.98 V
    [failed] = log.named("actuator_failed")
    assert "would be sent as 10.030000 V, outside [-2, 10] V: nothing written" in failed["error"]


def test_a_reload_onto_an_output_that_opens_ends_the_fault_and_says_so() -> None:
    """Issue 16.11: a reload that cleared an actuator fault logged no ``actuator_recovered``."""
    log = Events()
    config = ActuatorConfig()

    async def main() -> None:
        actuation = Actuation(log)
        dead = RecordingActuator(description="output A")
        dead.broken = True
        await actuation.start(dead, config)
        assert actuation.fault_reason is not None and len(log.named("actuator_failed")) == 1
        await actuation.stop()  # an [actuator] edit: the daemon restarts the actuation ...
        fixed = RecordingActuator(description="output B")  # ... on an output that opens
        await actuation.start(fixed, config)
        assert actuation.fault_reason is None
        await actuation.stop()

    asyncio.run(main())
    [recovered] = log.named("actuator_recovered")
    assert recovered["via"] == "reload" and recovered["device"] == "output B" and recovered["failures"] >= 1
