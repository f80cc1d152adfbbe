"""The actuator contract (``nanodrift.drivers.base.Actuator``), one set of checks run against every plugin that can
move the stage, in the style of python-can's ``test/back2back_test.py``:

- ``simulated``: the simulated cell's closed loop (it takes ``q_um``);
- ``modbus``: an analog output (holding register 10, int16, 1 mV per count, ``verify``) on pymodbus'
  TCP server on 127.0.0.1 (``nanodrift.drivers.testing``);
- ``serial_line``: a PI controller speaking GCS on a pty (``SVA 1 {voltage_v:.4f}``, ``SVA? 1``
  read back, ``ERR?``; ``nanodrift.drivers.testing``);
- ``labbox``: a lab's own output (``tests/helpers/lab_plugin.py``), found through a real entry point.

Every assertion on what was written looks at the emulator's side (the register, the lines the
controller received, the box's file, the cell's setpoint), never at the actuator's own account.

The contract: ``open``/``command``/``close`` (close safe twice and after a failed open; open again
retries); ``sent_voltage(v)`` is what the device then holds (within float tolerance), no farther from
``v`` than the device's resolution; with ``limits_v`` set, nothing outside them reaches the device (a
voltage at a limit that the device's rounding would put outside is written as the value on the
inside); ``ValueError`` and nothing written for a value the device cannot represent;
:class:`DeviceError` (no other exception) for a write the device refuses and for a device that is
gone, and the actuator works again once the device does; ``read_back`` after a command returns what
was sent, or None for a device that cannot say.
"""

from __future__ import annotations

import asyncio
import json
import re
import shutil
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers import lab_plugin
from pymodbus.constants import ExcCodes

from nanodrift.drivers.base import Actuator, DeviceError, DriverContext
from nanodrift.drivers.modbus.codec import decode
from nanodrift.drivers.registry import available, load_plugin
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.plugin import RESOURCE_KEY
from nanodrift.drivers.testing import FakeGcsController, ModbusTestDevice, ModbusTestServer, tcp_context

T = 30.0  # a whole test's wall-clock bound
GAIN = 0.02  # volts per um: every command here passes q_um = voltage_v / GAIN
LIMITS = (0.0, 10.0)


def run(body: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(body(), T))


# --- the backends ---------------------------------------------------------------------------------


class Rig:
    kind: str
    #: the finest step of the device's voltage (0: takes the float as it is)
    resolution_v = 0.0
    #: what ``read_back`` answers after a command: "voltage_v", "q_um" or None (cannot say)
    reads_back: str | None = "voltage_v"
    #: (limits_v, a voltage at a limit, what the device must then hold): the rounding goes inward
    limit_case: tuple[tuple[float, float], float, float]
    #: (limits_v, a voltage the device cannot represent), or None: it takes any finite value
    unrepresentable: tuple[tuple[float, float], float] | None = None
    #: whether the device can refuse a write, fail to open or vanish (a simulated cell cannot)
    can_fail = True

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path

    def options(self) -> dict[str, Any]:
        raise NotImplementedError

    def context(self) -> DriverContext:
        return DriverContext()

    def actuator(self) -> Actuator:
        self.built_context = self.context()
        plugin = load_plugin(self.kind)  # through the entry point, as the daemon finds it
        assert plugin.actuator_model is not None, f"{self.kind} cannot move the stage"
        return plugin.create_actuator(plugin.actuator_model.model_validate(self.options()), self.built_context)

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    async def held_v(self) -> float:
        """The voltage the device holds now (its side)."""
        raise NotImplementedError

    def written_v(self) -> list[float]:
        """Every voltage the device was sent, in order (its side)."""
        raise NotImplementedError

    async def refuse_writes(self) -> None:
        """The device still answers, but the next writes do not take."""
        raise NotImplementedError

    async def gone(self) -> None:
        raise NotImplementedError

    async def back(self) -> None:
        """Working again after ``refuse_writes`` or ``gone``."""
        raise NotImplementedError


class SimulatedRig(Rig):
    kind = "simulated"
    reads_back = "q_um"
    limit_case = ((0.0, 5.0), 5.0, 5.0)
    can_fail = False

    def options(self) -> dict[str, Any]:
        return {"kind": "simulated"}

    def actuator(self) -> Actuator:
        actuator = super().actuator()
        cell = self.built_context.resources.get(RESOURCE_KEY, SimulatedCell)
        assert cell is not None
        self.cell = cell
        self.setpoints: list[float] = []
        command = self.cell.command

        def recorded(q_um: float) -> None:  # the cell's side: what its closed loop was given
            self.setpoints.append(q_um)
            command(q_um)

        self.cell.command = recorded  # type: ignore[method-assign]
        return actuator

    async def held_v(self) -> float:
        return self.cell.state.q * GAIN

    def written_v(self) -> list[float]:
        return [q * GAIN for q in self.setpoints]


class ModbusRig(Rig):
    kind = "modbus"
    resolution_v = 0.001
    limit_case = ((0.0004, 4.9996), 4.9996, 4.999)  # the nearest count, 5.000 V, is outside
    unrepresentable = ((0.0, 50.0), 40.0)  # 40000 counts: beyond int16

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.device = ModbusTestDevice(1, holding_ranges=((0, 32),))
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
        return [float(decode(values, "int16")) * 0.001 for _, address, values in self.device.writes if address == 10]

    async def refuse_writes(self) -> None:
        self.device.fail_writes_with = ExcCodes.DEVICE_FAILURE

    async def gone(self) -> None:
        await self.server.stop()

    async def back(self) -> None:
        self.device.fail_writes_with = None
        if self.server._server is None:
            await self.server.start()


class SerialRig(Rig):
    kind = "serial_line"
    resolution_v = 0.0001
    limit_case = ((0.0, 4.99996), 4.99996, 4.9999)  # ".4f" writes 5.0000: outside
    unrepresentable = ((1.00001, 1.00004), 1.00002)  # ".4f" writes 1.0000 or 1.0001: both outside

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.controller = FakeGcsController(tmp_path / "ttyPI")

    def options(self) -> dict[str, Any]:
        return {"kind": "serial_line", "port": self.controller.port, "command": "SVA 1 {voltage_v:.4f}\n",
                "readback": "SVA? 1\n", "error_query": "ERR?\n", "timeout_s": 2.0}

    async def stop(self) -> None:
        self.controller.close()

    async def held_v(self) -> float:
        return self.controller.voltage

    def written_v(self) -> list[float]:
        return [float(m.group(1)) for line in list(self.controller.lines)
                if (m := re.fullmatch(r"SVA 1 (\S+)", line))]

    async def refuse_writes(self) -> None:
        self.controller.amplifier_off = True  # SVA accepted, the voltage does not change

    async def gone(self) -> None:
        self.controller.unplug()

    async def back(self) -> None:
        self.controller.amplifier_off = False
        if not self.controller.link.exists():
            self.controller.replug()


class LabRig(Rig):
    """A lab's own output box (1 mV steps, 0..10 V), its output a file of JSON lines."""

    kind = "labbox"
    resolution_v = 0.001
    limit_case = ((0.0004, 4.9996), 4.9996, 4.999)
    unrepresentable = ((0.0, 12.0), 11.0)  # the box puts out 0..10 V

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.folder = tmp_path / "box"
        self.folder.mkdir()
        self.path = self.folder / "out.jsonl"

    def options(self) -> dict[str, Any]:
        return {"kind": "labbox", "path": str(self.path), "channel": 2}

    async def held_v(self) -> float:
        return self.written_v()[-1]

    def written_v(self) -> list[float]:
        if not self.path.exists():
            return []
        return [float(json.loads(line)["voltage_v"]) for line in self.path.read_text().splitlines()]

    async def refuse_writes(self) -> None:
        shutil.rmtree(self.folder)  # the box's share went away

    gone = refuse_writes

    async def back(self) -> None:
        self.folder.mkdir(exist_ok=True)


RIGS: dict[str, type[Rig]] = {"simulated": SimulatedRig, "modbus": ModbusRig, "serial_line": SerialRig,
                              "labbox": LabRig}


@pytest.fixture(scope="module", autouse=True)
def lab_package(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    with lab_plugin.installed(tmp_path_factory.mktemp("lab")):
        yield


@pytest.fixture(params=list(RIGS))
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Rig:
    return RIGS[request.param](tmp_path)


@pytest.fixture(params=[name for name, rig in RIGS.items() if rig.can_fail])
def failing_rig(request: pytest.FixtureRequest, tmp_path: Path) -> Rig:
    return RIGS[request.param](tmp_path)


@pytest.fixture(params=[name for name, rig in RIGS.items() if rig.unrepresentable is not None])
def bounded_rig(request: pytest.FixtureRequest, tmp_path: Path) -> Rig:
    return RIGS[request.param](tmp_path)


async def command(actuator: Actuator, voltage_v: float) -> None:
    await asyncio.wait_for(actuator.command(voltage_v / GAIN, voltage_v, x_um=voltage_v / GAIN), 10.0)


async def assert_serves(rig: Rig, actuator: Actuator, voltage_v: float) -> None:
    """``voltage_v`` commanded: the device holds ``sent_voltage(voltage_v)``."""
    sent = actuator.sent_voltage(voltage_v)
    await command(actuator, voltage_v)
    assert await rig.held_v() == pytest.approx(sent, abs=1e-9), voltage_v
    assert rig.written_v()[-1] == pytest.approx(sent, abs=1e-9), voltage_v


class TestActuatorContract:
    def test_the_device_holds_sent_voltage_after_each_command(self, rig: Rig) -> None:
        async def body() -> None:
            await rig.start()
            try:
                actuator = rig.actuator()
                assert actuator.description  # names the device in messages
                actuator.limits_v = LIMITS
                await actuator.open()
                asked = [0.1234567, 2.5, 7.7777777, 0.0, 9.99999]
                for volts in asked:
                    sent = actuator.sent_voltage(volts)
                    assert abs(sent - volts) <= rig.resolution_v / 2 + 1e-9, (volts, sent)
                    await assert_serves(rig, actuator, volts)
                assert rig.written_v() == pytest.approx([actuator.sent_voltage(v) for v in asked], abs=1e-9)
                await actuator.close()
                await actuator.close()  # safe twice
            finally:
                await rig.stop()

        run(body)

    def test_read_back_after_a_command_is_what_was_sent(self, rig: Rig) -> None:
        async def body() -> None:
            await rig.start()
            try:
                actuator = rig.actuator()
                actuator.limits_v = LIMITS
                await actuator.open()
                for volts in (3.3333333, 6.25):
                    await command(actuator, volts)
                    back = await asyncio.wait_for(actuator.read_back(), 10.0)
                    if rig.reads_back is None:
                        assert back is None
                    elif rig.reads_back == "voltage_v":
                        assert back == ("voltage_v", pytest.approx(actuator.sent_voltage(volts), abs=1e-9))
                    else:
                        assert back == ("q_um", pytest.approx(volts / GAIN, abs=1e-9))
                await actuator.close()
            finally:
                await rig.stop()

        run(body)

    def test_nothing_outside_limits_v_reaches_the_device(self, rig: Rig) -> None:
        (low, high), at_limit, expected = rig.limit_case

        async def body() -> None:
            await rig.start()
            try:
                actuator = rig.actuator()
                actuator.limits_v = (low, high)
                await actuator.open()
                assert actuator.sent_voltage(at_limit) == pytest.approx(expected, abs=1e-9)
                await assert_serves(rig, actuator, at_limit)
                await assert_serves(rig, actuator, low)
                written = rig.written_v()
                assert len(written) == 2 and all(low <= v <= high for v in written), written
                assert written[0] == pytest.approx(expected, abs=1e-9)
                await actuator.close()
            finally:
                await rig.stop()

        run(body)

    def test_a_value_the_device_cannot_represent_is_a_value_error_and_nothing_is_written(
            self, bounded_rig: Rig) -> None:
        rig = bounded_rig
        assert rig.unrepresentable is not None
        limits, volts = rig.unrepresentable

        async def body() -> None:
            await rig.start()
            try:
                actuator = rig.actuator()
                actuator.limits_v = LIMITS
                await actuator.open()
                await assert_serves(rig, actuator, 1.5)
                held = await rig.held_v()
                before = rig.written_v()
                actuator.limits_v = limits  # the device cannot put out every voltage of these
                with pytest.raises(ValueError):
                    await command(actuator, volts)
                await asyncio.sleep(0.2)  # a write under way would land by now
                assert rig.written_v() == before
                assert await rig.held_v() == held
                actuator.limits_v = LIMITS
                await assert_serves(rig, actuator, 2.5)  # the actuator still works
                await actuator.close()
            finally:
                await rig.stop()

        run(body)

    def test_a_write_the_device_refuses_is_a_device_error_and_the_next_one_works(self, failing_rig: Rig) -> None:
        rig = failing_rig

        async def body() -> None:
            await rig.start()
            try:
                actuator = rig.actuator()
                actuator.limits_v = LIMITS
                await actuator.open()
                await assert_serves(rig, actuator, 1.5)
                await rig.refuse_writes()
                with pytest.raises(DeviceError):
                    await command(actuator, 4.5)
                await rig.back()
                await assert_serves(rig, actuator, 4.5)
                await actuator.close()
            finally:
                await rig.stop()

        run(body)

    def test_a_device_that_is_gone_is_a_device_error_and_a_reopen_recovers(self, failing_rig: Rig) -> None:
        rig = failing_rig

        async def body() -> None:
            await rig.start()
            try:
                actuator = rig.actuator()
                actuator.limits_v = LIMITS
                await actuator.open()
                await assert_serves(rig, actuator, 1.5)
                await rig.gone()
                with pytest.raises(DeviceError):
                    await command(actuator, 4.5)
                await actuator.close()
                await rig.back()
                await actuator.open()
                await assert_serves(rig, actuator, 4.5)
                await actuator.close()
            finally:
                await rig.stop()

        run(body)

    def test_close_is_safe_after_a_failed_open_and_open_retries(self, failing_rig: Rig) -> None:
        rig = failing_rig

        async def body() -> None:
            await rig.start()
            try:
                actuator = rig.actuator()
                actuator.limits_v = LIMITS
                await rig.gone()
                with pytest.raises(DeviceError):
                    await asyncio.wait_for(actuator.open(), 10.0)
                await actuator.close()
                await actuator.close()
                await rig.back()
                await asyncio.wait_for(actuator.open(), 10.0)  # calling it again after a failure retries
                await assert_serves(rig, actuator, 3.0)
                await actuator.close()
            finally:
                await rig.stop()

        run(body)


def test_every_plugin_that_can_move_the_stage_is_run_through_the_contract() -> None:
    """A new actuator plugin in nanodrift's entry points must get a rig here (the lab's is installed above)."""
    movers = {kind for kind in available() if load_plugin(kind).actuator_model is not None}
    assert movers == set(RIGS)
