"""Per-command write latency of the ``pi_gcs`` output over TCP and over a pty, beside the generic ``serial_line``
output driving a GCS controller on a pty, in the same run.

One command is the driver's whole ``command()``, from the call to its return: what the daemon's actuation
waits for per write.

- ``pi_gcs`` (TCP, pty): one batch ``ERR?`` / ``SVA 1 <V>`` / ``ERR?`` / ``SVA? 1`` and its three answers
  (the pending-error check, the command's own error, the read-back), against
  ``nanodrift.drivers.testing.pi_gcs_emulator`` on 127.0.0.1 / on a pty;
- ``serial_line`` (pty, the baseline): ``SVA 1 <V>`` then ``SVA? 1`` then ``ERR?``, each query its own round
  trip, as config/lab.toml configures it, against ``FakeGcsController``.

The devices run in one child process (their own interpreter: no GIL shared with the drivers); the drivers take
turns command by command, so a load on the machine falls on all three alike.

    .venv/bin/python benchmarks/pi_gcs.py [--commands 2000]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import statistics
import tempfile
import threading
import time
from multiprocessing.synchronize import Event
from pathlib import Path

from nanodrift.drivers.base import Actuator, DriverContext
from nanodrift.drivers.registry import load_plugin
from nanodrift.drivers.testing import FakeGcsController
from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice, PiGcsTcpServer

WARMUP = 50
LIMITS_V = (-2.0, 12.0)


def devices(root: str, ready: multiprocessing.Queue, stop: Event) -> None:
    """The three controllers, until ``stop``: puts (tcp port, pi_gcs pty, serial_line pty) on ``ready``."""
    loop = asyncio.new_event_loop()
    threading.Thread(target=loop.run_forever, daemon=True).start()
    server = PiGcsTcpServer(PiGcsEmulator(axes={"1": EmulatedAxis(servo=True)}))
    asyncio.run_coroutine_threadsafe(server.start(), loop).result(10)
    pty = PiGcsPtyDevice(Path(root) / "ttyPI_gcs", PiGcsEmulator(axes={"1": EmulatedAxis(servo=True)}))
    baseline = FakeGcsController(Path(root) / "ttyPI_line")
    ready.put((server.port, pty.port, baseline.port))
    stop.wait()
    pty.close()
    baseline.close()


def build(kind: str, options: dict[str, object]) -> Actuator:
    plugin = load_plugin(kind)
    assert plugin.actuator_model is not None
    actuator = plugin.create_actuator(plugin.actuator_model.model_validate({"kind": kind, **options}), DriverContext())
    actuator.limits_v = LIMITS_V
    return actuator


async def measure(actuators: dict[str, Actuator], commands: int) -> dict[str, list[float]]:
    for actuator in actuators.values():
        await actuator.open()
    times: dict[str, list[float]] = {name: [] for name in actuators}
    for k in range(WARMUP + commands):
        volts = 1.0 + (k % 97) * 0.05  # a new value every time: no controller can skip one
        for name, actuator in actuators.items():
            start = time.perf_counter()
            await actuator.command(volts / 0.02, volts)
            if k >= WARMUP:
                times[name].append(time.perf_counter() - start)
    for actuator in actuators.values():
        await actuator.close()
    return times


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--commands", type=int, default=2000, help="commands per driver (after a warm-up)")
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as root:
        ready: multiprocessing.Queue = multiprocessing.Queue()
        stop = multiprocessing.Event()
        child = multiprocessing.Process(target=devices, args=(root, ready, stop), daemon=True)
        child.start()
        try:
            tcp_port, gcs_pty, line_pty = ready.get(timeout=30)
            actuators = {
                "pi_gcs over TCP (127.0.0.1)": build("pi_gcs", {"host": "127.0.0.1", "port": tcp_port}),
                "pi_gcs over a pty": build("pi_gcs", {"transport": "serial", "port": gcs_pty}),
                "serial_line over a pty (SVA, SVA?, ERR?)": build(
                    "serial_line", {"port": line_pty, "readback": "SVA? 1\n", "error_query": "ERR?\n"}),
            }
            times = asyncio.run(measure(actuators, args.commands))
        finally:
            stop.set()
            child.join(10)
    baseline = statistics.median(times["serial_line over a pty (SVA, SVA?, ERR?)"])
    print(f"per-command write latency, {args.commands} commands each (driver's command() call to return)")
    print(f"{'':44s}{'median us':>11s}{'p99 us':>10s}{'median / serial_line':>22s}")
    for name, values in times.items():
        median = statistics.median(values)
        print(f"{name:44s}{1e6 * median:11.0f}{1e6 * percentile(values, 0.99):10.0f}{median / baseline:21.2f}x")


if __name__ == "__main__":
    main()
