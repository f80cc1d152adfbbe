"""The exact bytes the modbus driver puts on the wire (pymeasure ``expected_protocol`` style):
a raw socket / raw pty plays the module, records the request and answers by hand."""

from __future__ import annotations

import asyncio
import os
import tty

import pytest
from helpers.modbus_helpers import crc16_modbus, tcp_context

from nanodrift.drivers.base import DriverContext
from nanodrift.drivers.modbus.config import ModbusHubConfig, ModbusSensorConfig
from nanodrift.drivers.modbus.plugin import PLUGIN

# 8 thermocouples, raw int16 x0.1 degC; register 5 is an open thermocouple
RAW = [215, 216, 217, 218, 219, 0x8000, 221, 222]
DATA = b"".join(r.to_bytes(2, "big") for r in RAW)


def thermocouples(hub: str) -> list[ModbusSensorConfig]:
    return [ModbusSensorConfig(name=f"T{i + 1}", hub=hub, device_id=1, address=i, input_type="input", scale=0.1,
                               nan_value=-32768) for i in range(8)]


def test_tcp_adu_of_one_read_of_eight_input_registers() -> None:
    captured: list[bytes] = []

    async def module(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        while request := await reader.read(12):
            captured.append(request)
            pdu = bytes([0x04, len(DATA)]) + DATA
            # MBAP: transaction id echoed, protocol 0, length = unit id + PDU, unit id echoed
            writer.write(request[:4] + (1 + len(pdu)).to_bytes(2, "big") + request[6:7] + pdu)
            await writer.drain()
        writer.close()

    async def body() -> None:
        server = await asyncio.start_server(module, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        [group] = PLUGIN.create(thermocouples("adam"), tcp_context(port))
        await group.open()
        first = await group.read()
        await group.read()
        await group.close()
        server.close()
        assert captured == [
            bytes.fromhex("0001 0000 0006 01 04 0000 0008"),  # tid 1, pid 0, len 6, unit 1, fc 4, addr 0, count 8
            bytes.fromhex("0002 0000 0006 01 04 0000 0008"),
        ]
        assert first["T1"].value == pytest.approx(21.5)
        assert first["T6"].reason == "open thermocouple (raw -32768)"

    asyncio.run(asyncio.wait_for(body(), 20))


def test_rtu_frame_with_crc() -> None:
    assert crc16_modbus(bytes.fromhex("01 03 00 00 00 0A")) == bytes.fromhex("C5 CD")  # the textbook vector

    async def body() -> None:
        master, slave = os.openpty()
        tty.setraw(slave)
        loop = asyncio.get_running_loop()
        captured = bytearray()
        answered = asyncio.Event()

        def on_bytes() -> None:
            captured.extend(os.read(master, 256))
            if len(captured) >= 8 and not answered.is_set():
                answered.set()
                body = bytes([0x01, 0x04, len(DATA)]) + DATA
                os.write(master, body + crc16_modbus(body))

        loop.add_reader(master, on_bytes)
        try:
            context = DriverContext(hubs={"bus": ModbusHubConfig(name="bus", type="serial", port=os.ttyname(slave),
                                                           baudrate=19200, timeout_s=0.5)})
            [group] = PLUGIN.create(thermocouples("bus"), context)
            await group.open()
            readings = await group.read()
            await group.close()
        finally:
            loop.remove_reader(master)
            os.close(master)
            os.close(slave)
        assert bytes(captured) == bytes.fromhex("01 04 0000 0008 F1CC")  # unit 1, fc 4, addr 0, count 8, CRC
        assert readings["T8"].value == pytest.approx(22.2)

    asyncio.run(asyncio.wait_for(body(), 20))
