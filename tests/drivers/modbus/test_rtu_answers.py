"""Modbus RTU answers are checked for the exact register count too (issue 10, reproduction 8, over RTU).

A crafted device on one end of a pty null-modem answers with exact bytes (CRC included), so the test
says what went over the wire: first a correct answer (the framing is right), then one whose byte
count and CRC agree but that carries one register more than requested. Over RTU the byte count
decides where the frame ends, so this is the malformed answer a device can really send.
"""

from __future__ import annotations

import asyncio
import os
import select
import threading
import time

import pytest
from helpers.modbus_helpers import PtyNullModem, crc16_modbus

from nanodrift.drivers.base import DeviceError
from nanodrift.drivers.modbus.config import ModbusHubConfig
from nanodrift.drivers.modbus.hub import ModbusHub


class CraftedRtuDevice:
    """Reads one 8-byte request per answer in ``answers`` (registers to send back), answers it, records it."""

    def __init__(self, port: str, answers: list[list[int]]) -> None:
        self.fd = os.open(port, os.O_RDWR | os.O_NOCTTY)
        self.answers = answers
        self.requests: list[bytes] = []
        self._thread = threading.Thread(target=self._serve, name="crafted-rtu", daemon=True)
        self._thread.start()

    def _read_request(self, deadline: float) -> bytes:
        buffer = b""
        while len(buffer) < 8 and time.monotonic() < deadline:
            ready, _, _ = select.select([self.fd], [], [], 0.1)
            if ready:
                buffer += os.read(self.fd, 8 - len(buffer))
        return buffer

    def _serve(self) -> None:
        for registers in self.answers:
            request = self._read_request(time.monotonic() + 20)
            if len(request) < 8:
                return
            self.requests.append(request)
            body = bytes([request[0], request[1], 2 * len(registers)]) + b"".join(
                r.to_bytes(2, "big") for r in registers)
            os.write(self.fd, body + crc16_modbus(body))

    def close(self) -> None:
        self._thread.join(timeout=5)
        os.close(self.fd)


def test_an_rtu_answer_with_more_registers_than_requested_is_a_device_error() -> None:
    async def body() -> None:
        with PtyNullModem() as modem:
            device = CraftedRtuDevice(modem.b, [[215, 216], [215, 216, 217]])
            hub = ModbusHub(ModbusHubConfig(name="bus", type="serial", port=modem.a, baudrate=115200,
                                            timeout_s=0.5))
            hub.acquire()
            try:
                assert await hub.read_registers("input", 1, 0, 2) == [215, 216]  # the framing is right
                with pytest.raises(DeviceError) as info:
                    await hub.read_registers("input", 1, 0, 2)
            finally:
                hub.release()  # the last user: the port is closed
                device.close()
            request = bytes.fromhex("01 04 0000 0002")  # unit 1, input registers, address 0, count 2
            assert device.requests == [request + crc16_modbus(request)] * 2
        message = str(info.value)
        assert "malformed answer from device 1 input register 0 (count 2)" in message, message
        assert ("2 registers (4 bytes) requested, the answer's byte count says 6 and it carries 6 data bytes "
                "(3 registers)") in message, message
        assert modem.a in message, message

    asyncio.run(asyncio.wait_for(body(), 30))

