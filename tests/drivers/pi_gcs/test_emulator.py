"""The GCS emulator itself (``nanodrift.drivers.testing.pi_gcs_emulator``), spoken to raw over TCP on 127.0.0.1 and
a pty: it enforces what PI documents (the servo state for SVA and MOV, the travel and voltage ranges, ERR? returning
and clearing the last error, the error codes of PIPython's gcserror.py), so a plugin tested against it meets the
controller's behaviour, not a permissive stand-in."""

from __future__ import annotations

import asyncio
from pathlib import Path

import serial

from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice, PiGcsTcpServer

#: (request, what ERR? then says): each exchange from a fresh register
CONVERSATION = [
    ("SVA 1 10", "79"),      # servo on: open-loop commands are not allowed
    ("SVO 1 0", "0"),
    ("SVA 1 200", "302"),    # above VMA? (130 V)
    ("SVA 1 10", "0"),
    ("MOV 1 100", "5"),      # servo off: move attempted with servo off
    ("SVO 1 1", "0"),
    ("MOV 1 600", "7"),      # beyond TMX? (500 um)
    ("MOV 1 100", "0"),
    ("MOV 9 100", "15"),     # no axis 9
    ("SVA 1 abc", "1"),      # not a number
    ("FOO 1", "2"),          # unknown command
]


def test_the_emulator_refuses_as_a_pi_controller_does_over_tcp() -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(servo=True)})

    async def body() -> None:
        server = PiGcsTcpServer(emulator)
        await server.start()
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        for request, error in CONVERSATION:
            writer.write(f"{request}\nERR?\n".encode())
            assert (await reader.readline()).decode().strip() == error, request
        writer.write(b"ERR?\nMOV? 1\nSVA? 1\n")  # read once, the error is cleared
        assert [(await reader.readline()).decode() for _ in range(3)] == ["0\n", "1=100.000000\n", "1=10.000000\n"]
        writer.close()
        await server.stop()

    asyncio.run(asyncio.wait_for(body(), 10))
    assert emulator.applied_sva == [("1", 10.0)] and emulator.applied_mov == [("1", 100.0)]


def test_the_emulator_on_a_pty_answers_multi_line_queries_and_logs_every_line(tmp_path: Path) -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(), "2": EmulatedAxis(drift_compensation=True)})
    device = PiGcsPtyDevice(tmp_path / "ttyPI", emulator)
    try:
        with serial.serial_for_url(device.port, timeout=2.0) as port:
            port.write(b"DCO?\n*IDN?\n")
            assert port.readline() == b"1=0 \n" and port.readline() == b"2=1\n"
            assert b"Physik Instrumente" in port.readline()
    finally:
        device.close()
    assert emulator.received() == ["DCO?", "*IDN?"]


def test_the_stage_hooks_hear_only_the_sva_and_mov_that_take_effect() -> None:
    """``on_sva``/``on_mov`` are what moves a simulated stage: a refused command must never reach it."""
    heard: list[tuple[str, str, float]] = []
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(servo=True), "2": EmulatedAxis(servo=False)},
                             on_sva=lambda axis, volts: heard.append(("SVA", axis, volts)),
                             on_mov=lambda axis, um: heard.append(("MOV", axis, um)))
    for line in ["SVA 1 5", "MOV 2 100", "MOV 1 600", "MOV 1 120.5", "SVA 2 200", "SVA 2 7.25"]:
        emulator.handle(line)
    # SVA 1 (servo on), MOV 2 (servo off), MOV 1 600 (beyond TMX?) and SVA 2 200 (beyond VMA?) are refused
    assert heard == [("MOV", "1", 120.5), ("SVA", "2", 7.25)]
