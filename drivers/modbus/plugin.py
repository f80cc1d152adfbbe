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
    SensorConfig,
    SensorGroup,
    as_config,
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
        channels = [as_config(c, ModbusSensorConfig) for c in configs]
        for config in channels:  # every channel's hub named in [[hubs]], before any group is built
            shared_hub(context, config.hub, f"sensor {config.name!r}")
        return [ModbusBlockGroup(block, shared_hub(context, block.hub), context.clock)
                for block in plan_blocks(channels)]

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        config = as_config(config, ModbusActuatorConfig)
        return ModbusActuator(config, shared_hub(context, config.hub, "actuator"))


def shared_hub(context: DriverContext, name: str, user: str = "") -> ModbusHub:
    """The one :class:`ModbusHub` of hub ``name`` in this daemon/procedure (created on first use); a
    :class:`DriverSetupError` naming ``user`` when no ``[[hubs]]`` has that name."""
    hub = as_config(context.hub(name, user), ModbusHubConfig)
    return context.resources.per_name(SHARED_HUBS_KEY, name, lambda: ModbusHub(hub))


PLUGIN = ModbusPlugin()
