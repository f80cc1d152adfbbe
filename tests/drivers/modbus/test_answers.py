"""Modbus answers are checked: exactly the registers asked for, with a byte count that agrees.

A raw TCP peer on 127.0.0.1 answers with pinned bytes, so each test says exactly what went over the
wire. Before the hub checked answers, more registers than requested (or a byte count smaller than the
data) were taken as an ok reading.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable

import pytest
from helpers.modbus_helpers import tcp_context
from helpers.modbus_peer import CraftedModbusPeer, Request, Responder, byte_count_says, correct, mbap, too_many

from nanodrift.drivers.base import DeviceError, State
from nanodrift.drivers.modbus.config import ModbusSensorConfig
from nanodrift.drivers.modbus.hub import ModbusHub
from nanodrift.drivers.modbus.plugin import PLUGIN


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


def pinned(answer_after_tid: bytes) -> Responder:
    """This exact answer, with the request's transaction id in front."""
    return lambda r: r.tid.to_bytes(2, "big") + answer_after_tid


# read 2 input registers from address 0 of device 1: pymodbus' request after its transaction id
REQUEST_AFTER_TID = bytes.fromhex("0000 0006 01 04 0000 0002")
ANSWERS = {
    # 3 registers (byte count 6, MBAP length 9) for 2 requested
    "too many registers": (bytes.fromhex("0000 0009 01 04 06 00d7 00dc 00e1"),
                           "byte count says 6 and it carries 6 data bytes (3 registers)"),
    # byte count 4 (2 registers) but 6 data bytes in the frame
    "byte count smaller than the data": (bytes.fromhex("0000 0009 01 04 04 00d7 00dc 00e1"),
                                         "byte count says 4 and it carries 6 data bytes (3 registers)"),
    # byte count 6 but only 4 data bytes in the frame
    "byte count larger than the data": (bytes.fromhex("0000 0007 01 04 06 00d7 00dc"),
                                        "byte count says 6 and it carries 4 data bytes (2 registers)"),
    # 1 register for 2 requested
    "too few registers": (bytes.fromhex("0000 0005 01 04 02 00d7"),
                          "byte count says 2 and it carries 2 data bytes (1 registers)"),
}


@pytest.mark.parametrize("case", list(ANSWERS))
def test_a_malformed_answer_is_a_device_error_naming_device_address_and_counts(case: str) -> None:
    answer, counts = ANSWERS[case]

    async def body() -> None:
        with CraftedModbusPeer([pinned(answer)]) as peer:
            hub = ModbusHub(tcp_context(peer.port, timeout_s=0.5).hubs["adam"])
            hub.acquire()
            try:
                with pytest.raises(DeviceError) as info:
                    await hub.read_registers("input", 1, 0, 2)
            finally:
                hub.release()
            [request] = peer.requests
            assert request.raw[2:] == REQUEST_AFTER_TID
        message = str(info.value)
        assert "device 1 input register 0 (count 2)" in message, message
        assert f"2 registers (4 bytes) requested, the answer's {counts}" in message, message
        assert f"127.0.0.1:{peer.port}" in message

    run(body())


def test_a_well_formed_answer_still_reads_and_a_bad_one_never_gives_ok_readings() -> None:
    async def body() -> None:
        configs = [ModbusSensorConfig(name=f"T{i + 1}", hub="adam", address=i, input_type="input", scale=0.1)
                   for i in range(2)]
        with CraftedModbusPeer([correct([215, 216]), too_many(), byte_count_says(2)]) as peer:
            [group] = PLUGIN.create(configs, tcp_context(peer.port, timeout_s=0.5))
            await group.open()
            try:
                readings = await group.read()
                assert {k: (r.state, round(r.value, 6)) for k, r in readings.items()} == {
                    "T1": (State.OK, 21.5), "T2": (State.OK, 21.6)}
                for _ in range(2):  # too many registers, then a byte count of 2 for 4 data bytes
                    with pytest.raises(DeviceError, match="malformed answer from device 1 input register 0"):
                        await group.read()
            finally:
                await group.close()
            assert [r.count for r in peer.requests] == [2, 2, 2]

    run(body())


def test_the_pinned_helpers_build_the_frames_the_spec_gives() -> None:
    """The peer's own framing, checked against the Modbus spec's worked example (FC 4, 1 register)."""
    request = Request(tid=1, protocol=0, unit=1, function=4, address=8, count=1, raw=b"")
    assert mbap(1, 1, bytes.fromhex("04 02 000a")) == bytes.fromhex("0001 0000 0005 01 04 02 000a")
    assert correct([10])(request) == bytes.fromhex("0001 0000 0005 01 04 02 000a")
