"""The harness' ``file`` sensor plugin (:mod:`helpers.daemon_harness` documents the file it reads).

A module of its own, importing only :mod:`nanodrift.drivers.base`: every daemon of the tests loads it through its
entry point (``file = helpers.file_plugin:PLUGIN``), and the harness' own imports (zenoh sessions, the Modbus
emulators) would add a tenth of a second of CPU to each daemon's start for nothing it uses.
"""

from __future__ import annotations

import asyncio
import json
from collections.abc import Sequence
from pathlib import Path

from nanodrift.drivers.base import (
    Clock,
    DeviceError,
    DriverContext,
    DriverPlugin,
    MonotonicClock,
    Reading,
    SensorConfig,
    SensorGroup,
)


class FileSensorConfig(SensorConfig):
    path: str


class FileGroup(SensorGroup):
    def __init__(self, configs: Sequence[FileSensorConfig], clock: Clock) -> None:
        self.names = tuple(c.name for c in configs)
        self.roles = {c.name: c.role for c in configs}
        self.interval_s = min(c.interval_s for c in configs)
        self.timeout_s = min(c.timeout_s for c in configs)
        self.path = Path(configs[0].path)
        self.clock = clock

    async def open(self) -> None:
        if not self.path.exists():
            raise DeviceError(f"{self.path}: no such file")

    async def read(self) -> dict[str, Reading]:
        try:
            doc = json.loads(self.path.read_text())
        except (OSError, ValueError) as error:
            raise DeviceError(f"{self.path}: {error}") from None
        if doc.get("error"):
            raise DeviceError(str(doc["error"]))
        if doc.get("hang"):
            await asyncio.sleep(3600)
        now = self.clock.now()
        out = {}
        for name in self.names:
            unit = "degC" if self.roles[name] == "temperature" else "um"
            fault = (doc.get("fault") or {}).get(name)
            if fault:
                out[name] = Reading.fault(now, str(fault), unit)
            elif name in (doc.get("values") or {}):
                age = float((doc.get("age") or {}).get(name, 0.0))
                out[name] = Reading(float(doc["values"][name]), now - age, unit=unit)
            else:
                out[name] = Reading.fault(now, "no value in file", unit)
        return out

    async def close(self) -> None:
        return None


class FilePlugin(DriverPlugin):
    name = "file"
    config_model = FileSensorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        by_path: dict[str, list[FileSensorConfig]] = {}
        for c in configs:
            assert isinstance(c, FileSensorConfig)
            by_path.setdefault(c.path, []).append(c)
        return [FileGroup(group, context.clock or MonotonicClock()) for group in by_path.values()]


PLUGIN = FilePlugin()
