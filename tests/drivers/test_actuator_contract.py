"""The actuator contract (``nanodrift.drivers.testing.contract``) run against every plugin that can move the
stage, exactly as a lab runs it against its own plugin: a rig per plugin, a ``Test...`` subclass per rig.

- ``simulated``: the simulated cell's closed loop (it takes ``q_um``); its outputs: the stacked XY stage;
- ``modbus``: an analog output (holding register 10, int16, 1 mV per count, ``verify``) on pymodbus'
  TCP server on 127.0.0.1 (``nanodrift.drivers.testing``); its outputs: registers 10 and 11 on one hub;
- ``serial_line``: a PI controller speaking GCS on a pty (``SVA 1 {voltage_v:.4f}``, ``SVA? 1``
  read back, ``ERR?``; ``nanodrift.drivers.testing``); its outputs: axes 1 and 2 on one port;
- ``pi_gcs``: a PI controller speaking GCS 2.0 (``nanodrift.drivers.testing.pi_gcs_emulator``), open loop
  (``SVA``), over TCP on 127.0.0.1 and on a pty; its outputs: axes 1 and 2 of one controller, one connection;
- ``labbox``: a lab's own output (``tests/helpers/lab_plugin.py``), found through a real entry point;
  its outputs: channels 1 and 2 of one box.

Every assertion on what was written looks at the emulator's side (the register, the lines the
controller received, the box's file, the cell's setpoint), never at the actuator's own account.
"""

from __future__ import annotations

import json
import re
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import serial
from helpers import lab_plugin
from pymodbus.constants import ExcCodes

from nanodrift.drivers.base import Actuator, DriverContext
from nanodrift.drivers.modbus.codec import decode
from nanodrift.drivers.registry import available, load_plugin
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.config import SECTION, SimulationConfig
from nanodrift.drivers.simulated.plugin import RESOURCE_KEY
from nanodrift.drivers.testing import FakeGcsController, ModbusTestDevice, ModbusTestServer, tcp_context
from nanodrift.drivers.testing.contract import GAIN_V_PER_UM, ActuatorContract, ActuatorRig
from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice, PiGcsTcpServer

# --- the rigs -------------------------------------------------------------------------------------


class SimulatedRig(ActuatorRig):
    kind = "simulated"
    reads_back = "q_um"
    limit_case = ((0.0, 5.0), 5.0, 5.0)
    can_fail = False
    multi_output_unsupported = None
    AXES = ("x", "y")

    def options(self) -> dict[str, Any]:
        return {"kind": "simulated"}

    def actuator(self) -> Actuator:
        actuator = super().actuator()
        cell = self.built_context.resources.get(RESOURCE_KEY, SimulatedCell)
        assert cell is not None
        self.cell = cell
        self.setpoints: list[float] = []
        command = self.cell.command

        def recorded(axis: str, q_um: float) -> None:  # the cell's side: what its closed loop was given
            self.setpoints.append(q_um)
            command(axis, q_um)

        self.cell.command = recorded  # type: ignore[method-assign]
        return actuator

    async def held_v(self) -> float:
        return self.cell.states["x"].q * GAIN_V_PER_UM

    def written_v(self) -> list[float]:
        return [q * GAIN_V_PER_UM for q in self.setpoints]

    def output_options(self) -> list[dict[str, Any]]:
        return [{"kind": "simulated"} for _ in self.AXES]

    def outputs_context(self) -> DriverContext:
        return DriverContext(sections={SECTION: SimulationConfig(axes="".join(self.AXES))})

    def actuators(self) -> list[Actuator]:
        outputs = super().actuators()
        cell = self.built_context.resources.get(RESOURCE_KEY, SimulatedCell)
        assert cell is not None
        self.axis_setpoints: dict[str, list[float]] = {axis: [] for axis in self.AXES}
        command = cell.command

        def recorded(axis: str, q_um: float) -> None:  # the stacked stage's side: each axis' closed loop
            self.axis_setpoints[axis].append(q_um)
            command(axis, q_um)

        cell.command = recorded  # type: ignore[method-assign]
        return outputs

    def output_written_v(self, index: int) -> list[float]:
        return [q * GAIN_V_PER_UM for q in self.axis_setpoints[self.AXES[index]]]


class OverlapWatchingDevice(ModbusTestDevice):
    """A register map that notes every request arriving while another is still being answered."""

    def __init__(self, device_id: int, **ranges: Any) -> None:
        super().__init__(device_id, **ranges)
        self.in_flight = 0
        self.overlaps: list[str] = []

    async def _action(self, function_code: int, _start: int, address: int, count: int,
                      _registers: list[int], set_values: object) -> ExcCodes | None:
        self.in_flight += 1
        if self.in_flight > 1 and not self.quiet:
            self.overlaps.append(f"function {function_code} at {address} while another request was answered")
        try:
            return await super()._action(function_code, _start, address, count, _registers, set_values)
        finally:
            self.in_flight -= 1


class ModbusRig(ActuatorRig):
    kind = "modbus"
    resolution_v = 0.001
    limit_case = ((0.0004, 4.9996), 4.9996, 4.999)  # the nearest count, 5.000 V, is outside
    unrepresentable = ((0.0, 50.0), 40.0)  # 40000 counts: beyond int16
    multi_output_unsupported = None
    ADDRESSES = (10, 11)

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.device = OverlapWatchingDevice(1, holding_ranges=((0, 32),))
        self.server = ModbusTestServer([self.device])

    def options(self) -> dict[str, Any]:
        return {"kind": "modbus", "hub": "adam", "address": 10, "data_type": "int16", "scale": 0.001,
                "verify": True}

    def context(self) -> DriverContext:
        return tcp_context(self.server.port, timeout_s=2.0)

    async def start(self) -> None:
        await self.server.start()

    async def stop(self) -> None:
        await self.server.stop()

    async def held_v(self) -> float:
        return float(decode(await self.server.get_registers(1, 10, 1), "int16")) * 0.001

    def written_v(self) -> list[float]:
        return self.output_written_v(0)

    async def refuse_writes(self) -> None:
        self.device.fail_writes_with = ExcCodes.DEVICE_FAILURE

    async def gone(self) -> None:
        await self.server.stop()

    async def back(self) -> None:
        self.device.fail_writes_with = None
        if self.server._server is None:
            await self.server.start()

    def output_options(self) -> list[dict[str, Any]]:
        self.device.write_delay_s = 0.005  # each write answered a little late: a request sneaking in shows
        return [{**self.options(), "address": address} for address in self.ADDRESSES]

    def output_written_v(self, index: int) -> list[float]:
        return [float(decode(values, "int16")) * 0.001 for _, address, values in self.device.writes
                if address == self.ADDRESSES[index]]

    def overlapping_exchanges(self) -> list[str]:
        strays = [f"a write at {address}, no output's register" for _, address, _ in self.device.writes
                  if address not in self.ADDRESSES]
        return self.device.overlaps + strays

    def connection_ids(self) -> set[str] | None:
        server = self.server._server
        return None if server is None else set(server.active_connections)


class SerialRig(ActuatorRig):
    kind = "serial_line"
    resolution_v = 0.0001
    limit_case = ((0.0, 4.99996), 4.99996, 4.9999)  # ".4f" writes 5.0000: outside
    unrepresentable = ((1.00001, 1.00004), 1.00002)  # ".4f" writes 1.0000 or 1.0001: both outside
    multi_output_unsupported = None
    AXES = ("1", "2")
    #: every request the actuators write, whole
    REQUEST = re.compile(r"SVA [12] [-+0-9.]+|SVA\? [12]|ERR\?")
    ASKS_AN_ANSWER = ("SVA?", "ERR?")

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.controller = FakeGcsController(tmp_path / "ttyPI", axes=self.AXES)

    def options(self) -> dict[str, Any]:
        return self.axis_options("1")

    def axis_options(self, axis: str) -> dict[str, Any]:
        return {"kind": "serial_line", "port": self.controller.port, "command": f"SVA {axis} {{voltage_v:.4f}}\n",
                "readback": f"SVA? {axis}\n", "error_query": "ERR?\n", "timeout_s": 2.0}

    async def stop(self) -> None:
        self.controller.close()

    async def held_v(self) -> float:
        return self.controller.voltage

    def written_v(self) -> list[float]:
        return self.output_written_v(0)

    async def refuse_writes(self) -> None:
        self.controller.amplifier_off = True  # SVA accepted, the voltage does not change

    async def gone(self) -> None:
        self.controller.unplug()

    async def back(self) -> None:
        self.controller.amplifier_off = False
        if not self.controller.link.exists():
            self.controller.replug()

    def output_options(self) -> list[dict[str, Any]]:
        return [self.axis_options(axis) for axis in self.AXES]

    def output_written_v(self, index: int) -> list[float]:
        return [float(m.group(1)) for line in list(self.controller.lines)
                if (m := re.fullmatch(rf"SVA {self.AXES[index]} (\S+)", line))]

    def overlapping_exchanges(self) -> list[str]:
        """A line that is not one whole request, or a request that came before the answer to the query
        before it left (answers leave in the order asked: the k-th answer is the k-th query's)."""
        lines, times = list(self.controller.lines), list(self.controller.line_times)
        answered_at = [t for t, _ in list(self.controller.sent)]
        found = [f"not a whole request: {line!r}" for line in lines if not self.REQUEST.fullmatch(line)]
        queries = [i for i, line in enumerate(lines) if line.split()[:1] and line.split()[0] in self.ASKS_AN_ANSWER]
        for k, i in enumerate(queries):
            if i + 1 < len(lines) and (k >= len(answered_at) or times[i + 1] < answered_at[k]):
                found.append(f"{lines[i + 1]!r} came before the answer to {lines[i]!r}")
        return found


class PiGcsTcpRig(ActuatorRig):
    """A PI controller (two axes, servo on at power-up as an E-727 with its stage) on TCP; the plugin switches
    the servo off at open and writes ``SVA`` with 6 decimals; someone switching the servo back on from
    outside makes the controller refuse ``SVA`` (error 79)."""

    kind = "pi_gcs"
    resolution_v = 1e-6
    limit_case = ((0.0, 4.9999996), 4.9999996, 4.999999)  # ".6f" writes 5.000000: outside
    unrepresentable = ((1.0000001, 1.0000004), 1.0000002)  # 1.000000 and 1.000001 are both outside
    multi_output_unsupported = None
    AXES = ("1", "2")

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.emulator = PiGcsEmulator(axes={axis: EmulatedAxis(servo=True) for axis in self.AXES})
        self.server = PiGcsTcpServer(self.emulator)

    def transport(self) -> dict[str, Any]:
        return {"host": "127.0.0.1", "port": self.server.port}

    def options(self) -> dict[str, Any]:
        return {"kind": "pi_gcs", **self.transport(), "axis": "1", "timeout_s": 2.0}

    async def start(self) -> None:
        await self.server.start()

    async def stop(self) -> None:
        await self.server.stop()

    async def held_v(self) -> float:
        return self.emulator.sva("1")

    def written_v(self) -> list[float]:
        return self.output_written_v(0)

    async def refuse_writes(self) -> None:
        self.emulator.set_servo("1", True)

    async def gone(self) -> None:
        await self.server.stop()

    async def back(self) -> None:
        self.emulator.set_servo("1", False)
        if not self.server.serving:
            await self.server.start()

    def output_options(self) -> list[dict[str, Any]]:
        return [{**self.options(), "axis": axis} for axis in self.AXES]

    def output_written_v(self, index: int) -> list[float]:
        return [float(line.split()[2]) for line in self.emulator.received("SVA")
                if line.split()[1] == self.AXES[index]]

    def overlapping_exchanges(self) -> list[str]:
        """Each SVA is one whole batch (ERR?, SVA, ERR?, SVA?) on the device: another axis' lines inside it
        would show two exchanges interleaved."""
        lines = self.emulator.received()
        found = []
        for i, line in enumerate(lines):
            words = line.split()
            if words[:1] == ["SVA"] and lines[i - 1:i + 3] != ["ERR?", line, "ERR?", f"SVA? {words[1]}"]:
                found.append(f"{line!r} not in one whole batch: {lines[max(0, i - 1):i + 3]}")
        return found

    def connection_ids(self) -> set[str] | None:
        return set(self.server.connections)


class PiGcsPtyRig(PiGcsTcpRig):
    """The same controller on a pty (its RS-232 port): gone is the adapter unplugged."""

    def __init__(self, tmp_path: Path) -> None:
        ActuatorRig.__init__(self, tmp_path)
        self.emulator = PiGcsEmulator(axes={axis: EmulatedAxis(servo=True) for axis in self.AXES})
        self.device = PiGcsPtyDevice(tmp_path / "ttyPI", self.emulator)

    def transport(self) -> dict[str, Any]:
        return {"transport": "serial", "port": self.device.port}

    async def start(self) -> None:
        pass

    async def stop(self) -> None:
        self.device.close()

    async def gone(self) -> None:
        self.device.unplug()

    async def back(self) -> None:
        self.emulator.set_servo("1", False)
        if not self.device.link.exists():
            self.device.replug()

    def connection_ids(self) -> set[str] | None:
        return None  # a pty cannot tell


class LabRig(ActuatorRig):
    """A lab's own output box (1 mV steps, 0..10 V), its output a file of JSON lines."""

    kind = "labbox"
    resolution_v = 0.001
    limit_case = ((0.0004, 4.9996), 4.9996, 4.999)
    unrepresentable = ((0.0, 12.0), 11.0)  # the box puts out 0..10 V
    multi_output_unsupported = None
    CHANNELS = (1, 2)

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.folder = tmp_path / "box"
        self.folder.mkdir()
        self.path = self.folder / "out.jsonl"

    def options(self) -> dict[str, Any]:
        return {"kind": "labbox", "path": str(self.path), "channel": 2}

    async def held_v(self) -> float:
        return self.written_v()[-1]

    def lines(self) -> list[dict[str, Any]]:
        return [json.loads(line) for line in self.path.read_text().splitlines()] if self.path.exists() else []

    def written_v(self) -> list[float]:
        return [float(line["voltage_v"]) for line in self.lines()]

    async def refuse_writes(self) -> None:
        shutil.rmtree(self.folder)  # the box's share went away

    gone = refuse_writes

    async def back(self) -> None:
        self.folder.mkdir(exist_ok=True)

    def output_options(self) -> list[dict[str, Any]]:
        return [{**self.options(), "channel": channel} for channel in self.CHANNELS]

    def output_written_v(self, index: int) -> list[float]:
        return [float(line["voltage_v"]) for line in self.lines() if line["channel"] == self.CHANNELS[index]]


RIGS: dict[str, type[ActuatorRig]] = {"simulated": SimulatedRig, "modbus": ModbusRig, "serial_line": SerialRig,
                                      "pi_gcs": PiGcsTcpRig, "labbox": LabRig}


@pytest.fixture(scope="module", autouse=True)
def lab_package(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The lab's package installed for this module (an entry point the registry finds)."""
    with lab_plugin.installed(tmp_path_factory.mktemp("lab")):
        yield


# --- the contract, per rig ------------------------------------------------------------------------


class TestSimulated(ActuatorContract):
    rig = SimulatedRig


class TestModbus(ActuatorContract):
    rig = ModbusRig


class TestSerialLine(ActuatorContract):
    rig = SerialRig


class TestPiGcsTcp(ActuatorContract):
    rig = PiGcsTcpRig


class TestPiGcsPty(ActuatorContract):
    rig = PiGcsPtyRig


class TestLabBox(ActuatorContract):
    rig = LabRig


def test_every_plugin_that_can_move_the_stage_is_run_through_the_contract() -> None:
    """A new actuator plugin in nanodrift's entry points must get a rig and a class here (the lab's is
    installed above)."""
    movers = {kind for kind in available() if load_plugin(kind).actuator_model is not None}
    assert movers == set(RIGS)
    tested = {cls.rig.kind for cls in ActuatorContract.__subclasses__() if cls.__module__ == __name__}
    assert tested == set(RIGS)


def test_the_serial_rig_sees_a_request_sent_before_the_answer_to_the_one_before(tmp_path: Path) -> None:
    """The emulator-side overlap check has teeth: two queries written at once, and a garbled line, are caught."""
    rig = SerialRig(tmp_path)
    try:
        with serial.serial_for_url(rig.controller.port, timeout=2.0) as port:
            port.write(b"SVA? 1\nSVA? 2\n")
            assert port.readline() == b"1=0.0000\n" and port.readline() == b"2=0.0000\n"
            port.write(b"SVA 1 SVA? 2\n")
            port.write(b"ERR?\n")
            assert port.readline().strip().isdigit()  # the error code the garbled line set
        found = rig.overlapping_exchanges()
        assert any("came before the answer to 'SVA? 1'" in problem for problem in found), found
        assert any("not a whole request: 'SVA 1 SVA? 2'" in problem for problem in found), found
    finally:
        rig.controller.close()
