"""From a command to the device holding the new value: the actuator against one bare write, same run.

- ``modbus``: a pymodbus TCP server on 127.0.0.1 in its own process stamps each write of the output
  register as it lands. The actuator (``drivers.modbus``: the shared hub, ``raw_for``/``encode``,
  FC 6; ``verify = true`` then reads it back) against one ``write_register`` of a bare
  ``AsyncModbusTcpClient``, alternately.
- ``serial_line``: a GCS controller on a pty in its own process stamps each ``SVA`` line as it is
  complete. The actuator (template, then ``SVA? 1`` readback and ``ERR?``, as config/lab.toml) against
  one bare pyserial ``write`` of the same bytes, alternately.

"holds" is the time from the call to the device's stamp (both processes read CLOCK_MONOTONIC through
``time.perf_counter``); "returns" is when the actuator's ``command`` returns (after its checks).

    .venv/bin/python benchmarks/actuation.py [--commands 1000]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import socket
import statistics
import sys
import tempfile
import threading
import time
from multiprocessing.synchronize import Event
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
ADDRESS = 10


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


# -- the devices, each in its own process ---------------------------------------------------------


def modbus_device(port: int, ready: Event, landed: multiprocessing.Queue) -> None:
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    async def action(function_code: int, _start: int, address: int, _count: int, _registers: list[int],
                     values: list[int] | None) -> None:
        if values is not None and address == ADDRESS:
            landed.put((int(values[0]), time.perf_counter()))

    async def main() -> None:
        bits = [SimData(address=0, count=16, values=False, datatype=DataType.BITS)]
        registers = [SimData(address=0, count=32, values=0, datatype=DataType.REGISTERS)]
        device = SimDevice(id=1, simdata=(list(bits), list(bits), list(registers), list(registers)), action=action)
        server = ModbusTcpServer([device], address=("127.0.0.1", port))
        await server.serve_forever(background=True)
        ready.set()
        await asyncio.Event().wait()

    asyncio.run(main())


def gcs_controller(link: str, ready: Event, landed: multiprocessing.Queue) -> None:
    sys.path.insert(0, str(REPO / "tests"))
    from helpers.serial_helpers import FakeGcsController

    controller = FakeGcsController(Path(link))
    controller.on_voltage = lambda volts: landed.put((round(volts * 1e4), time.perf_counter()))
    ready.set()
    threading.Event().wait()  # serve until terminated


def start(target: object, *args: object) -> tuple[multiprocessing.Process, multiprocessing.Queue]:
    ready = multiprocessing.Event()
    landed: multiprocessing.Queue = multiprocessing.Queue()
    process = multiprocessing.Process(target=target, args=(*args, ready, landed), daemon=True)
    process.start()
    if not ready.wait(20):
        raise SystemExit(f"{target.__name__} did not start")  # type: ignore[attr-defined]
    return process, landed


def stamp_of(landed: multiprocessing.Queue, value: int) -> float:
    """The device's stamp for ``value`` (earlier stamps of other values are dropped)."""
    while True:
        got, t = landed.get(timeout=5)
        if got == value:
            return t


# -- the runs -------------------------------------------------------------------------------------


async def bench_modbus(commands: int) -> dict[str, list[float]]:
    from pymodbus.client import AsyncModbusTcpClient

    from drivers.base import DriverContext
    from drivers.modbus.config import ModbusActuatorConfig, ModbusHubConfig
    from drivers.modbus.plugin import PLUGIN

    port = free_port()
    process, landed = start(modbus_device, port)
    try:
        context = DriverContext(hubs={"ao": ModbusHubConfig(name="ao", host="127.0.0.1", port=port)})
        actuator = PLUGIN.create_actuator(ModbusActuatorConfig(hub="ao", address=ADDRESS, scale=0.001), context)
        bare = AsyncModbusTcpClient("127.0.0.1", port=port)
        await actuator.open()
        await bare.connect()
        times: dict[str, list[float]] = {"holds": [], "returns": [], "bare": []}
        for k in range(commands + 50):  # the first 50 warm up
            raw = 1 + k % 9000
            t0 = time.perf_counter()
            await actuator.command(raw / 20.0, raw * 0.001)
            t1 = time.perf_counter()
            held = stamp_of(landed, raw)
            raw_bare = 1 + (k + 4500) % 9000
            t2 = time.perf_counter()
            await bare.write_register(ADDRESS, raw_bare, device_id=1)
            held_bare = stamp_of(landed, raw_bare)
            if k >= 50:
                times["holds"].append(held - t0)
                times["returns"].append(t1 - t0)
                times["bare"].append(held_bare - t2)
        await actuator.close()
        bare.close()
        return times
    finally:
        process.terminate()
        process.join(5)


async def bench_serial(commands: int) -> dict[str, list[float]]:
    import serial

    from drivers.base import DriverContext
    from drivers.serial_line.config import SerialLineActuatorConfig
    from drivers.serial_line.plugin import PLUGIN

    with tempfile.TemporaryDirectory() as tmp:
        link = str(Path(tmp) / "ttyPI")
        process, landed = start(gcs_controller, link)
        try:
            config = SerialLineActuatorConfig(port=link, readback="SVA? 1\n", error_query="ERR?\n")
            actuator = PLUGIN.create_actuator(config, DriverContext())
            await actuator.open()
            bare_port = None
            times: dict[str, list[float]] = {"holds": [], "returns": [], "bare": []}
            for k in range(commands + 50):
                counts = 1 + k % 90000
                t0 = time.perf_counter()
                await actuator.command(counts / 200.0, counts * 1e-4)
                t1 = time.perf_counter()
                held = stamp_of(landed, counts)
                if bare_port is None:  # one port at a time on a pty: the actuator's stays open, a second fd writes
                    bare_port = serial.Serial(link, 115200, timeout=1)
                counts_bare = 1 + (k + 45000) % 90000
                data = f"SVA 1 {counts_bare * 1e-4:.4f}\n".encode()
                t2 = time.perf_counter()
                bare_port.write(data)
                bare_port.flush()
                held_bare = stamp_of(landed, counts_bare)
                if k >= 50:
                    times["holds"].append(held - t0)
                    times["returns"].append(t1 - t0)
                    times["bare"].append(held_bare - t2)
            await actuator.close()
            if bare_port is not None:
                bare_port.close()
            return times
        finally:
            process.terminate()
            process.join(5)


def report(title: str, times: dict[str, list[float]], actuator: str, bare: str) -> None:
    print(title)
    print(f"{'':46s}{'median us':>11s}{'p99 us':>10s}")
    rows = ((f"{actuator}: command -> device holds it", "holds"), (f"{actuator}: command returns (after its checks)",
                                                                    "returns"), (f"bare: {bare}", "bare"))
    for label, key in rows:
        t = times[key]
        print(f"{label:46s}{1e6 * statistics.median(t):11.0f}{1e6 * percentile(t, 0.99):10.0f}")
    ratio = statistics.median(times["holds"]) / statistics.median(times["bare"])
    print(f"ratio of the medians (command -> held / bare write -> held): {ratio:.2f}x\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--commands", type=int, default=1000)
    args = parser.parse_args()
    modbus = asyncio.run(bench_modbus(args.commands))
    report(f"modbus: {args.commands} commands, pymodbus TCP server on 127.0.0.1 (own process), int16 FC 6, "
           "verify = true", modbus, "actuator", "AsyncModbusTcpClient.write_register")
    serial_times = asyncio.run(bench_serial(args.commands))
    report(f"serial_line: {args.commands} commands, GCS controller on a pty (own process), SVA + SVA? + ERR?",
           serial_times, "actuator", "pyserial write of the same SVA line")


if __name__ == "__main__":
    main()
