"""A lab's own driver package, as a lab would write it: not part of nanodrift, found through a real
entry point (``labbox = helpers.lab_plugin:PLUGIN`` in ``nanodrift.drivers``).

The sensors are the harness' ``file`` sensors (a JSON file the test rewrites). The output is one
channel of a lab's box, emulated by a file of JSON lines (the last line is what the output holds):
it takes 0..``full_scale_v`` in steps of 1 mV, so it quantizes like a DAC (a voltage near a limit is
written as the count on the inside). The contract tests run it through the same checks as
nanodrift's own plugins.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Literal

from pydantic import Field

from helpers.file_plugin import FilePlugin  # (not the harness: daemons import this module)
from nanodrift.drivers import registry
from nanodrift.drivers.base import Actuator, ActuatorOptions, DeviceError, DriverContext

STEP_V = 0.001  # one count of the box's output


class LabBoxConfig(ActuatorOptions):
    kind: Literal["labbox"] = "labbox"
    path: str
    channel: int = Field(default=1, ge=1, le=4)
    full_scale_v: float = Field(default=10.0, gt=0)


class LabBoxOutput(Actuator):
    def __init__(self, config: LabBoxConfig) -> None:
        self.config = config
        self.path = Path(config.path)
        self.description = f"lab box channel {config.channel} ({config.path})"
        self._open = False

    async def open(self) -> None:
        try:
            self.path.touch()
        except OSError as error:
            raise DeviceError(f"{self.description}: {error}") from error
        self._open = True

    async def close(self) -> None:
        self._open = False

    def _count(self, voltage_v: float) -> int:
        if not math.isfinite(voltage_v):
            raise ValueError(f"{self.description}: {voltage_v} is not a voltage")
        count = round(voltage_v / STEP_V)
        if self.limits_v is not None:
            low, high = self.limits_v
            if count * STEP_V > high + 1e-12:
                count = math.floor(high / STEP_V + 1e-9)
            elif count * STEP_V < low - 1e-12:
                count = math.ceil(low / STEP_V - 1e-9)
        if not 0 <= count * STEP_V <= self.config.full_scale_v + 1e-12:
            raise ValueError(f"{self.description}: {voltage_v:g} V is outside 0..{self.config.full_scale_v:g} V")
        return count

    def sent_voltage(self, voltage_v: float) -> float:
        return round(self._count(voltage_v) * STEP_V, 6)

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        sent = self.sent_voltage(voltage_v)  # ValueError before anything is written
        try:
            with self.path.open("a") as out:
                out.write(json.dumps({"channel": self.config.channel, "voltage_v": sent}) + "\n")
        except OSError as error:
            raise DeviceError(f"{self.description}: writing {sent:.3f} V failed: {error}") from error

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        try:
            lines = self.path.read_text().splitlines()
        except OSError as error:
            raise DeviceError(f"{self.description}: reading the output failed: {error}") from error
        return ("voltage_v", float(json.loads(lines[-1])["voltage_v"])) if lines else None


class LabBoxPlugin(FilePlugin):
    """``file`` sensors plus the box's output."""

    name = "labbox"
    actuator_model = LabBoxConfig

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        if not isinstance(config, LabBoxConfig):
            config = LabBoxConfig.model_validate(config.model_dump())
        return LabBoxOutput(config)


PLUGIN = LabBoxPlugin()


def install(directory: Path, entry: str = "labbox = helpers.lab_plugin:PLUGIN") -> Path:
    """A ``*.dist-info`` declaring ``entry`` in ``nanodrift.drivers`` (what ``pip install`` of the lab's
    package leaves behind); returns the directory to put on the path."""
    info = directory / "nanodrift_lab_box-0.0.dist-info"
    info.mkdir(parents=True, exist_ok=True)
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: nanodrift-lab-box\nVersion: 0.0\n")
    (info / "entry_points.txt").write_text(f"[{registry.GROUP}]\n{entry}\n")
    return directory


@contextmanager
def installed(directory: Path, entry: str = "labbox = helpers.lab_plugin:PLUGIN") -> Iterator[Path]:
    """The lab's package installed (on ``sys.path``) for the ``with`` body; the registry forgets it after."""
    path = str(install(directory, entry))
    sys.path.insert(0, path)
    registry.available.cache_clear()
    registry.load_plugin.cache_clear()
    try:
        yield directory
    finally:
        sys.path.remove(path)
        registry.available.cache_clear()
        registry.load_plugin.cache_clear()
