"""The ``serial_line`` driver kind: one group per instrument (one port each)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

from drivers.base import DriverContext, SensorConfig, SensorGroup
from drivers.serial_line.config import SerialLineSensorConfig
from drivers.serial_line.line import SerialLineGroup


class SerialLinePlugin:
    name = "serial_line"
    config_model: ClassVar[type[SensorConfig]] = SerialLineSensorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        groups: list[SensorGroup] = []
        ports: dict[str, str] = {}
        for config in configs:
            if not isinstance(config, SerialLineSensorConfig):
                config = SerialLineSensorConfig.model_validate(config.model_dump())
            if config.port in ports:
                raise ValueError(f"sensor {config.name!r}: port {config.port!r} is already used by sensor "
                                 f"{ports[config.port]!r} (one instrument per port)")
            ports[config.port] = config.name
            groups.append(SerialLineGroup(config, context.clock))
        return groups


PLUGIN = SerialLinePlugin()
