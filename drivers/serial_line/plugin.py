"""The ``serial_line`` driver kind: one group per instrument (one port each), and an ASCII controller as
the actuator (on the sensor's port object when a sensor reads the same controller).

A shared port is one request at a time, each answer matched to its request (``line.py``). A sensor
that *streams* cannot share a port with an actuator that asks questions (``readback``,
``error_query``): nothing tells its lines from the answers, so that config is refused when it is
read (:meth:`SerialLinePlugin.config_problems`), and again when the drivers are built.
"""

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

    def config_problems(self, sensors: Sequence[tuple[int, SensorConfig]],
                        actuator: ActuatorOptions | None) -> list[str]:
        """Two sensors on one port; an actuator on a sensor's port with other settings, or asking
        questions on a port where the sensor streams."""
        problems: list[str] = []
        owners: dict[str, tuple[int, SerialLineSensorConfig]] = {}
        for index, config in sensors:
            if not isinstance(config, SerialLineSensorConfig):
                continue
            if config.port in owners:
                first, owner = owners[config.port]
                problems.append(f"sensors[{index}] ({config.name}).port: port {config.port!r} is already used by "
                                f"sensors[{first}] ({owner.name}) (one instrument per port)")
                continue
            owners[config.port] = (index, config)
        if isinstance(actuator, SerialLineActuatorConfig) and actuator.port in owners:
            index, sensor = owners[actuator.port]
            where = f"sensors[{index}] ({sensor.name})"
            for key in SHARED_SETTINGS:
                if getattr(sensor, key) != getattr(actuator, key):
                    problems.append(f"actuator.{key}: port {actuator.port!r} is read by {where} with {key} = "
                                    f"{getattr(sensor, key)!r}, the actuator says {getattr(actuator, key)!r} (one "
                                    "port, one setting)")
            if sensor.streaming and (actuator.readback or actuator.error_query):
                problems.append(_streaming_problem("actuator.port: ", where, actuator.port))
        return problems

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        groups: list[SensorGroup] = []
        owners: dict[str, SerialLineGroup] = {}
        context.resources.put(PORTS_KEY, owners)  # this build's ports only
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
        owners: dict[str, SerialLineGroup] = context.resources.get(PORTS_KEY, dict) or {}
        sensor = owners.get(config.port)
        if sensor is None:
            own = SerialLineSensorConfig(name="actuator", port=config.port, timeout_s=config.timeout_s,
                                         **{key: getattr(config, key) for key in SHARED_SETTINGS})
            return SerialLineActuator(config, SerialLineGroup(own, context.clock, solicited=True), owns_port=True)
        name = sensor.config.name
        for key in SHARED_SETTINGS:
            if getattr(sensor.config, key) != getattr(config, key):
                raise DriverSetupError(
                    f"actuator: port {config.port!r} is read by sensor {name!r} with {key} = "
                    f"{getattr(sensor.config, key)!r}, the actuator says {getattr(config, key)!r} (one port, one "
                    "setting)")
        if sensor.config.streaming and (config.readback or config.error_query):
            raise DriverSetupError(_streaming_problem("actuator: ", f"sensor {name!r}", config.port))
        return SerialLineActuator(config, sensor, owns_port=False)


def _streaming_problem(prefix: str, sensor: str, port: str) -> str:
    return (f"{prefix}{sensor} streams lines on {port!r}: its lines cannot be told from the answers to the "
            "actuator's readback/error_query, so they cannot be matched to their requests (give the sensor a "
            "query, drop readback and error_query, or give the actuator its own port)")


PLUGIN = SerialLinePlugin()
