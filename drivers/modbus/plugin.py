"""The ``modbus`` driver kind: hubs shared by channels, contiguous channels merged per request."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

from drivers.base import DriverContext, SensorConfig, SensorGroup
from drivers.modbus.config import ModbusSensorConfig
from drivers.modbus.group import ModbusBlockGroup, plan_blocks
from drivers.modbus.hub import ModbusHub

#: key of the hubs in ``DriverContext.shared``: one connection per hub name per daemon
SHARED_HUBS_KEY = "modbus.hubs"


class ModbusPlugin:
    name = "modbus"
    config_model: ClassVar[type[SensorConfig]] = ModbusSensorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        channels: list[ModbusSensorConfig] = []
        for config in configs:
            if not isinstance(config, ModbusSensorConfig):
                config = ModbusSensorConfig.model_validate(config.model_dump())
            if config.hub not in context.hubs:
                known = ", ".join(sorted(context.hubs)) or "none defined"
                raise ValueError(f"sensor {config.name!r}: no [[hubs]] named {config.hub!r} (hubs: {known})")
            channels.append(config)
        hubs: dict[str, ModbusHub] = context.shared.setdefault(SHARED_HUBS_KEY, {})
        groups: list[SensorGroup] = []
        for block in plan_blocks(channels):
            if block.hub not in hubs:
                hubs[block.hub] = ModbusHub(context.hubs[block.hub])
            groups.append(ModbusBlockGroup(block, hubs[block.hub], context.clock))
        return groups


PLUGIN = ModbusPlugin()
