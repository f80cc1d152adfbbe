"""The ``attocube_ids`` driver kind: the axes of an attocube IDS3010 displacement interferometer as position
sensors, over its JSON-RPC 2.0 API on TCP (port 9090). One group per device (``host``, ``port``): one
connection and one poll for its configured axes. The protocol and its sources:
:mod:`nanodrift.drivers.attocube_ids.group` and :mod:`nanodrift.drivers.attocube_ids.rpc`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

from nanodrift.drivers.attocube_ids.config import IdsSensorConfig
from nanodrift.drivers.attocube_ids.group import IdsGroup
from nanodrift.drivers.base import (
    ActuatorOptions,
    DriverContext,
    DriverPlugin,
    DriverSetupError,
    SensorConfig,
    SensorGroup,
    as_config,
)


class IdsPlugin(DriverPlugin):
    name = "attocube_ids"
    config_model: ClassVar[type[SensorConfig]] = IdsSensorConfig

    def config_problems(self, sensors: Sequence[tuple[int, SensorConfig]],
                        actuator: ActuatorOptions | None) -> list[str]:
        """One device axis read by two sensors."""
        problems: list[str] = []
        seen: dict[tuple[str, int, int], tuple[int, str]] = {}
        for index, config in sensors:
            if not isinstance(config, IdsSensorConfig):
                continue
            first, name = seen.setdefault((*config.device, config.ids_axis), (index, config.name))
            if first != index:
                problems.append(f"sensors[{index}] ({config.name}).ids_axis: axis {config.ids_axis} of the IDS at "
                                f"{config.host}:{config.port} is already read by sensors[{first}] ({name})")
        return problems

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        channels = [as_config(c, IdsSensorConfig) for c in configs]
        problems = self.config_problems(list(enumerate(channels)), None)
        if problems:
            raise DriverSetupError("attocube_ids: " + "; ".join(problems))
        devices: dict[tuple[str, int], list[IdsSensorConfig]] = {}
        for config in channels:
            devices.setdefault(config.device, []).append(config)
        return [IdsGroup(axes, context.clock) for axes in devices.values()]


PLUGIN = IdsPlugin()
