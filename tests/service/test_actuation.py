"""The daemon drives the stage: latest command wins, slew ramps (from where the stage is), faults refuse
targets, safe voltage on stop, and a lab's own output plugin.

Real peers: ``nanodrift run`` as a process (the ``file`` sensor plugin for temperatures) with
``[actuator] kind = "modbus"`` writing to pymodbus' own TCP server on 127.0.0.1, which runs on an
asyncio loop in a thread of this process and stamps every write as it lands; ``kind = "serial_line"``
talking GCS to a PI controller emulated on a pty; ``kind = "labout"``, a plugin defined here (not part
of nanodrift) and registered through an entry point as a lab's package would be; and a cell of several
axes: three axes of one GCS controller on one pty, two outputs of one Modbus module. Every wait polls a
condition with a deadline. The actuation's rules in process, on a one-axis and an XY cell, are in
``test_actuation_rules.py``.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import re
import subprocess
import threading
import time
from collections.abc import Callable, Coroutine, Iterator, Sequence
from pathlib import Path
from typing import Any, Literal

import pytest
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    FilePlugin,
    SensorFile,
    expected_q,
    file_sensor_config,
    free_port,
    install_file_plugin,
    run_cli,
    wait_until,
    write_test_model,
)
from helpers.edge_cell import confirm_output, state_dir_keys
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer
from helpers.serial_helpers import FakeGcsController
from pydantic import Field

from nanodrift.assembly import build_drivers
from nanodrift.config import parse_config
from nanodrift.drivers.base import Actuator, ActuatorOptions, DriverContext
from nanodrift.logs import get_logger
from nanodrift.motion import RAMP_PERIOD_S
from nanodrift.service.actuation import Actuation

SCALE = 0.001  # volts per count
ADDRESS = 10
VOLTS_PER_UM = 0.02


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
                 keys: str | None = None, pythonpath: Sequence[Path] = (), confirmed_v: float | None = None) -> None:
        """``confirmed_v``: an operator confirmed the output holds it before the daemon starts (issue 26.5)."""
        self.root = root
        self.state = state_dir_keys(root) if confirmed_v is not None else ""
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
        if confirmed_v is not None:
            confirmed = confirm_output(self.config_path, [self.plugins, *pythonpath], "--voltage", repr(confirmed_v))
            assert confirmed.returncode == 0, confirmed.stderr
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
            actuator=keys, extra=hub + self.state))

    def target(self, x_um: float) -> tuple[bool, dict[str, Any]]:
        return self.client.query({"x_um": x_um, "id": next(self._ids)})

    def actuator_status(self) -> dict[str, Any]:
        return self.client.status()["actuator"]

    def close(self) -> int:
        if self.client is not None:
            self.client.close()
            self.client = None  # type: ignore[assignment]
        return self.daemon.stop()


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
    assert len(stamps) > 10, f"{len(stamps)} writes: no ramp"  # hundreds idle; fewer on a loaded machine
    q = [(t, (raw * SCALE) / VOLTS_PER_UM) for t, raw in stamps]
    assert all(b >= a for (_, a), (_, b) in itertools.pairwise(q)), "the ramp went backwards"
    # one count, and 100 ms of stamping jitter: the server's thread stamps arrivals, and a loaded machine delays
    # one write against the next (10 ms failed once under load). A ramp 10 % too fast still fails within 1 s.
    slack_um = SCALE / VOLTS_PER_UM + rate * 0.100
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
    # verify = true: readable; an operator confirmed what it holds (issue 26.5: else only 0 V, its power-up value)
    cell = Cell(tmp_path, module.server.port, actuator=f"max_slew_um_per_s = {rate}", confirmed_v=held_raw * SCALE)
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
        # a second: the controller answers from a thread of this process, which a loaded machine can hold up for
        # tenths of a second (0.3 s made a slow answer of '7' a silence: "no answer to 'ERR?'")
        keys = (f'kind = "serial_line"\nport = "{controller.port}"\nreadback = "SVA? 1\\n"\nerror_query = "ERR?\\n"\n'
                "timeout_s = 2.0\n")
        cell = Cell(tmp_path, None, keys=keys)
        cells.append(cell)
        # the controller's power-up value: a first start believes nothing else (issue 26.5)
        assert cell.daemon.log_events("actuator_open")[0]["known_from"] == "power-up value"
        ok, command = cell.target(100.0)
        assert ok, command
        wait_until(lambda: controller.voltage == round(command["voltage_v"], 4), 10, "SVA of 100 um")
        assert cell.actuator_status()["device"] == f"controller on {controller.port}"

        # an error code for every query: the readback (idle verification) or the ERR? after the target's
        # write meets it first, whichever the daemon asks first; either way the fault quotes the '7'
        answering_7 = ("unexpected answer '7' to 'SVA? 1\\n'", "the controller reports error '7' after 'SVA 1 ")
        for trouble, reasons in ((("answer", b"7"), answering_7),
                                 # silence: the idle readback or the ERR? after the target's write, whichever
                                 # is asked first (a loaded machine delays the readback past the write)
                                 (("silent", True), ("no answer to 'SVA? 1\\n' within 2 s",
                                                     "no answer to 'ERR?\\n' within 2 s after 'SVA 1 "))):
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
        return run_cli("check-config", str(config),
                       pythonpath=[*pythonpath, install_file_plugin(tmp_path / "plugins")])

    refused = check(f'kind = "labout"\npath = "{box}"\nchanel = 2\nchannel = 9\n{limits}')
    assert refused.returncode != 0
    assert "actuator.chanel" in refused.stderr and "actuator.channel" in refused.stderr, refused.stderr
    too_wide = check(f'kind = "labout"\npath = "{box}"\nchannel = 2\nv_min = 0.0\nv_max = 12.0\n')
    assert too_wide.returncode != 0
    assert "channel 2 puts out 0..10 V, not [0, 12] V" in too_wide.stderr, too_wide.stderr

    cell = Cell(tmp_path, None, keys=f'kind = "labout"\npath = "{box}"\nchannel = 2\n',
                actuator=f"{limits}max_slew_um_per_s = 5000.0\n", pythonpath=pythonpath, confirmed_v=2.0)
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


# --- a cell of several axes: one GCS controller's line, one Modbus module's connection ------------

AXES = {"x": "1", "y": "2", "z": "3"}


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[FakeGcsController]:
    fake = FakeGcsController(tmp_path / "ttyPI", axes=tuple(AXES.values()))
    yield fake
    fake.close()


def three_axis_config(port: str, *, slew: float = 0.0) -> dict[str, object]:
    return {
        "cell": "xyz",
        "axes": [{"name": axis, "min_um": 0.0, "max_um": 500.0,
                  "actuator": {"kind": "serial_line", "port": port, "command": f"SVA {n} {{voltage_v:.4f}}\n",
                               "readback": f"SVA? {n}\n", "timeout_s": 2.0, "safe_voltage_v": 0.0,
                               "max_slew_um_per_s": slew}}
                 for axis, n in AXES.items()],
    }


async def until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.005)


def sva_lines(controller: FakeGcsController) -> list[tuple[str, float]]:
    return [(m[1], float(m[2])) for line in list(controller.lines) if (m := re.fullmatch(r"SVA (\d) (\S+)", line))]


def test_three_axes_share_one_line_and_each_command_is_written_whole_before_the_next(
        controller: FakeGcsController) -> None:
    config = parse_config(three_axis_config(controller.port))
    drivers = build_drivers(config)
    assert list(drivers.actuators) == ["x", "y", "z"]
    lines = {id(a.port) for a in drivers.actuators.values()}  # type: ignore[attr-defined]
    assert len(lines) == 1, "the three axes of one controller share one line (one lock)"

    goals = [{axis: round(0.5 + 0.37 * k + i, 4) for i, axis in enumerate(AXES)} for k in range(12)]

    async def scenario() -> None:
        actuation = Actuation(get_logger("test"))
        await actuation.start(drivers.actuators, config.axis_actuators())
        try:
            for goal in goals:  # a burst: newer commands replace pending ones, never half of one
                actuation.offer({a: v / 0.02 for a, v in goal.items()}, goal)
                if actuation._active:
                    actuation.wake()
                await asyncio.sleep(0.004)
            last = goals[-1]
            await until(lambda: all(abs(controller.voltages[AXES[a]] - v) < 1e-9 for a, v in last.items()), 5,
                        "the last command on every axis")
            assert actuation.fault_reason is None
        finally:
            await actuation.stop(final=True)

    asyncio.run(scenario())
    written = sva_lines(controller)
    # the safe stop writes 0 V to each axis on its own (issue 26.8: one axis never waits for another), so in any
    # order, and a write that timed out waiting for the shared line is retried: the trailing 0 V lines
    served_count = len(written)
    while served_count and written[served_count - 1][1] == 0.0:
        served_count -= 1
    safe = sorted(set(written[served_count:]))
    served = [written[i:i + 3] for i in range(0, served_count, 3)]
    assert served_count % 3 == 0 and len(served) >= 2, written
    offered = [tuple((AXES[a], v) for a, v in goal.items()) for goal in goals]
    for group in served:  # axis 1, 2, 3 of one command, then the next command's
        assert tuple(group) in offered, (group, written)
    assert tuple(served[-1]) == offered[-1]
    assert [offered.index(tuple(g)) for g in served] == sorted(offered.index(tuple(g)) for g in served)
    assert safe == [("1", 0.0), ("2", 0.0), ("3", 0.0)]  # the safe stop: every axis at its safe_voltage_v
    assert all(controller.voltages[AXES[a]] == 0.0 for a in AXES), controller.voltages


def test_a_slewed_three_axis_move_ramps_each_axis_at_its_own_rate_in_steps_of_whole_commands(
        controller: FakeGcsController) -> None:
    config = parse_config(three_axis_config(controller.port, slew=500.0))  # 10 V/s at 0.02 V/um
    drivers = build_drivers(config)
    x_landed: list[tuple[float, float]] = []  # (time.monotonic(), V) as each of x's values lands on the controller
    controller.on_voltage = lambda volts: x_landed.append((time.monotonic(), volts))

    async def scenario() -> float:
        actuation = Actuation(get_logger("test"), safe_budget_s=5.0)
        await actuation.start(drivers.actuators, config.axis_actuators())
        began = time.monotonic()
        try:
            goal = {"x": 4.0, "y": 2.0, "z": 0.0}
            actuation.offer({a: v / 0.02 for a, v in goal.items()}, goal)
            actuation.wake()
            await until(lambda: abs(controller.voltages["1"] - 4.0) < 1e-9, 5, "x at 4 V")
            return time.monotonic() - began
        finally:
            await actuation.stop(final=False)

    asyncio.run(scenario())
    written = sva_lines(controller)
    x_steps = [v for n, v in written if n == "1"]
    # a ramp, not a jump: the first step from rest covers one ramp period (0.2 V); the others the time since the
    # previous write returned (a pause of 9x the write time on a slow or loaded line: fewer, larger steps)
    assert len(x_steps) >= 3 and x_steps[0] == pytest.approx(10.0 * RAMP_PERIOD_S) and x_steps[-1] == 4.0, x_steps
    # on the device: never faster than 10 V/s between two values it received (100 ms of stamping jitter)
    for (t0, v0), (t1, v1) in itertools.pairwise(x_landed):
        assert v1 - v0 <= 10.0 * (t1 - t0 + RAMP_PERIOD_S + 0.1), (x_landed, x_steps)
    axes_in_order = [n for n, _ in written]
    assert axes_in_order[:3] == ["1", "2", "3"]  # each step writes the axes in the cell's order
    assert [v for n, v in written if n == "2"][-1] == 2.0 and all(v == 0.0 for n, v in written if n == "3")


def test_two_axes_of_one_modbus_module_share_one_connection_and_its_lock() -> None:
    axes = [{"name": axis, "min_um": 0.0, "max_um": 500.0,
             "actuator": {"kind": "modbus", "hub": "dac", "address": address, "scale": 0.001}}
            for axis, address in (("x", 10), ("y", 11))]
    config = parse_config({"cell": "xy", "axes": axes, "hubs": [{"name": "dac", "port": 5020}]})
    drivers = build_drivers(config)
    x, y = drivers.actuators["x"], drivers.actuators["y"]
    assert x.hub is y.hub  # type: ignore[attr-defined]  # one ModbusHub: one connection, one lock
    assert (x.config.address, y.config.address) == (10, 11)  # type: ignore[attr-defined]
