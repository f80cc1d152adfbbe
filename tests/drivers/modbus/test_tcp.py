"""The modbus driver against pymodbus' real TCP server on 127.0.0.1: values, faults, recovery."""

from __future__ import annotations

import asyncio
import time
from collections.abc import Awaitable, Callable

import pytest
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer, device_registers, tcp_context
from pymodbus.constants import ExcCodes

from nanodrift.drivers.base import DeviceError, Reading, SensorGroup, State
from nanodrift.drivers.modbus.config import ModbusSensorConfig
from nanodrift.drivers.modbus.group import ModbusBlockGroup
from nanodrift.drivers.modbus.plugin import PLUGIN

VALUES = {"int16": -1234, "uint16": 54321, "int32": -7654321, "uint32": 3_000_000_000, "float32": 21.375}


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


def thermocouples(n: int = 8, **kw: object) -> list[ModbusSensorConfig]:
    return [ModbusSensorConfig(name=f"T{i + 1}", hub="adam", address=i, input_type="input", scale=0.1,
                               nan_value=-32768, **kw) for i in range(n)]


async def opened(configs: list[ModbusSensorConfig], port: int, **kw: object) -> list[SensorGroup]:
    groups = PLUGIN.create(configs, tcp_context(port, **kw))
    for g in groups:
        await g.open()
    return groups


async def read_all(groups: list[SensorGroup]) -> dict[str, Reading]:
    out: dict[str, Reading] = {}
    for g in groups:
        out.update(await g.read())
    return out


async def until(condition: Callable[[], Awaitable[bool]], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not await condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.05)


def test_every_data_type_and_swap_is_read_and_scaled() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1, holding_ranges=((0, 64),))
        async with ModbusTestServer([device]) as server:
            configs, expected, address = [], {}, 0
            for data_type, value in VALUES.items():
                for swap in ("none", "byte", "word", "word_byte"):
                    if "word" in swap and data_type.endswith("16"):
                        continue
                    name = f"{data_type}_{swap}"
                    configs.append(ModbusSensorConfig(name=name, hub="adam", address=address, data_type=data_type,
                                                      swap=swap, scale=0.5, offset=-3.0, input_type="holding"))
                    await server.set_registers(1, address, device_registers(value, data_type, swap), "holding")
                    expected[name] = value * 0.5 - 3.0
                    address += len(device_registers(value, data_type, swap))
            groups = await opened(configs, server.port)
            assert len(groups) == 1 and groups[0].request_count == 1  # 34 contiguous registers, one request
            readings = await read_all(groups)
            assert {k: r.state for k, r in readings.items()} == dict.fromkeys(expected, State.OK)
            for name, value in expected.items():
                assert readings[name].value == pytest.approx(value, rel=1e-7), name
            assert device.reads == [(3, 0, address)]
            for g in groups:
                await g.close()

    run(body())


def test_eight_thermocouples_one_request_and_burnout_faults_one_channel() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        async with ModbusTestServer([device]) as server:
            raw = [215, 216, 0x8000, 218, 0xFF38, 220, 221, 222]  # 0xFF38 = -200 -> -20.0 degC
            await server.set_registers(1, 0, raw)
            groups = await opened(thermocouples(), server.port)
            readings = await read_all(groups)
            assert device.reads == [(4, 0, 8)]
            assert readings["T3"].state is State.FAULT
            assert readings["T3"].reason == "open thermocouple (raw -32768)"
            ok = {k: round(r.value, 6) for k, r in readings.items() if k != "T3"}
            assert ok == {"T1": 21.5, "T2": 21.6, "T4": 21.8, "T5": -20.0, "T6": 22.0, "T7": 22.1, "T8": 22.2}
            assert all(r.unit == "degC" for r in readings.values())
            await server.set_registers(1, 2, [217])  # thermocouple reconnected
            assert (await read_all(groups))["T3"].value == pytest.approx(21.7)
            for g in groups:
                await g.close()

    run(body())


def test_exception_codes_fault_the_group_naming_the_code() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        async with ModbusTestServer([device]) as server:
            configs = [*thermocouples(), ModbusSensorConfig(name="X", hub="adam", address=100, input_type="input")]
            groups = await opened(configs, server.port)
            readings = await read_all(groups)
            assert readings["X"].state is State.FAULT
            assert readings["X"].reason == (
                "Modbus exception 2 (illegal data address) from device 1 at input register 100")
            assert readings["T1"].state is State.OK
            device.fail_with = ExcCodes.DEVICE_FAILURE
            readings = await read_all(groups)
            for i in range(8):
                assert readings[f"T{i + 1}"].reason == (
                    "Modbus exception 4 (server device failure) from device 1 at input register 0 (count 8)")
            device.fail_with = None
            assert all(r.state is State.OK for k, r in (await read_all(groups)).items() if k != "X")
            for g in groups:
                await g.close()

    run(body())


def test_bridged_gap_refused_by_device_is_split_for_good() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1, input_ranges=((0, 1), (3, 1)))  # registers 1, 2 not mapped
        async with ModbusTestServer([device]) as server:
            await server.set_registers(1, 0, [100])
            await server.set_registers(1, 3, [300])
            configs = [ModbusSensorConfig(name=n, hub="adam", address=a, input_type="input") for n, a in
                       (("A", 0), ("B", 3))]
            [group] = await opened(configs, server.port)
            assert isinstance(group, ModbusBlockGroup) and group.block.count == 4
            readings = await group.read()
            assert {k: r.value for k, r in readings.items()} == {"A": 100.0, "B": 300.0}
            # the bridged read (0..3) was refused before the device saw it; then the two mapped ranges
            assert group.request_count == 2 and device.reads == [(4, 0, 1), (4, 3, 1)]
            await group.read()
            assert device.reads == [(4, 0, 1), (4, 3, 1)] * 2  # split for good: no bridged read again
            await group.close()

    run(body())


def test_requests_on_one_hub_are_serialised() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        in_flight = peak = 0

        async def slow_action(*args: object) -> None:
            nonlocal in_flight, peak
            in_flight += 1
            peak = max(peak, in_flight)
            await asyncio.sleep(0.02)
            in_flight -= 1

        async with ModbusTestServer([device]) as server:
            device._action = slow_action  # type: ignore[method-assign]
            await server.stop()
            await server.start()
            configs = [ModbusSensorConfig(name=f"C{i}", hub="adam", address=10 * i, input_type="input")
                       for i in range(3)]
            groups = await opened(configs, server.port)
            assert len(groups) == 3
            for _ in range(3):
                await asyncio.gather(*(g.read() for g in groups))
            assert peak == 1
            for g in groups:
                await g.close()

    run(body())


def test_silent_device_raises_device_error_within_the_timeout() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)

        async def never_answers(*args: object) -> None:
            await asyncio.sleep(5)

        async with ModbusTestServer([device]) as server:
            device._action = never_answers  # type: ignore[method-assign]
            await server.stop()
            await server.start()
            [group] = await opened(thermocouples(), server.port, timeout_s=0.2)
            start = time.monotonic()
            with pytest.raises(DeviceError, match=r"no response from device 1 input register 0 \(count 8\)"):
                await asyncio.wait_for(group.read(), group.timeout_s)  # as the daemon polls: ours comes first
            assert time.monotonic() - start < 1.5
            assert not group.hub.connected  # a silent TCP peer is a dead socket: reconnect next time
            await group.open()
            with pytest.raises(TimeoutError):  # a caller giving up mid-request drops the socket as well
                await asyncio.wait_for(group.read(), 0.05)
            assert not group.hub.connected
            await group.close()

    run(body())


def test_server_stopped_and_restarted_channels_recover() -> None:
    async def body() -> None:
        device = ModbusTestDevice(1)
        server = ModbusTestServer([device])
        await server.start()
        await server.set_registers(1, 0, [200 + i for i in range(8)])
        [group] = await opened(thermocouples(), server.port)
        assert (await group.read())["T1"].value == pytest.approx(20.0)

        await server.stop()
        with pytest.raises(DeviceError, match=f"modbus hub 'adam'.*127.0.0.1:{server.port}"):
            await group.read()
        start = time.monotonic()
        for _ in range(3):  # while the module is away, each read tries once and fails fast, never hangs
            before = group.hub.connect_attempts
            with pytest.raises(DeviceError, match=f"cannot connect to 127.0.0.1:{server.port}$"):
                await group.read()
            assert group.hub.connect_attempts == before + 1  # the daemon's poller times the retries, not the hub
        assert time.monotonic() - start < 1.0
        with pytest.raises(DeviceError):  # the daemon's reopen fails too while it is away
            await group.close()
            await group.open()

        await server.start()
        await server.set_registers(1, 0, [300 + i for i in range(8)])

        async def recovered() -> bool:
            try:
                return (await group.read())["T8"].value == pytest.approx(30.7)
            except DeviceError:
                return False

        await until(recovered, timeout=5.0, what="channels recover after the server restarts")
        await group.close()
        assert not group.hub.connected
        await server.stop()

    run(body())
