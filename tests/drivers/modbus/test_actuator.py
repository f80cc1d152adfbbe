"""The Modbus analog output actuator against pymodbus' real TCP server on 127.0.0.1 (register content,
exceptions, verify, recovery, counts at the limits, reading the output back) and a raw socket module that
pins the request bytes (FC 6, FC 16, FC 3)."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable

import pytest
from helpers.budget import examples
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer, device_registers, tcp_context
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from pymodbus.constants import ExcCodes

from nanodrift.drivers.base import DeviceError, DriverContext
from nanodrift.drivers.modbus.actuator import ModbusActuator
from nanodrift.drivers.modbus.codec import raw_for
from nanodrift.drivers.modbus.config import ModbusActuatorConfig, ModbusSensorConfig
from nanodrift.drivers.modbus.plugin import PLUGIN


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


def output(context: DriverContext, **kw: object) -> ModbusActuator:
    settings: dict[str, object] = {"hub": "adam", "address": 10, "scale": 0.001}
    settings.update(kw)
    actuator = PLUGIN.create_actuator(ModbusActuatorConfig.model_validate(settings), context)
    assert isinstance(actuator, ModbusActuator)
    return actuator


async def until(condition: Callable[[], Awaitable[bool]], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not await condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.05)


@pytest.mark.parametrize(
    ("data_type", "swap", "scale", "offset", "function_code"),
    [
        ("int16", "none", 0.001, 0.0, 6),
        ("uint16", "byte", 10 / 4095, 0.0, 6),  # a 12-bit 0-10 V output, bytes swapped
        ("int32", "word", 1e-6, -1.0, 16),
        ("float32", "word_byte", 1.0, 0.0, 16),
    ],
)
def test_the_register_holds_the_voltage_after_each_command(data_type: str, swap: str, scale: float, offset: float,
                                                           function_code: int) -> None:
    async def body() -> None:
        device = ModbusTestDevice(1, holding_ranges=((0, 32),))
        async with ModbusTestServer([device]) as server:
            actuator = output(tcp_context(server.port), data_type=data_type, swap=swap, scale=scale, offset=offset)
            await actuator.open()
            count = 1 if function_code == 6 else 2
            for volts in (0.0, 4.999, 9.87654, 0.5):
                await actuator.command(volts / 0.02, volts)
                exact = (volts - offset) / scale
                raw = exact if data_type == "float32" else round(exact)
                # pymodbus' own converter says what the device must hold, not nanodrift.drivers.modbus.codec
                assert await server.get_registers(1, 10, count) == device_registers(raw, data_type, swap), volts
            assert [(fc, address) for fc, address, _ in device.writes] == [(function_code, 10)] * 4
            assert device.reads == [(3, 10, count)] * 4  # verify = true: one read back per write
            await actuator.close()
            assert not actuator.hub.connected  # the last user of the hub closed it

    run(body())


def test_fc6_fc16_and_readback_request_bytes() -> None:
    captured: list[bytes] = []
    holding: dict[int, int] = {}

    async def module(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while header := await reader.readexactly(7):
            pdu = await reader.readexactly(int.from_bytes(header[4:6], "big") - 1)
            captured.append(header + pdu)
            fc, address = pdu[0], int.from_bytes(pdu[1:3], "big")
            if fc == 6:
                holding[address] = int.from_bytes(pdu[3:5], "big")
                answer = pdu  # FC 6 echoes the request
            elif fc == 16:
                count = int.from_bytes(pdu[3:5], "big")
                for k in range(count):
                    holding[address + k] = int.from_bytes(pdu[6 + 2 * k: 8 + 2 * k], "big")
                answer = pdu[:5]
            else:  # FC 3
                count = int.from_bytes(pdu[3:5], "big")
                data = b"".join(holding.get(address + k, 0).to_bytes(2, "big") for k in range(count))
                answer = bytes([3, len(data)]) + data
            writer.write(header[:4] + (1 + len(answer)).to_bytes(2, "big") + header[6:7] + answer)
            await writer.drain()

    async def body() -> None:
        server = await asyncio.start_server(module, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        context = tcp_context(port)
        short = output(context, device_id=3, address=10)
        await short.open()
        await short.command(249.95, 4.999)  # 4999 counts
        await short.close()
        wide = output(context, device_id=3, address=0x1234, data_type="int32", scale=1e-6, verify=False)
        await wide.open()
        await wide.command(0.0, -2.0)  # -2000000 = 0xFFE17B80
        await wide.close()
        server.close()
        # MBAP: transaction id (a new connection starts at 1), protocol 0, length, unit id; then the PDU
        assert captured == [
            bytes.fromhex("0001 0000 0006 03 06 000A 1387"),  # FC 6: register 10 := 4999
            bytes.fromhex("0002 0000 0006 03 03 000A 0001"),  # FC 3: read register 10 back
            bytes.fromhex("0001 0000 000B 03 10 1234 0002 04 FFE1 7B80"),  # FC 16: 2 registers, 4 bytes, big endian
        ]
        assert holding == {10: 4999, 0x1234: 0xFFE1, 0x1235: 0x7B80}

    run(body())


def test_values_that_do_not_fit_the_data_type_are_refused_and_nothing_is_written() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        async with ModbusTestServer([device]) as server:
            actuator = output(tcp_context(server.port), data_type="uint16", scale=10 / 4095)
            await actuator.open()
            with pytest.raises(ValueError, match=r"cannot write -0.5000 V.*outside uint16's range 0..65535"):
                await actuator.command(-25.0, -0.5)
            with pytest.raises(ValueError, match="cannot write nan V"):
                await actuator.command(0.0, float("nan"))
            assert device.writes == []
            await actuator.close()

    run(body())


def test_verify_mismatch_is_a_device_error_naming_what_was_written_and_read() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)

        def clamps(address: int, values: list[int]) -> None:
            values[:] = [min(v, 4095) for v in values]  # a 12-bit output keeps what it can

        async with ModbusTestServer([device]) as server:
            actuator = output(tcp_context(server.port))
            await actuator.open()
            await actuator.command(200.0, 4.0)
            device.on_write = clamps
            with pytest.raises(DeviceError) as caught:
                await actuator.command(250.0, 5.0)
            assert str(caught.value) == (
                f"modbus output (hub 'adam' at 127.0.0.1:{server.port}, device 1, holding register 10): "
                "wrote raw 5000 (5.0000 V), read back raw 4095 (4.0950 V)")
            unverified = output(tcp_context(server.port), verify=False)
            await unverified.open()
            await unverified.command(250.0, 5.0)  # without verify the clamp goes unnoticed
            device.on_write = None
            await actuator.command(250.0, 5.0)  # the device is right again: so is the actuator
            assert await server.get_registers(1, 10, 1) == [5000]
            await actuator.close()
            await unverified.close()

    run(body())


def test_an_exception_answer_is_a_device_error_naming_the_code() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        async with ModbusTestServer([device]) as server:
            actuator = output(tcp_context(server.port))
            await actuator.open()
            device.fail_writes_with = ExcCodes.DEVICE_FAILURE
            with pytest.raises(DeviceError, match=r"writing 5.0000 V \(raw 5000\) failed: Modbus exception 4 "
                                                  r"\(server device failure\) from device 1 at holding register 10"):
                await actuator.command(250.0, 5.0)
            unmapped = output(tcp_context(server.port), address=200)  # outside the device's register map
            await unmapped.open()
            with pytest.raises(DeviceError, match=r"Modbus exception 2 \(illegal data address\)"):
                await unmapped.command(250.0, 5.0)
            await unmapped.close()
            await actuator.close()

    run(body())


def test_the_output_recovers_after_the_device_comes_back() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        server = ModbusTestServer([device])
        await server.start()
        actuator = output(tcp_context(server.port, timeout_s=0.3))
        await actuator.open()
        await actuator.command(100.0, 2.0)

        await server.stop()
        with pytest.raises(DeviceError, match=rf"modbus output \(hub 'adam' at 127.0.0.1:{server.port}.*writing "
                                              r"2.2000 V"):
            await actuator.command(110.0, 2.2)
        start = time.monotonic()
        for _ in range(3):  # while the module is away, commands fail fast (connection refused), never hang
            with pytest.raises(DeviceError):
                await actuator.command(110.0, 2.2)
        assert time.monotonic() - start < 1.0

        await server.start()

        async def written() -> bool:
            try:
                await actuator.command(120.0, 2.4)
            except DeviceError:
                return False
            return True

        await until(written, timeout=5.0, what="commands succeed again after the module is back")
        assert await server.get_registers(1, 10, 1) == [2400]
        await actuator.close()
        await server.stop()

    run(body())


def test_the_output_shares_the_sensors_hub_and_its_lock() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        async with ModbusTestServer([device]) as server:
            await server.set_registers(1, 0, [215, 216], "input")
            device.writes.clear()  # the test's own setting of the registers
            context = tcp_context(server.port)
            [group] = PLUGIN.create([ModbusSensorConfig(name=f"T{i + 1}", hub="adam", address=i, input_type="input",
                                                        scale=0.1) for i in range(2)], context)
            actuator = output(context)
            assert actuator.hub is group.hub  # one connection per hub, one lock
            await group.open()
            await actuator.open()
            volts = [0.001 * k for k in range(40)]

            async def reads() -> None:
                for _ in range(40):
                    assert (await group.read())["T2"].value == pytest.approx(21.6)

            async def writes() -> None:
                for v in volts:
                    await actuator.command(v / 0.02, v)

            await asyncio.gather(reads(), writes())  # interleaved on one socket: every answer matched
            assert await server.get_registers(1, 10, 1) == [39]
            assert (len(device.reads), len(device.writes)) == (40 + 40, 40)  # polls and read-backs; writes
            await group.close()
            assert actuator.hub.connected  # the actuator still uses it
            await actuator.close()
            assert not actuator.hub.connected

    run(body())


# --- a voltage at a limit never becomes a count beyond it; where the output is, read at open ------


TWELVE_BIT = 10 / 4095  # a 0-10 V output module with a 12-bit DAC: volts per count


def test_a_voltage_within_half_a_count_of_a_limit_takes_the_count_inside() -> None:
    # 9.999 V is 4094.59 counts: the nearest, 4095, is 10.000 V, above v_max = 9.999
    assert raw_for(9.999, TWELVE_BIT, 0.0, "uint16") == 4095  # no limits given: the nearest count
    assert raw_for(9.999, TWELVE_BIT, 0.0, "uint16", within=(0.0, 9.999)) == 4094
    assert raw_for(10.0, TWELVE_BIT, 0.0, "uint16", within=(0.0, 10.0)) == 4095  # the top itself is kept
    # the other end: v_min = 0.001 V is 0.41 counts, the nearest (0) is 0 V, below it
    assert raw_for(0.001, TWELVE_BIT, 0.0, "uint16", within=(0.001, 9.999)) == 1
    # a negative scale (an inverting output): inside still means inside in volts
    assert raw_for(-9.999, -TWELVE_BIT, 0.0, "int16", within=(-9.999, 0.0)) == 4094
    # float32: the nearest float32 of 0.1 is 0.100000001; the one below it is taken
    written = raw_for(0.1, 1.0, 0.0, "float32", within=(0.0, 0.1))
    assert written < 0.1 and written == pytest.approx(0.1, rel=1e-7)
    with pytest.raises(ValueError, match=r"no raw value within \[1.0001, 1.0002\]"):
        raw_for(1.00015, TWELVE_BIT, 0.0, "uint16", within=(1.0001, 1.0002))  # narrower than a count


@settings(max_examples=examples(300), deadline=None)
@given(counts=st.sampled_from([255, 1023, 4095, 32767]), full_scale=st.floats(0.5, 20.0),
       offset=st.floats(-10.0, 10.0), low=st.floats(0.0, 1.0), high=st.floats(0.0, 1.0), at=st.floats(0.0, 1.0))
def test_what_is_written_is_inside_the_limits_and_within_a_count_of_the_voltage(
        counts: int, full_scale: float, offset: float, low: float, high: float, at: float) -> None:
    scale = full_scale / counts
    v_min, v_max = offset + min(low, high) * full_scale, offset + max(low, high) * full_scale
    assume(v_max - v_min > 1.01 * scale)  # at least one count inside
    voltage = v_min + at * (v_max - v_min)
    raw = raw_for(voltage, scale, offset, "int32", within=(v_min, v_max))
    written = raw * scale + offset
    assert v_min - 1e-6 * scale <= written <= v_max + 1e-6 * scale
    assert abs(written - voltage) <= scale * (1 + 1e-9)
    nearest = round((voltage - offset) / scale)
    if v_min <= nearest * scale + offset <= v_max:
        assert raw == nearest  # the nearest count is inside: it is the one written


def test_the_output_module_never_gets_a_count_above_v_max() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        async with ModbusTestServer([device]) as server:
            actuator = output(tcp_context(server.port), data_type="uint16", scale=TWELVE_BIT)
            actuator.limits_v = (0.0, 9.999)  # the daemon and the procedures set the operator's limits
            await actuator.open()
            await actuator.command(499.95, 9.999)
            [raw] = await server.get_registers(1, 10, 1)
            assert raw == 4094 and raw * TWELVE_BIT <= 9.999
            await actuator.command(250.0, 5.0)
            assert await server.get_registers(1, 10, 1) == [round(5.0 / TWELVE_BIT)]  # inside: the nearest count
            await actuator.close()

    run(body())


def test_read_back_says_what_the_output_register_holds_when_verify_is_on() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        async with ModbusTestServer([device]) as server:
            await server.set_registers(1, 10, [3210], "holding")  # left there by an earlier run
            device.writes.clear()  # the test's own setting of the register
            actuator = output(tcp_context(server.port), offset=-1.0)
            await actuator.open()
            field, volts = await actuator.read_back()
            assert field == "voltage_v" and volts == pytest.approx(3210 * 0.001 - 1.0)
            assert device.reads == [(3, 10, 1)] and device.writes == []  # read, nothing written
            blind = output(tcp_context(server.port), verify=False)  # the register may not be readable
            await blind.open()
            assert await blind.read_back() is None
            assert device.reads == [(3, 10, 1)]
            device.fail_with = ExcCodes.DEVICE_FAILURE
            with pytest.raises(DeviceError, match=r"holding register 10\): reading the output failed: Modbus "
                                                  r"exception 4"):
                await actuator.read_back()
            await blind.close()
            await actuator.close()

    run(body())
