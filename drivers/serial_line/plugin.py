"""The ``serial_line`` driver kind: one group per instrument (one port each), and an ASCII controller as
the actuator (on the sensor's port object when a sensor reads the same controller)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

from drivers.base import (
    Actuator,
    ActuatorOptions,
    DriverContext,
    DriverPlugin,
    DriverSetupError,
    SensorConfig,
    SensorGroup,
)
from drivers.serial_line.actuator import SerialLineActuator
from drivers.serial_line.config import SerialLineActuatorConfig, SerialLineSensorConfig
from drivers.serial_line.line import SerialLineGroup

#: key of the port owners in ``DriverContext.resources``: port -> the sensor group reading it
PORTS_KEY = "serial_line.ports"
#: settings a sensor and the actuator on one port must agree on
SHARED_SETTINGS = ("baudrate", "bytesize", "parity", "stopbits", "eol")


class SerialLinePlugin(DriverPlugin):
    name = "serial_line"
    config_model: ClassVar[type[SensorConfig]] = SerialLineSensorConfig
    actuator_model = SerialLineActuatorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        groups: list[SensorGroup] = []
        owners: dict[str, SerialLineGroup] = {}
        context.resources[PORTS_KEY] = owners  # this build's ports only
        for config in configs:
            if not isinstance(config, SerialLineSensorConfig):
                config = SerialLineSensorConfig.model_validate(config.model_dump())
            if config.port in owners:
                raise DriverSetupError(f"sensor {config.name!r}: port {config.port!r} is already used by sensor "
                                       f"{owners[config.port].config.name!r} (one instrument per port)")
            group = SerialLineGroup(config, context.clock)
            owners[config.port] = group
            groups.append(group)
        return groups

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        if not isinstance(config, SerialLineActuatorConfig):
            config = SerialLineActuatorConfig.model_validate(config.model_dump())
        sensor = context.resources.get(PORTS_KEY, {}).get(config.port)
        if sensor is None:
            own = SerialLineSensorConfig(name="actuator", port=config.port, timeout_s=config.timeout_s,
                                         **{key: getattr(config, key) for key in SHARED_SETTINGS})
            return SerialLineActuator(config, SerialLineGroup(own, context.clock), owns_port=True)
        name = sensor.config.name
        for key in SHARED_SETTINGS:
            if getattr(sensor.config, key) != getattr(config, key):
                raise DriverSetupError(
                    f"actuator: port {config.port!r} is read by sensor {name!r} with {key} = "
                    f"{getattr(sensor.config, key)!r}, the actuator says {getattr(config, key)!r} (one port, one "
                    "setting)")
        if sensor.config.streaming and (config.readback or config.error_query):
            raise DriverSetupError(
                f"actuator: sensor {name!r} streams lines on {config.port!r}; its lines cannot be told from "
                "answers to readback/error_query (query the sensor, or drop the readback)")
        return SerialLineActuator(config, sensor, owns_port=False)


PLUGIN = SerialLinePlugin()
