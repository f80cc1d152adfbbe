"""From a target arriving to the device holding the new value, against the device's bare round trip, same run.

- The daemon is ``python -m nanodrift.cli run`` (what ``nanodrift run`` runs) in its own process, with the
  test harness' ``file`` temperature sensors and a small known model; a client-mode Zenoh session on
  127.0.0.1 puts each target on ``nanodrift/<cell>/target``. "target -> held" runs from just before
  that ``put`` to the device's own stamp of the write (every process reads CLOCK_MONOTONIC through
  ``time.perf_counter``). Targets go one at a time, each put ``--gap-ms`` after the last (25 ms: more than
  the daemon's write period, ``WRITE_PERIOD_S`` = 20 ms, so each is an isolated target). A second, shorter
  run puts each target as soon as the last is held (a sustained stream): there the daemon coalesces to one
  write per period, and that row shows the pacing, not the latency.
- ``modbus``: a pymodbus TCP server in its own process stamps each write of the output register; the
  daemon's ``[actuator] kind = "modbus"`` writes it (FC 6, ``verify = true``). The bare round trip is
  one ``write_register`` of pymodbus' ``AsyncModbusTcpClient`` to the same server (the next register,
  which the daemon's verify never reads), returned, alternating with the targets.
- ``serial_line``: PI GCS controllers emulated on ptys, each in its own process, stamp each ``SVA``
  line as it is complete; the daemon writes ``SVA 1 <V>``, then asks ``SVA? 1`` and ``ERR?`` (as
  config/lab.toml). The bare round trip, on a second controller (a pty answers whoever reads first),
  is pyserial writing ``SVA 1 <V>`` and ``SVA? 1`` and reading the answer line, alternating with the
  targets.
- An extra line: the driver alone, its ``command()`` called in this process until the device holds it
  (the daemon's share is the difference).

    .venv/bin/python benchmarks/actuation.py [--targets 1000]
"""

from __future__ import annotations

import argparse
import asyncio
import json
import multiprocessing
import statistics
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from multiprocessing.synchronize import Event
from pathlib import Path
from typing import Any

import serial
from pymodbus.client import AsyncModbusTcpClient
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))  # the test helpers ...
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # ... after the repo: tests/drivers is not drivers
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    write_test_model,
)
from helpers.serial_helpers import FakeGcsController

from nanodrift.drivers.base import DriverContext
from nanodrift.drivers.modbus.config import ModbusActuatorConfig, ModbusHubConfig
from nanodrift.drivers.modbus.plugin import PLUGIN as MODBUS
from nanodrift.drivers.serial_line.config import SerialLineActuatorConfig
from nanodrift.drivers.serial_line.plugin import PLUGIN as SERIAL_LINE

ADDRESS = 10  # the daemon's (and the driver's) output register
BARE_ADDRESS = 11  # the bare client's: never read back by the daemon's verify
SCALE = 0.001  # volts per count
WARMUP = 50
DRIVER_ALONE = 300  # commands for the extra line


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


# -- the devices, each in its own process ---------------------------------------------------------


def modbus_device(port: int, ready: Event, landed: multiprocessing.Queue) -> None:
    async def action(function_code: int, _start: int, address: int, _count: int, _registers: list[int],
                     values: list[int] | None) -> None:
        if values is not None:
            landed.put(((address, int(values[0])), time.perf_counter()))

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
    controller = FakeGcsController(Path(link))
    controller.on_voltage = lambda volts: landed.put((round(volts * 1e4), time.perf_counter()))
    ready.set()
    threading.Event().wait()  # serve until terminated


class Device:
    """A device process and the queue of its stamps ``(value, perf_counter)``."""

    def __init__(self, target: Callable[..., None], *args: object) -> None:
        ready = multiprocessing.Event()
        self.landed: multiprocessing.Queue = multiprocessing.Queue()
        self.process = multiprocessing.Process(target=target, args=(*args, ready, self.landed), daemon=True)
        self.process.start()
        if not ready.wait(20):
            raise SystemExit(f"{target.__name__} did not start")

    def stamp_of(self, value: object) -> float:
        """The device's stamp for ``value`` (earlier stamps of other values are dropped)."""
        while True:
            got, t = self.landed.get(timeout=5)
            if got == value:
                return t

    def close(self) -> None:
        self.process.terminate()
        self.process.join(5)


# -- the daemon -----------------------------------------------------------------------------------


class Served:
    """``nanodrift run`` with file sensors, the harness' model and ``actuator`` keys; a client on its cell."""

    def __init__(self, root: Path, actuator: str, extra: str = "") -> None:
        self.port = free_port()
        self.cell = f"bench{self.port}"
        plugins = install_file_plugin(root / "plugins")
        model = root / "model.json"
        write_test_model(model)
        sensors = SensorFile(root / "sensors.json", TEMPS)
        config = root / "nanodrift.toml"
        config.write_text(file_sensor_config(root, cell=self.cell, port=self.port, model_path=model,
                                             sensor_file=sensors.path, actuator=actuator, extra=extra))
        self.daemon = Daemon(["--config", str(config)], root / "daemon.log", [plugins])
        self.daemon.wait_log("serving", timeout=30)  # listening: the client can connect
        self.client = Client(self.port, self.cell)
        self.client.wait_alive(30)
        self.client.wait_ready(("T1", "T2"))
        self._id = 0

    def put(self, x_um: float) -> tuple[float, dict[str, Any]]:
        """Put one target; (perf_counter just before the put, the command it was answered with)."""
        self._id += 1
        target_id = self._id
        t0 = time.perf_counter()
        self.client.put(json.dumps({"x_um": x_um, "id": target_id}))

        def answered() -> dict[str, Any] | None:
            for kind, doc in self.client.answers_for(target_id):
                if kind == "error":
                    raise SystemExit(f"target {target_id} refused: {doc}")
                return doc
            return None

        return t0, self.client.wait(answered, 5, f"the answer to target {target_id}")

    def close(self) -> None:
        self.client.close()
        self.daemon.stop()


def x_for(k: int) -> float:
    return 50.0 + k % 400  # consecutive targets differ: so do the values the device is given


# -- the runs -------------------------------------------------------------------------------------


async def bench_modbus(targets: int, root: Path, gap_s: float) -> dict[str, list[float]]:
    port = free_port()
    device = Device(modbus_device, port)
    served = None
    try:
        hub = f'[[hubs]]\nname = "ao"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {port}\n'
        served = Served(root, f'kind = "modbus"\nhub = "ao"\naddress = {ADDRESS}\nscale = {SCALE}\nverify = true\n',
                        extra=hub)
        bare = AsyncModbusTcpClient("127.0.0.1", port=port)
        await bare.connect()
        times: dict[str, list[float]] = {"held": [], "bare": [], "driver": []}
        for k in range(targets + WARMUP):
            t0, command = served.put(x_for(k))
            held = device.stamp_of((ADDRESS, round(command["voltage_v"] / SCALE))) - t0
            raw_bare = 1 + (k * 37) % 9000
            t1 = time.perf_counter()
            await bare.write_register(BARE_ADDRESS, raw_bare, device_id=1)
            rtt = time.perf_counter() - t1
            device.stamp_of((BARE_ADDRESS, raw_bare))
            if k >= WARMUP:
                times["held"].append(held)
                times["bare"].append(rtt)
            await asyncio.sleep(max(0.0, gap_s - (time.perf_counter() - t0)))
        bare.close()
        served.close()
        served = None
        context = DriverContext(hubs={"ao": ModbusHubConfig(name="ao", host="127.0.0.1", port=port)})
        actuator = MODBUS.create_actuator(ModbusActuatorConfig(hub="ao", address=ADDRESS, scale=SCALE), context)
        await actuator.open()
        for k in range(DRIVER_ALONE + WARMUP):
            raw = 1 + (k * 41) % 9000
            t0 = time.perf_counter()
            await actuator.command(raw / 20.0, raw * SCALE)
            held = device.stamp_of((ADDRESS, raw)) - t0
            if k >= WARMUP:
                times["driver"].append(held)
        await actuator.close()
        return times
    finally:
        if served is not None:
            served.close()
        device.close()


async def bench_serial(targets: int, root: Path, gap_s: float) -> dict[str, list[float]]:
    daemons_link, bare_link = str(root / "ttyPI-daemon"), str(root / "ttyPI-bare")
    daemons, bares = Device(gcs_controller, daemons_link), Device(gcs_controller, bare_link)
    served = None
    try:
        served = Served(root, f'kind = "serial_line"\nport = "{daemons_link}"\nreadback = "SVA? 1\\n"\n'
                              'error_query = "ERR?\\n"\n')
        bare = serial.Serial(bare_link, 115200, timeout=1)
        times: dict[str, list[float]] = {"held": [], "bare": [], "driver": []}
        for k in range(targets + WARMUP):
            t0, command = served.put(x_for(k))
            held = daemons.stamp_of(round(float(f"{command['voltage_v']:.4f}") * 1e4)) - t0
            counts = 1 + (k * 37) % 90000
            t1 = time.perf_counter()
            bare.write(f"SVA 1 {counts * 1e-4:.4f}\n".encode())
            bare.write(b"SVA? 1\n")
            answer = bare.readline()
            rtt = time.perf_counter() - t1
            if not answer.startswith(b"1="):
                raise SystemExit(f"bare readback: {answer!r}")
            bares.stamp_of(counts)
            if k >= WARMUP:
                times["held"].append(held)
                times["bare"].append(rtt)
            await asyncio.sleep(max(0.0, gap_s - (time.perf_counter() - t0)))
        bare.close()
        served.close()
        served = None
        config = SerialLineActuatorConfig(port=bare_link, readback="SVA? 1\n", error_query="ERR?\n")
        actuator = SERIAL_LINE.create_actuator(config, DriverContext())
        await actuator.open()
        for k in range(DRIVER_ALONE + WARMUP):
            counts = 1 + (k * 41) % 90000
            t0 = time.perf_counter()
            await actuator.command(counts / 200.0, counts * 1e-4)
            held = bares.stamp_of(counts) - t0
            if k >= WARMUP:
                times["driver"].append(held)
        await actuator.close()
        return times
    finally:
        if served is not None:
            served.close()
        daemons.close()
        bares.close()


def report(title: str, times: dict[str, list[float]], bare: str, driver: str) -> None:
    print(title)
    print(f"{'':62s}{'median us':>11s}{'p99 us':>10s}")
    rows = (("target put -> device holds it (nanodrift run)", "held"), (f"bare round trip: {bare}", "bare"),
            (f"extra: {driver} -> device holds it", "driver"))
    for label, key in rows:
        t = times[key]
        print(f"{label:62s}{1e6 * statistics.median(t):11.0f}{1e6 * percentile(t, 0.99):10.0f}")
    median = statistics.median(times["held"]) / statistics.median(times["bare"])
    p99 = percentile(times["held"], 0.99) / percentile(times["bare"], 0.99)
    print(f"ratio target -> held / bare round trip: median {median:.2f}x, p99 {p99:.2f}x")


def stream_line(times: dict[str, list[float]]) -> None:
    held = times["held"]
    print(f"{'stream: next put as soon as the last is held':62s}{1e6 * statistics.median(held):11.0f}"
          f"{1e6 * percentile(held, 0.99):10.0f}   (the write period, {len(held)} targets)\n")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--targets", type=int, default=1000)
    parser.add_argument("--gap-ms", type=float, default=25.0, help="time between two puts (default 25 ms)")
    parser.add_argument("--stream-targets", type=int, default=100, help="targets of the back-to-back run")
    args = parser.parse_args()
    gap_s = args.gap_ms / 1000.0
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp)
        for name in ("modbus", "serial", "modbus-stream", "serial-stream"):
            (root / name).mkdir()
        modbus = asyncio.run(bench_modbus(args.targets, root / "modbus", gap_s))
        report(f"modbus: {args.targets} targets, one every {args.gap_ms:g} ms; pymodbus TCP server on 127.0.0.1 "
               "(own process), int16 FC 6, verify = true", modbus, "AsyncModbusTcpClient.write_register",
               f"ModbusActuator.command() x {DRIVER_ALONE}")
        stream_line(asyncio.run(bench_modbus(args.stream_targets, root / "modbus-stream", 0.0)))
        serial_times = asyncio.run(bench_serial(args.targets, root / "serial", gap_s))
        report(f"serial_line: {args.targets} targets, one every {args.gap_ms:g} ms; GCS controllers on ptys "
               "(own processes), SVA + SVA? + ERR?", serial_times, "pyserial SVA + SVA? + read the answer",
               f"SerialLineActuator.command() x {DRIVER_ALONE}")
        stream_line(asyncio.run(bench_serial(args.stream_targets, root / "serial-stream", 0.0)))


if __name__ == "__main__":
    main()
