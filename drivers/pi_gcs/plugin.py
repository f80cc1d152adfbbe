"""The ``pi_gcs`` driver kind: an output only (``[actuator]`` or ``[axes.actuator]``). The axes of one
controller (one ``host:port`` or one serial device) share one connection: one lock, each request batch
its own answers, closed when the last axis closes."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar, Literal

from pydantic import model_validator

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
from nanodrift.drivers.pi_gcs.actuator import PiGcsActuator
from nanodrift.drivers.pi_gcs.config import PiGcsActuatorConfig
from nanodrift.drivers.pi_gcs.link import GcsLink

NOT_A_SENSOR = ("kind: pi_gcs is an output ([actuator] kind = \"pi_gcs\"), not a sensor: read the stage's position "
                "with a position sensor (an interferometer)")
#: key of the connections in ``DriverContext.resources``: controller address -> its link
LINKS_KEY = "pi_gcs.links"


class PiGcsSensorConfig(SensorConfig):
    """``pi_gcs`` reads no sensor (the stage's position comes from an interferometer): a ``[[sensors]]``
    entry of this kind is refused, saying so."""

    kind: Literal["pi_gcs"] = "pi_gcs"

    @model_validator(mode="after")
    def _not_a_sensor(self) -> PiGcsSensorConfig:
        raise ValueError(NOT_A_SENSOR)


class PiGcsPlugin(DriverPlugin):
    name = "pi_gcs"
    config_model: ClassVar[type[SensorConfig]] = PiGcsSensorConfig
    actuator_model = PiGcsActuatorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        if configs:
            raise DriverSetupError(NOT_A_SENSOR)
        return []

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        config = as_config(config, PiGcsActuatorConfig)
        link = context.resources.per_name(LINKS_KEY, config.address, lambda: GcsLink(config))
        if (link.config.transport, link.config.baudrate) != (config.transport, config.baudrate):
            raise DriverSetupError(f"actuator: controller {config.address} is reached with other settings by another "
                                   "axis (one connection, one setting)")
        return PiGcsActuator(config, link)


PLUGIN = PiGcsPlugin()
