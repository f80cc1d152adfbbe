"""The ``modbus`` driver kind: hubs shared by channels, contiguous channels merged per request, and an
analog output as the actuator (on the same hub objects: one connection, one lock)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

from nanodrift.drivers.base import (
    Actuator,
    ActuatorOptions,
    DriverContext,
    DriverPlugin,
    DriverSetupError,
    SensorConfig,
    SensorGroup,
)
from nanodrift.drivers.modbus.actuator import ModbusActuator
from nanodrift.drivers.modbus.config import ModbusActuatorConfig, ModbusHubConfig, ModbusSensorConfig
from nanodrift.drivers.modbus.group import ModbusBlockGroup, plan_blocks
from nanodrift.drivers.modbus.hub import ModbusHub

#: key of the hubs in ``DriverContext.resources``: one connection per hub name per daemon
SHARED_HUBS_KEY = "modbus.hubs"


class ModbusPlugin(DriverPlugin):
    name = "modbus"
    config_model: ClassVar[type[SensorConfig]] = ModbusSensorConfig
    hub_model = ModbusHubConfig
    actuator_model = ModbusActuatorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        channels: list[ModbusSensorConfig] = []
        for config in configs:
            if not isinstance(config, ModbusSensorConfig):
                config = ModbusSensorConfig.model_validate(config.model_dump())
            if config.hub not in context.hubs:
                known = ", ".join(sorted(context.hubs)) or "none defined"
                raise DriverSetupError(f"sensor {config.name!r}: no [[hubs]] named {config.hub!r} (hubs: {known})")
            channels.append(config)
        groups: list[SensorGroup] = []
        for block in plan_blocks(channels):
            groups.append(ModbusBlockGroup(block, shared_hub(context, block.hub), context.clock))
        return groups

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        if not isinstance(config, ModbusActuatorConfig):
            config = ModbusActuatorConfig.model_validate(config.model_dump())
        if config.hub not in context.hubs:
            known = ", ".join(sorted(context.hubs)) or "none defined"
            raise DriverSetupError(f"actuator: no [[hubs]] named {config.hub!r} (hubs: {known})")
        return ModbusActuator(config, shared_hub(context, config.hub))


def shared_hub(context: DriverContext, name: str) -> ModbusHub:
    """The one :class:`ModbusHub` of hub ``name`` in this daemon/procedure (created on first use)."""
    hubs: dict[str, ModbusHub] = context.resources.setdefault(SHARED_HUBS_KEY, {})
    if name not in hubs:
        hub = context.hubs[name]
        assert isinstance(hub, ModbusHubConfig)
        hubs[name] = ModbusHub(hub)
    return hubs[name]


PLUGIN = ModbusPlugin()
