"""The ``serial_line`` driver kind: one group per instrument (one port each), and an ASCII controller as
the actuator (on the sensor's port object when a sensor reads the same controller).

A shared port is one request at a time, each answer matched to its request (``line.py``). A sensor
that *streams* cannot share a port with an actuator that asks questions (``readback``,
``error_query``): nothing tells its lines from the answers, so that config is refused when it is
read (:meth:`SerialLinePlugin.config_problems`), and again when the drivers are built.

The resynchronisation query (``resync_query``/``resync_pattern``) is a setting of the line: either the
sensor or the actuator on a shared port may declare it (both: the same). A port on which a querying
sensor and an actuator that asks questions share the line without one is accepted, with a warning
(:meth:`SerialLinePlugin.config_warnings`, shown by ``check-config``; an error with ``--strict``): an
answer later than the quiet period can then be taken for the other device's answer. Not refused:
controllers without an identification query exist, and such configs ran before the keys did.
"""

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
    as_config,
)
from nanodrift.drivers.serial_line.actuator import SerialLineActuator
from nanodrift.drivers.serial_line.config import SerialLineActuatorConfig, SerialLineSensorConfig
from nanodrift.drivers.serial_line.line import QUIET_S, SerialLineGroup

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
            first, owner = owners.setdefault(config.port, (index, config))
            if first != index:
                problems.append(f"sensors[{index}] ({config.name}).port: port {config.port!r} is already used by "
                                f"sensors[{first}] ({owner.name}) (one instrument per port)")
        if isinstance(actuator, SerialLineActuatorConfig) and actuator.port in owners:
            index, sensor = owners[actuator.port]
            where = f"sensors[{index}] ({sensor.name})"
            problems += _sharing_problems(sensor, sensor.resync, where, actuator, keyed=True)
            if sensor.streaming and actuator.resync is not None:
                problems.append(f"actuator.resync_query: {where} streams lines on {actuator.port!r}: nothing on "
                                "the line is a request's answer to resynchronise (drop resync_query and "
                                "resync_pattern)")
        return problems

    def config_warnings(self, sensors: Sequence[tuple[int, SensorConfig]],
                        actuator: ActuatorOptions | None) -> list[str]:
        """A port shared by a querying sensor and an actuator that asks questions, without a resync query."""
        if not isinstance(actuator, SerialLineActuatorConfig) or not actuator.asks or actuator.resync is not None:
            return []
        for index, sensor in sensors:
            if (isinstance(sensor, SerialLineSensorConfig) and sensor.port == actuator.port and not sensor.streaming
                    and sensor.resync is None):
                asks = " and ".join(repr(q) for q in (actuator.readback, actuator.error_query) if q)
                return [f"actuator.port: port {actuator.port!r} is shared by sensors[{index}] ({sensor.name}), "
                        f"querying {sensor.query!r}, and the actuator asking {asks}, with no resync_query: an "
                        f"answer that comes later than min(timeout_s, {QUIET_S:g} s) after its request timed out "
                        "looks like a fresh one (no request ids) and can be taken, once, for the other's answer "
                        "(a voltage published as the position); declare resync_query and resync_pattern (GCS: "
                        "resync_query = \"*IDN?\\n\", resync_pattern = 'PI|Physik')"]
        return []

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        owners: dict[str, SerialLineGroup] = {}
        context.resources.put(PORTS_KEY, owners)  # this build's ports only
        for config in configs:
            config = as_config(config, SerialLineSensorConfig)
            if config.port in owners:
                raise DriverSetupError(f"sensor {config.name!r}: port {config.port!r} is already used by sensor "
                                       f"{owners[config.port].config.name!r} (one instrument per port)")
            owners[config.port] = SerialLineGroup(config, context.clock)
        return list(owners.values())

    def create_actuators(self, configs: Sequence[ActuatorOptions], context: DriverContext) -> list[Actuator]:
        """Several axes of one controller (a multi-axis GCS controller): the axes on one port share one
        line (one lock: each request its own answer); the first axis' actuator owns it when no sensor does."""
        actuators: list[Actuator] = []
        lines: dict[str, SerialLineActuator] = {}
        for config in configs:
            config = as_config(config, SerialLineActuatorConfig)
            first = lines.get(config.port)
            if first is None:
                actuator = self.create_actuator(config, context)
                assert isinstance(actuator, SerialLineActuator)
                lines[config.port] = actuator
                actuators.append(actuator)
                continue
            for key in SHARED_SETTINGS:
                if getattr(first.config, key) != getattr(config, key):
                    raise DriverSetupError(f"actuator: port {config.port!r} is driven by another axis with {key} = "
                                           f"{getattr(first.config, key)!r}, this axis says {getattr(config, key)!r} "
                                           "(one port, one setting)")
            if config.resync is not None:
                first.port.use_resync(*config.resync)
            actuators.append(SerialLineActuator(config, first.port, owns_port=False))
        return actuators

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        config = as_config(config, SerialLineActuatorConfig)
        owners: dict[str, SerialLineGroup] = context.resources.get(PORTS_KEY, dict) or {}
        sensor = owners.get(config.port)
        if sensor is None:
            own = SerialLineSensorConfig(name="actuator", port=config.port, timeout_s=config.timeout_s,
                                         **{key: getattr(config, key) for key in SHARED_SETTINGS})
            line = SerialLineGroup(own, context.clock, solicited=True)
            if config.resync is not None:  # a controller alone on its port: its own late answers
                line.use_resync(*config.resync)
            return SerialLineActuator(config, line, owns_port=True)
        if problems := _sharing_problems(sensor.config, sensor.resync, f"sensor {sensor.config.name!r}", config,
                                         keyed=False):
            raise DriverSetupError(problems[0])
        if config.resync is not None:
            sensor.use_resync(*config.resync)  # the line's setting, whichever of the two declares it
        return SerialLineActuator(config, sensor, owns_port=False)


def _sharing_problems(sensor: SerialLineSensorConfig, line_resync: tuple[str, str] | None, where: str,
                      actuator: SerialLineActuatorConfig, *, keyed: bool) -> list[str]:
    """Why ``actuator`` cannot share the port ``sensor`` (``where``, its line resynchronised by ``line_resync``)
    reads; ``keyed``: lines named ``actuator.<key>: ...`` (the config's form), else ``actuator: ...`` (a build's)."""
    def named(key: str) -> str:
        return f"actuator.{key}: " if keyed else "actuator: "

    port = actuator.port
    problems = [f"{named(key)}port {port!r} is read by {where} with {key} = {getattr(sensor, key)!r}, the actuator "
                f"says {getattr(actuator, key)!r} (one port, one setting)"
                for key in SHARED_SETTINGS if getattr(sensor, key) != getattr(actuator, key)]
    if sensor.streaming and actuator.asks:
        problems.append(f"{named('port')}{where} streams lines on {port!r}: its lines cannot be told from the answers "
                        "to the actuator's readback/error_query, so they cannot be matched to their requests (give "
                        "the sensor a query, drop readback and error_query, or give the actuator its own port)")
    if line_resync is not None and actuator.resync is not None and line_resync != actuator.resync:
        problems.append(f"{named('resync_query')}port {port!r} is resynchronised by {where} with "
                        f"{_resync_text(line_resync)}, the actuator says {_resync_text(actuator.resync)} (one port, "
                        f"one resync query{': declare it once' if keyed else ''})")
    return problems


def _resync_text(resync: tuple[str, str]) -> str:
    return f"resync_query = {resync[0]!r}, resync_pattern = {resync[1]!r}"


PLUGIN = SerialLinePlugin()
