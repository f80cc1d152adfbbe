"""One poll of the instrument plugins against their emulators behind real transports.

- ``dcon``: 8 thermocouples of one module on a pty: the plugin's poll (one ``#AA`` line for all eight)
  versus the baseline of 8 single-channel ``#AAN`` exchanges on the same bus (what a one-value-per-line
  reader needs), measured alternately in the same run;
- ``attocube_ids``: a poll of one axis and of three axes of one IDS on TCP 127.0.0.1.

The emulators answer from threads of this process (a real module takes ~10 ms per exchange at 9600
bps: the figures are the software's share).

    .venv/bin/python benchmarks/instrument_poll.py [--cycles 300]
"""

from __future__ import annotations

import argparse
import asyncio
import statistics
import tempfile
import time
from collections.abc import Awaitable, Callable
from pathlib import Path

from nanodrift.drivers.base import DriverContext
from nanodrift.drivers.dcon.config import DconHubConfig
from nanodrift.drivers.dcon.group import DconModuleGroup
from nanodrift.drivers.dcon.protocol import frame, parse_all_channels
from nanodrift.drivers.registry import load_plugin
from nanodrift.drivers.testing import DconBusEmulator, DconModule, IdsEmulator


def summary(name: str, samples_s: list[float]) -> float:
    median = statistics.median(samples_s)
    p95 = sorted(samples_s)[int(0.95 * len(samples_s)) - 1]
    print(f"  {name:<44} median {median * 1e3:7.3f} ms   p95 {p95 * 1e3:7.3f} ms")
    return median


async def timed(call: Callable[[], Awaitable[object]], cycles: int) -> list[float]:
    samples = []
    for _ in range(cycles):
        start = time.perf_counter()
        await call()
        samples.append(time.perf_counter() - start)
    return samples


async def dcon(cycles: int, folder: Path) -> None:
    bus = DconBusEmulator(folder / "ttyRS485", [DconModule(1, [20.0 + c for c in range(8)])])
    plugin = load_plugin("dcon")
    hub = DconHubConfig(name="rs485", port=bus.port, timeout_s=0.5)
    configs = [plugin.config_model.model_validate({"name": f"T{c}", "kind": "dcon", "hub": "rs485", "address": 1,
                                                   "channel": c}) for c in range(8)]
    [group] = plugin.create(configs, DriverContext(hubs={"rs485": hub}))
    assert isinstance(group, DconModuleGroup)
    await group.open()

    async def per_channel() -> None:
        for channel in range(8):
            parse_all_channels(await group.bus.request(frame(f"#01{channel}", with_checksum=False), "a value"))

    merged: list[float] = []
    single: list[float] = []
    for _ in range(cycles):  # alternately, so both see the same machine load
        merged += await timed(group.read, 1)
        single += await timed(per_channel, 1)
    await group.close()
    bus.close()
    print("dcon: 8 channels of one module on a pty")
    one = summary("one #AA line for all 8 (the plugin's poll)", merged)
    eight = summary("8 x #AAN, one exchange per channel (baseline)", single)
    print(f"  ratio baseline / plugin: {eight / one:.2f}")


async def ids(cycles: int) -> None:
    print("attocube_ids: one IDS on TCP 127.0.0.1 (1 and 3 axes polled alternately)")
    with IdsEmulator() as device:
        plugin = load_plugin("attocube_ids")
        groups = {}
        for axes in (1, 3):
            configs = [plugin.config_model.model_validate({"name": f"ifm{a}", "kind": "attocube_ids",
                                                           "host": "127.0.0.1", "port": device.port, "ids_axis": a})
                       for a in range(axes)]
            [groups[axes]] = plugin.create(configs, DriverContext())
            await groups[axes].open()
        samples: dict[int, list[float]] = {1: [], 3: []}
        for _ in range(cycles):
            for axes, group in groups.items():
                samples[axes] += await timed(group.read, 1)
        for axes, group in groups.items():
            await group.close()
            summary(f"a poll of {axes} axis/axes ({1 + 2 * axes} calls)", samples[axes])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cycles", type=int, default=300)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory() as folder:
        asyncio.run(dcon(args.cycles, Path(folder)))
    asyncio.run(ids(args.cycles))


if __name__ == "__main__":
    main()
