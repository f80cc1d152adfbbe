"""The ``dcon`` driver kind: thermocouple modules speaking DCON ASCII (ADAM-4018/4118, ICP DAS I-7018) on
RS-485 or a TCP gateway.

One group per module (hub and address): ``#AA`` answers every channel in one exchange. One bus object
per hub (``context.resources``), shared by its modules' groups, one request at a time. The protocol and
the documents it follows: :mod:`nanodrift.drivers.dcon.protocol`.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

from nanodrift.drivers.base import (
    ActuatorOptions,
    DriverContext,
    DriverPlugin,
    DriverSetupError,
    SensorConfig,
    SensorGroup,
    as_config,
)
from nanodrift.drivers.dcon.bus import DconBus
from nanodrift.drivers.dcon.config import DconHubConfig, DconSensorConfig
from nanodrift.drivers.dcon.group import DconModuleGroup

#: key of the buses in ``DriverContext.resources``: hub name -> its one bus
BUSES_KEY = "dcon.buses"
#: settings every channel of one module must share (they are the module's, not the channel's)
MODULE_SETTINGS = ("checksum", "open_detection")


class DconPlugin(DriverPlugin):
    name = "dcon"
    config_model: ClassVar[type[SensorConfig]] = DconSensorConfig
    hub_model = DconHubConfig

    def config_problems(self, sensors: Sequence[tuple[int, SensorConfig]],
                        actuator: ActuatorOptions | None) -> list[str]:
        """A channel read twice, and channels of one module that disagree on the module's settings."""
        problems: list[str] = []
        seen: dict[tuple[str, int, int], tuple[int, str]] = {}
        modules: dict[tuple[str, int], tuple[int, DconSensorConfig]] = {}
        for index, config in sensors:
            if not isinstance(config, DconSensorConfig):
                continue
            where = f"sensors[{index}] ({config.name})"
            first, name = seen.setdefault((config.hub, config.address, config.channel), (index, config.name))
            if first != index:
                problems.append(f"{where}.channel: channel {config.channel} of module {config.address:02X} on hub "
                                f"{config.hub!r} is already read by sensors[{first}] ({name})")
                continue
            first, owner = modules.setdefault(config.module, (index, config))
            for setting in MODULE_SETTINGS:
                mine, theirs = getattr(config, setting), getattr(owner, setting)
                if mine != theirs:
                    problems.append(f"{where}.{setting}: {mine!r} differs from sensors[{first}] ({owner.name}) on "
                                    f"the same module ({theirs!r}): it is the module's setting")
        return problems

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        problems = self.config_problems(list(enumerate(configs)), None)
        if problems:
            raise DriverSetupError("dcon: " + "; ".join(problems))
        modules: dict[tuple[str, int], list[DconSensorConfig]] = {}
        for config in (as_config(c, DconSensorConfig) for c in configs):
            context.hub(config.hub, f"sensor {config.name!r}")
            modules.setdefault(config.module, []).append(config)
        per_hub = {hub: sum(1 for h, _ in modules if h == hub) for hub, _ in modules}
        return [DconModuleGroup(channels, shared_bus(context, hub), context.clock, modules_on_bus=per_hub[hub])
                for (hub, _), channels in modules.items()]


def shared_bus(context: DriverContext, name: str) -> DconBus:
    """The one :class:`DconBus` of hub ``name`` in this daemon or procedure (created on first use)."""
    return context.resources.per_name(BUSES_KEY, name, lambda: DconBus(as_config(context.hubs[name], DconHubConfig)))


PLUGIN = DconPlugin()
