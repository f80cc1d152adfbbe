"""The modbus driver over RTU: pymodbus' serial server on one end of a pty null-modem."""

from __future__ import annotations

import asyncio

import pytest
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer, PtyNullModem, device_registers

from nanodrift.drivers.base import DeviceError, DriverContext, State
from nanodrift.drivers.modbus.config import ModbusHubConfig, ModbusSensorConfig
from nanodrift.drivers.modbus.plugin import PLUGIN


def test_rtu_bus_with_two_devices_reads_every_type_and_faults() -> None:
    async def body() -> None:
        with PtyNullModem() as modem:
            one, two = ModbusTestDevice(1), ModbusTestDevice(7)
            server = ModbusTestServer([one, two], serial_port=modem.b)
            await server.start()
            await server.set_registers(1, 0, [215, 0x8000, 217])
            await server.set_registers(7, 4, device_registers(-12.25, "float32", "word_byte"), "holding")
            await server.set_registers(7, 6, device_registers(4_000_000_000, "uint32", "word"), "holding")
            context = DriverContext(hubs={"bus": ModbusHubConfig(name="bus", type="serial", port=modem.a,
                                                           baudrate=115200, timeout_s=0.5)})
            configs = [ModbusSensorConfig(name=f"T{i + 1}", hub="bus", device_id=1, address=i, input_type="input",
                                          scale=0.1, nan_value=-32768) for i in range(3)]
            configs += [
                ModbusSensorConfig(name="F", hub="bus", device_id=7, address=4, data_type="float32",
                                   swap="word_byte"),
                ModbusSensorConfig(name="U", hub="bus", device_id=7, address=6, data_type="uint32", swap="word",
                                   scale=1e-9),
                ModbusSensorConfig(name="missing", hub="bus", device_id=7, address=200, input_type="input"),
            ]
            groups = PLUGIN.create(configs, context)
            assert len(groups) == 3
            assert groups[0].hub is groups[1].hub is groups[2].hub  # one bus, one port
            for g in groups:
                await g.open()
            readings = {}
            for g in groups:
                readings.update(await g.read())
            assert readings["T1"].value == pytest.approx(21.5) and readings["T3"].value == pytest.approx(21.7)
            assert readings["T2"].reason == "open thermocouple (raw -32768)"
            assert readings["F"].value == -12.25
            assert readings["U"].value == pytest.approx(4.0)
            assert readings["missing"].state is State.FAULT
            assert readings["missing"].reason == (
                "Modbus exception 2 (illegal data address) from device 7 at input register 200")
            assert one.reads == [(4, 0, 3)] and two.reads == [(3, 4, 4)]

            await server.stop()  # the bus goes silent: no answer is a DeviceError, the port stays open
            with pytest.raises(DeviceError, match=r"no response from device 1 input register 0 \(count 3\)"):
                await groups[0].read()
            assert groups[0].hub.connected
            await server.start()
            assert (await groups[0].read())["T3"].value == pytest.approx(21.7)  # recovers by itself
            for g in groups:
                await g.close()
            await server.stop()

    asyncio.run(asyncio.wait_for(body(), 30))
