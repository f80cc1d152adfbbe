"""The daemon drives the stage: latest command wins, slew ramps, faults refuse targets, safe voltage on stop.

Real peers: ``nanodrift run`` as a process (the ``file`` sensor plugin for temperatures) with
``[actuator] kind = "modbus"`` writing to pymodbus' own TCP server on 127.0.0.1, which runs on an
asyncio loop in a thread of this process and stamps every write as it lands. Every wait polls a
condition with a deadline.
"""

from __future__ import annotations

import asyncio
import itertools
import math
import threading
import time
from collections.abc import Coroutine, Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    expected_q,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer
from hypothesis import given, settings
from hypothesis import strategies as st

from daemon.config import ActuatorConfig
from daemon.service.actuation import RAMP_PERIOD_S, Actuation, plan_ramp
from drivers.base import Actuator

SCALE = 0.001  # volts per count
ADDRESS = 10
VOLTS_PER_UM = 0.02


# --- the ramp planner ----------------------------------------------------------------------------

positions = st.floats(min_value=-600.0, max_value=600.0, allow_nan=False)
rates = st.floats(min_value=1.0, max_value=5000.0, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(start=positions, target=positions, rate=rates)
def test_a_ramp_never_exceeds_the_rate_is_monotone_and_ends_at_the_target(start: float, target: float,
                                                                          rate: float) -> None:
    plan = plan_ramp(start, target, rate, RAMP_PERIOD_S)
    assert plan[-1] == target
    step = rate * RAMP_PERIOD_S
    points = [start, *plan]
    for a, b in itertools.pairwise(points):
        assert abs(b - a) <= step * (1 + 1e-9)
        assert (b - a) * (target - start) >= 0  # never moves away from the target
    steps = abs(target - start) / step  # rounding may add one tiny last step
    assert max(1, math.ceil(steps - 1e-9)) <= len(plan) <= max(1, math.ceil(steps + 1e-9) + 1)


@given(start=positions, target=positions)
def test_no_ramp_when_the_limit_is_off(start: float, target: float) -> None:
    assert plan_ramp(start, target, 0.0) == [target]


# --- Actuation in process: order and coalescing --------------------------------------------------


class RecordingActuator(Actuator):
    description = "recording actuator"

    def __init__(self, write_s: float = 0.0) -> None:
        self.written: list[tuple[float, float, float | None]] = []
        self.write_s = write_s

    async def open(self) -> None:
        return None

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        await asyncio.sleep(self.write_s)
        self.written.append((q_um, voltage_v, x_um))

    async def close(self) -> None:
        return None


class Silent:
    def __getattr__(self, name: str) -> Any:
        return lambda *a, **k: None


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


# --- a Modbus output module on a thread ----------------------------------------------------------


class OutputModule:
    """pymodbus' TCP server on its own loop thread; ``stamps`` is every write of the output register."""

    def __init__(self) -> None:
        self.device = ModbusTestDevice(1, holding_ranges=((0, 32),))
        self.server = ModbusTestServer([self.device])
        self.stamps: list[tuple[float, int, int]] = []  # (time.monotonic(), address, raw)
        self.device.on_write = self._landed
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="modbus-output", daemon=True)
        self._thread.start()
        self.call(self.server.start())

    def _landed(self, address: int, values: list[int]) -> None:
        now = time.monotonic()
        self.stamps.extend((now, address + i, _signed(v)) for i, v in enumerate(values))

    def call(self, coro: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def register(self, address: int = ADDRESS) -> int:
        return _signed(self.call(self.server.get_registers(1, address, 1))[0])

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
    """``nanodrift run`` with file sensors and a Modbus output, and a client."""

    def __init__(self, root: Path, port_modbus: int, *, address: int = ADDRESS, actuator: str = "") -> None:
        self.root = root
        self.cell = f"act{free_port()}"
        self.port = free_port()
        self.port_modbus = port_modbus
        self.plugins = install_file_plugin(root / "plugins")
        self.model_path = root / "model.json"
        write_test_model(self.model_path)
        self.sensors = SensorFile(root / "sensors.json", TEMPS)
        self.config_path = root / "nanodrift.toml"
        self.write_config(address=address, actuator=actuator)
        self.daemon = Daemon(["--config", str(self.config_path)], root / "daemon.log", [self.plugins])
        self.daemon.wait_log("serving", timeout=30)
        self.client = Client(self.port, self.cell)
        self.client.wait_alive()
        self.client.wait_ready(("T1", "T2"))
        self._ids = itertools.count(1)

    def write_config(self, *, address: int, actuator: str) -> None:
        keys = (f'kind = "modbus"\nhub = "out"\ndevice_id = 1\naddress = {address}\nscale = {SCALE}\n'
                f"volts_per_um = {VOLTS_PER_UM}\n{actuator}")
        hub = f'[[hubs]]\nname = "out"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {self.port_modbus}\ntimeout_s = 0.3\n'
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
    actuator = cell.actuator_status()
    assert list(actuator)[:9] == ["volts_per_um", "offset_v", "v_min", "v_max", "x_min_um", "x_max_um", "kind",
                                  "max_slew_um_per_s", "safe_voltage_v"]
    assert actuator["state"] == "ok" and actuator["reason"] is None and actuator["output"] == "device"
    assert actuator["last_voltage_v"] == command["voltage_v"] and actuator["writes"] >= 2
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
    slack_um = SCALE / VOLTS_PER_UM + rate * 0.010  # one count, and 10 ms of stamping jitter
    for (t0, q0), (t1, q1) in itertools.combinations(q, 2):
        assert q1 - q0 <= rate * (t1 - t0) + slack_um, f"{q1 - q0:.3f} um in {t1 - t0:.4f} s"
    duration = q[-1][0] - q[0][0]
    assert duration >= (q[-1][1] - q[0][1]) / rate - 0.05


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
