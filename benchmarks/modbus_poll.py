"""One poll cycle of 8 Modbus thermocouple channels against a local pymodbus TCP server.

Merged (the driver's plan: one request for registers 0..7) versus the baseline of 8 separate
single-register reads, both through the same hub and client, measured alternately in the same run.
The server runs in its own process, like a real module.

    .venv/bin/python benchmarks/modbus_poll.py [--cycles 500]
"""

from __future__ import annotations

import argparse
import asyncio
import multiprocessing
import statistics
import time
from multiprocessing.synchronize import Event

from nanodrift.drivers.base import DriverContext, SensorGroup
from nanodrift.drivers.local_port import free_port
from nanodrift.drivers.modbus.config import ModbusHubConfig, ModbusSensorConfig
from nanodrift.drivers.modbus.group import ModbusBlockGroup, plan_blocks
from nanodrift.drivers.modbus.hub import ModbusHub

CHANNELS = 8


def serve(port: int, ready: Event) -> None:
    from pymodbus.server import ModbusTcpServer
    from pymodbus.simulator import DataType, SimData, SimDevice

    async def main() -> None:
        bits = [SimData(address=0, count=16, values=False, datatype=DataType.BITS)]
        registers = [SimData(address=0, values=[215 + i for i in range(32)], datatype=DataType.REGISTERS)]
        device = SimDevice(id=1, simdata=(list(bits), list(bits), list(registers), list(registers)))
        server = ModbusTcpServer([device], address=("127.0.0.1", port))
        await server.serve_forever(background=True)
        ready.set()
        await asyncio.Event().wait()

    asyncio.run(main())


def percentile(values: list[float], q: float) -> float:
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, round(q * (len(ordered) - 1)))]


async def cycle(groups: list[SensorGroup]) -> float:
    start = time.perf_counter()
    for group in groups:
        readings = await group.read()
        assert all(r.state == "ok" for r in readings.values()), readings
    return time.perf_counter() - start


async def bench(port: int, cycles: int) -> None:
    hub_config = ModbusHubConfig(name="adam", type="tcp", host="127.0.0.1", port=port, timeout_s=1.0)
    context = DriverContext(hubs={"adam": hub_config})
    configs = [ModbusSensorConfig(name=f"T{i + 1}", hub="adam", address=i, input_type="input", scale=0.1,
                                  nan_value=-32768) for i in range(CHANNELS)]
    hub = ModbusHub(hub_config)
    merged = [ModbusBlockGroup(b, hub, context.clock) for b in plan_blocks(configs)]
    separate = [ModbusBlockGroup(b, hub, context.clock) for b in plan_blocks(configs, max_gap=-1)]
    for g in merged + separate:
        await g.open()
    for _ in range(20):  # warm up
        await cycle(merged)
        await cycle(separate)
    times: dict[str, list[float]] = {"merged": [], "separate": []}
    plans = {"merged": merged, "separate": separate}
    for _ in range(cycles):
        for name, groups in plans.items():
            times[name].append(await cycle(groups))
    # what one cycle sends: each group's requests per poll (more than one only if a bridged block was split)
    requests = {name: sum(g.request_count for g in groups) for name, groups in plans.items()}
    for g in merged + separate:
        await g.close()

    print(f"Modbus poll cycle, {CHANNELS} int16 channels, pymodbus TCP server on 127.0.0.1, {cycles} cycles each")
    print(f"{'':28s}{'requests/cycle':>15s}{'median ms':>12s}{'p99 ms':>10s}")
    rows = (("merged (driver plan)", "merged"), (f"baseline ({CHANNELS} single reads)", "separate"))
    for label, name in rows:
        t = times[name]
        print(f"{label:28s}{requests[name]:15.1f}{1e3 * statistics.median(t):12.3f}"
              f"{1e3 * percentile(t, 0.99):10.3f}")
    ratio = statistics.median(times["separate"]) / statistics.median(times["merged"])
    print(f"speed-up of the median cycle: {ratio:.1f}x")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=500)
    args = parser.parse_args()
    port = free_port()
    ready = multiprocessing.Event()
    server = multiprocessing.Process(target=serve, args=(port, ready), daemon=True)
    server.start()
    try:
        if not ready.wait(20):
            raise SystemExit("the Modbus server did not start")
        asyncio.run(bench(port, args.cycles))
    finally:
        server.terminate()
        server.join(5)


if __name__ == "__main__":
    main()
