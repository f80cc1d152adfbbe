"""The serial_line actuator against a PI controller emulated on a pty (GCS): the exact lines written,
readback parsing, error answers and silence, a vanished port and its recovery, and a port shared with
a sensor reading the same controller."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import pytest
from helpers.serial_helpers import FakeGcsController

from nanodrift.drivers.base import DeviceError, DriverContext, DriverSetupError, State
from nanodrift.drivers.serial_line.actuator import SerialLineActuator
from nanodrift.drivers.serial_line.config import SerialLineActuatorConfig, SerialLineSensorConfig
from nanodrift.drivers.serial_line.plugin import PLUGIN


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[FakeGcsController]:
    fake = FakeGcsController(tmp_path / "ttyPI")
    yield fake
    fake.close()


def actuator_for(port: str, context: DriverContext | None = None, **kw: object) -> SerialLineActuator:
    settings: dict[str, object] = {"port": port, "readback": "SVA? 1\n", "timeout_s": 0.3}
    settings.update(kw)
    actuator = PLUGIN.create_actuator(SerialLineActuatorConfig.model_validate(settings), context or DriverContext())
    assert isinstance(actuator, SerialLineActuator)
    return actuator


async def until(condition: Callable[[], Awaitable[bool]], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not await condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.05)


def test_exact_lines_written_and_the_readback_checked(controller: FakeGcsController) -> None:
    async def body() -> None:
        actuator = actuator_for(controller.port, error_query="ERR?\n")
        await actuator.open()
        await actuator.command(249.95, 4.999)
        assert controller.voltage == pytest.approx(4.999)
        await actuator.command(-12.5, -0.25)
        await actuator.close()
        assert bytes(controller.received) == (b"SVA 1 4.9990\nSVA? 1\nERR?\n"
                                              b"SVA 1 -0.2500\nSVA? 1\nERR?\n")
        assert controller.voltage == pytest.approx(-0.25)

    run(body())


def test_a_closed_loop_template_and_its_readback_field(controller: FakeGcsController) -> None:
    async def body() -> None:
        # MOV-style: the controller gets the position; the fake's SVA stands in for MOV (1 um per "volt") and
        # POS? answers it: the readback is compared with the field the command wrote (q_um)
        controller.position_per_volt = 1.0
        actuator = actuator_for(controller.port, command="SVA 1 {q_um:.4f}\n", readback="POS? 1\n",
                                readback_tolerance=0.0005)
        assert actuator.config.expected_field == "q_um"
        await actuator.open()
        await actuator.command(240.1234, 4.8, x_um=240.0)
        await actuator.close()
        targets = actuator_for(controller.port, command="MOV A {x_um:.1f} Q {q_um:.2f} V {voltage_v:.3f}\n",
                               readback="")
        await targets.open()
        await targets.command(240.1234, 4.8, x_um=240.0)
        await targets.command(30.0, 0.6)  # no target known: x_um is the command itself

        async def all_arrived() -> bool:  # nothing answers a write-only command: wait for the controller
            return len(controller.lines) >= 4

        await until(all_arrived, timeout=5.0, what="the controller has read both MOV lines")
        await targets.close()
        assert controller.lines == ["SVA 1 240.1234", "POS? 1", "MOV A 240.0 Q 240.12 V 4.800",
                                    "MOV A 30.0 Q 30.00 V 0.600"]

    run(body())


def test_a_stage_that_does_not_take_the_voltage_is_a_fault_naming_both(controller: FakeGcsController) -> None:
    async def body() -> None:
        # the fault here is the read-back, not a timeout: 2 s to write a line (0.3 s failed a loaded run)
        actuator = actuator_for(controller.port, timeout_s=2.0)
        await actuator.open()
        await actuator.command(100.0, 2.0)
        controller.amplifier_off = True
        with pytest.raises(DeviceError) as caught:
            await actuator.command(250.0, 5.0)
        assert str(caught.value) == (
            f"controller on {controller.port}: wrote 'SVA 1 5.0000\\n' (voltage_v 5), read back 2 "
            "(answer '1=2.0000'; tolerance 0.001)")
        controller.amplifier_off = False
        await actuator.command(250.0, 5.0)  # the controller is right again: so is the actuator
        await actuator.close()

    run(body())


def test_error_answers_and_error_codes_are_faults(controller: FakeGcsController) -> None:
    async def body() -> None:
        actuator = actuator_for(controller.port, error_query="ERR?\n")
        await actuator.open()
        controller.answer = b"ERROR: axis disabled"
        with pytest.raises(DeviceError, match=r"unexpected answer 'ERROR: axis disabled' to 'SVA\? 1\\n' after "
                                              r"'SVA 1 5.0000\\n' \(expected pattern"):
            await actuator.command(250.0, 5.0)
        controller.answer = None
        # a command the controller refuses: GCS sets an error code and says nothing until ERR? asks
        bad_axis = actuator_for(controller.port, context=None, command="SVA 2 {voltage_v:.4f}\n", readback="",
                                error_query="ERR?\n")
        await actuator.close()
        await bad_axis.open()
        with pytest.raises(DeviceError, match=r"the controller reports error '15' after 'SVA 2 5.0000\\n'"):
            await bad_axis.command(250.0, 5.0)
        await bad_axis.close()
        assert controller.error == 0  # ERR? read and cleared it

    run(body())


def test_silence_is_a_fault_within_the_timeout_and_recovery_follows(controller: FakeGcsController) -> None:
    async def body() -> None:
        actuator = actuator_for(controller.port)
        await actuator.open()
        controller.silent = True
        start = time.monotonic()
        with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n' within 0.3 s after 'SVA 1 5.0000\\n'"):
            await actuator.command(250.0, 5.0)
        assert time.monotonic() - start < 1.0
        controller.silent = False
        await actuator.command(250.0, 5.0)
        await actuator.close()

    run(body())


def test_a_vanished_port_is_a_fault_and_the_actuator_recovers_when_it_is_back(controller: FakeGcsController) -> None:
    async def body() -> None:
        actuator = actuator_for(controller.port)
        await actuator.open()
        await actuator.command(100.0, 2.0)
        controller.unplug()
        with pytest.raises(DeviceError, match=controller.port):
            for _ in range(20):  # the reader thread notices EIO within its read timeout
                await actuator.command(110.0, 2.2)
                await asyncio.sleep(0.05)
        controller.replug()

        async def written() -> bool:
            try:
                await actuator.command(120.0, 2.4)
            except DeviceError:
                return False
            return True

        await until(written, timeout=15.0, what="commands succeed again once the controller is back")
        assert controller.voltage == pytest.approx(2.4)
        await actuator.close()

    run(body())


def test_a_sensor_and_the_actuator_share_the_controllers_port(controller: FakeGcsController) -> None:
    async def body() -> None:
        context = DriverContext()
        sensor = SerialLineSensorConfig(name="stage", role="position", port=controller.port, baudrate=115200,
                                        query="POS? 1\n", pattern=r"1=(?P<value>[-+0-9.]+)", timeout_s=0.5)
        [group] = PLUGIN.create([sensor], context)
        actuator = actuator_for(controller.port, context=context, timeout_s=0.5)
        assert actuator.port is group and not actuator.owns_port
        await group.open()
        await actuator.open()
        volts = [0.25 * k for k in range(1, 21)]
        seen: list[float] = []

        async def reads() -> None:
            for _ in range(20):
                reading = (await group.read())["stage"]
                assert reading.state is State.OK, reading.reason
                seen.append(reading.value)

        async def commands() -> None:
            for v in volts:
                await actuator.command(v / 0.02, v)

        await asyncio.gather(reads(), commands())  # one port, one lock: every answer went to its asker
        # a position is 100 x a voltage: a readback line taken for a position would show up here
        assert all(value == 0.0 or value / 100.0 in [pytest.approx(v) for v in volts] for value in seen)
        await actuator.close()  # a shared port stays open for its sensor
        assert (await group.read())["stage"].value == pytest.approx(500.0)
        await group.close()

    run(body())


def test_a_port_shared_with_a_sensor_must_agree_on_its_settings(tmp_path: Path) -> None:
    context = DriverContext()
    port = str(tmp_path / "ttyX")
    PLUGIN.create([SerialLineSensorConfig(name="stage", role="position", port=port, baudrate=9600, query="POS?\n")],
                  context)
    with pytest.raises(DriverSetupError, match=r"read by sensor 'stage' with baudrate = 9600, the actuator says 11520"):
        actuator_for(port, context=context)
    streaming = DriverContext()
    PLUGIN.create([SerialLineSensorConfig(name="stage", role="position", port=port, baudrate=115200)], streaming)
    with pytest.raises(DriverSetupError, match="streams lines"):
        actuator_for(port, context=streaming)
    assert actuator_for(port, context=streaming, readback="").port.config.name == "stage"  # write-only is fine


def test_read_back_asks_the_controller_where_the_output_is(controller: FakeGcsController) -> None:
    async def read(**kw: object) -> object:
        actuator = actuator_for(controller.port, **kw)
        await actuator.open()
        try:
            return await actuator.read_back()
        finally:
            await actuator.close()

    async def body() -> None:
        controller.voltage = 3.25  # left there by an earlier run
        assert await read() == ("voltage_v", 3.25)
        assert controller.lines == ["SVA? 1"]  # asked, nothing written
        assert await read(command="MOV 1 {q_um:.4f}\n", readback="POS? 1\n") == ("q_um", pytest.approx(325.0))
        assert await read(readback="") is None  # nothing to ask: the controller cannot say
        # a readback of the target is not where the command put the stage
        assert await read(command="MOV 1 {x_um:.4f}\n", readback="POS? 1\n") is None
        assert controller.lines == ["SVA? 1", "POS? 1"]
        controller.silent = True
        with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n' within 0.3 s after 'opening the port'"):
            await read()

    run(body())
