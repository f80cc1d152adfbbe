"""The ``simulated`` driver kind: sensor groups and an actuator on one shared :class:`SimulatedCell`.

An ordinary plugin (python-can's ``virtual`` bus, pyvisa-sim), and a virtual cell
(:class:`~nanodrift.drivers.base.VirtualCellPlugin`): it owns the ``[simulation]`` table,
supplies the cell's clock (scaled wall time in the daemon, a virtual clock in procedures) and, when
the table is present without ``[[sensors]]``, the paper's four thermocouples and interferometer.
With ``[simulation] axes = "xy"`` (or ``"xyz"``) the cell is a stacked stage
(:class:`~nanodrift.drivers.simulated.cell.SimulatedCell` of those axes): one simulated output per axis
(``[axes.actuator] kind = "simulated"``, built by :meth:`SimulatedPlugin.create_actuators`) and one
interferometer per axis (``interferometer_x``, ``interferometer_y``, ...); without ``[[axes]]`` the
plugin supplies them (workspace 0..480 µm), and without ``[[sensors]]`` T1..T4 and one beam per axis.
Temperature sensors with the same poll interval form one group (like one Modbus module answering
four thermocouples); the interferometer is a group of its own.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from typing import Any, ClassVar, Literal

from pydantic import BaseModel

from nanodrift.drivers.base import (
    Actuator,
    ActuatorOptions,
    Clock,
    DriverContext,
    DriverSetupError,
    MonotonicClock,
    Reading,
    SensorConfig,
    SensorGroup,
    VirtualCellPlugin,
    as_config,
)
from nanodrift.drivers.simulated.cell import SimulatedCell, position_channels
from nanodrift.drivers.simulated.clock import ScaledClock, VirtualClock
from nanodrift.drivers.simulated.config import SECTION, SimulatedActuatorConfig, SimulatedSensorConfig, SimulationConfig

RESOURCE_KEY = "simulated.cell"
PLUGIN_KIND = "simulated"
#: each axis' workspace on the default stacked stage (µm): the paper's calibrated travel
DEFAULT_AXIS_MAX_UM = 480.0


def shared_cell(context: DriverContext) -> SimulatedCell:
    """The one cell of this daemon/procedure, created on first use from the ``[simulation]`` table.

    On a :class:`VirtualClock` (procedures) scenario time is clock time, so a resumed calibration
    continues the same room history; on a :class:`ScaledClock` the scenario starts when the clock does
    (at a UTC midnight: see :meth:`SimulatedPlugin.make_clock`); on wall time, when the cell is created.
    """
    cell = context.resources.get(RESOURCE_KEY, SimulatedCell)
    if cell is None:
        settings = context.sections.get(SECTION)
        config = settings if isinstance(settings, SimulationConfig) else SimulationConfig()
        cell = SimulatedCell(config.physics(), context.clock, truth_log=config.truth_log or None)
        if isinstance(context.clock, VirtualClock):
            cell.epoch = 0.0
        elif isinstance(context.clock, ScaledClock):
            cell.epoch = context.clock.start_unix_s
        context.resources.put(RESOURCE_KEY, cell)
    return cell


class SimulatedGroup(SensorGroup):
    def __init__(self, cell: SimulatedCell, configs: Sequence[SimulatedSensorConfig]) -> None:
        self.cell = cell
        self.set_channels(configs)
        self._sources = {c.name: c.source for c in configs}
        self._channels = tuple(dict.fromkeys(self._sources.values()))  # stable order: same noise per seed
        #: the channels whose truth the cell knows (its interferometers), by name
        self._positions = {name: source for name, source in self._sources.items() if cell.is_position(source)}
        self.timeout_s = max(c.timeout_s for c in configs)

    async def open(self) -> None:
        return None

    async def read(self) -> dict[str, Reading]:
        by_source = self.cell.read(self._channels)
        return {name: by_source[source] for name, source in self._sources.items()}

    async def close(self) -> None:
        return None

    def true_values(self) -> dict[str, float]:
        """The true attained position behind this group's last interferometer reading (temperatures: none)."""
        truth = {name: self.cell.true_reading(source) for name, source in self._positions.items()}
        return {name: value for name, value in truth.items() if value is not None}


class SimulatedActuator(Actuator):
    """Moves one axis of the simulated stage (its closed loop takes ``q_um``; the voltage is informational)."""

    def __init__(self, cell: SimulatedCell, axis: str) -> None:
        self.cell = cell
        self.axis = axis
        self.description = "simulated stage" + (f", axis {axis}" if len(cell.axes) > 1 else "")

    async def open(self) -> None:
        return None

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        self.cell.command(self.axis, q_um)

    async def close(self) -> None:
        return None

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        """The setpoint the stage's closed loop holds (0 µm on a fresh cell): the first ramp starts there."""
        return ("q_um", self.cell.states[self.axis].q)


class SimulatedPlugin(VirtualCellPlugin):
    name = PLUGIN_KIND
    config_model: ClassVar[type[SensorConfig]] = SimulatedSensorConfig
    section = SECTION
    section_model = SimulationConfig
    actuator_model = SimulatedActuatorConfig

    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]:
        cell = shared_cell(context)
        groups: list[SensorGroup] = []
        temps: dict[tuple[float, float], list[SimulatedSensorConfig]] = {}
        for c in (as_config(c, SimulatedSensorConfig) for c in configs):
            if c.source not in cell.channels:
                raise DriverSetupError(
                    f"sensor {c.name}: no simulated channel {c.source!r}; set channel to one of "
                    f"{', '.join(cell.channels)}")
            if cell.is_position(c.source) != (c.role == "position"):
                expected = "position" if cell.is_position(c.source) else "temperature"
                raise DriverSetupError(
                    f"sensor {c.name}: simulated channel {c.source} has role {expected}, not {c.role}")
            if c.role == "position":
                groups.append(SimulatedGroup(cell, [c]))
            else:
                temps.setdefault((c.interval_s, c.timeout_s), []).append(c)
        groups.extend(SimulatedGroup(cell, same) for same in temps.values())
        return groups

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        cell = shared_cell(context)
        if len(cell.axes) > 1:
            raise DriverSetupError(f"the simulated cell has axes {', '.join(cell.axes)}: one output per axis "
                                   "([[axes]] with [axes.actuator] kind = \"simulated\")")
        return SimulatedActuator(cell, cell.axes[0])

    def create_actuators(self, configs: Sequence[ActuatorOptions], context: DriverContext) -> list[Actuator]:
        """One output per axis of the stacked stage, the config's axes (``context.axes``) being its axes."""
        cell = shared_cell(context)
        if len(cell.axes) == 1:
            raise DriverSetupError(f"the config has axes {', '.join(context.axes)} but the simulated cell has one: "
                                   'set [simulation] axes = "' + "".join(context.axes) + '"')
        if sorted(context.axes) != sorted(cell.axes) or len(configs) != len(cell.axes):
            raise DriverSetupError(f"the config's axes ({', '.join(context.axes)}) are not the simulated cell's "
                                   f"([simulation] axes = \"{''.join(cell.axes)}\"): name the [[axes]] "
                                   f"{', '.join(cell.axes)}")
        return [SimulatedActuator(cell, axis) for axis in context.axes]

    def default_sensors(self, section: BaseModel) -> list[SensorConfig]:
        config = section if isinstance(section, SimulationConfig) else SimulationConfig()
        return list(default_sensor_configs(config.axis_names, speed=config.speed))

    def default_sensor_axes(self, section: BaseModel) -> dict[str, str]:
        config = section if isinstance(section, SimulationConfig) else SimulationConfig()
        return position_channels(config.axis_names) if config.axes else {}

    def default_axes(self, section: BaseModel) -> list[dict[str, Any]]:
        """``[[axes]]`` of the stacked stage: each 0..480 µm (the paper's travel) on a simulated output."""
        config = section if isinstance(section, SimulationConfig) else SimulationConfig()
        if not config.axes:
            return []
        return [{"name": axis, "min_um": 0.0, "max_um": DEFAULT_AXIS_MAX_UM, "actuator": {"kind": PLUGIN_KIND}}
                for axis in config.axis_names]

    def timing_warnings(self, section: BaseModel | None, sensors: Sequence[tuple[int, SensorConfig]]) -> list[str]:
        """Sensors (of any kind: the whole daemon runs on the cell's clock) too fast for ``speed``."""
        config = section if isinstance(section, SimulationConfig) else SimulationConfig()
        return config.timing_warnings(sensors)

    def make_clock(self, section: BaseModel | None, *, virtual_start_s: float | None = None) -> Clock:
        if virtual_start_s is not None:
            return VirtualClock(virtual_start_s)
        speed = section.speed if isinstance(section, SimulationConfig) else 1.0
        if speed == 1.0:
            return MonotonicClock()
        # the simulated lab's clock starts at the last UTC midnight, with the scenario: its day k is the
        # scenario's day k and the recorder's k-th day file (the ``week`` scenario's Monday is day 0)
        now = time.time()
        return ScaledClock(speed, start=now - now % 86400.0)

    def label_clock(self, clock: Clock) -> Callable[[], float]:
        """A scaled clock labels its own records: it reads unix seconds from the last UTC midnight on, ``speed``
        times faster, so the recorder's day files are the simulated lab's days (a simulated week: 7 files)."""
        return clock.now if isinstance(clock, ScaledClock) else time.time


PLUGIN = SimulatedPlugin()


def default_sensor_configs(axes: Sequence[str] = ("x",), interferometer_interval_s: float = 0.1,
                           thermocouple_interval_s: float = 0.5, *, speed: float = 1.0) -> list[SimulatedSensorConfig]:
    """The paper's cell: T1..T4 and an interferometer per axis (what a config with no sensors runs).

    On a fast clock the intervals and ages grow to what the daemon serves at ``speed`` (in cell seconds:
    :attr:`SimulationConfig.min_interval_s`, :attr:`SimulationConfig.min_max_age_s`): the paper's 0.5 s
    and 5 s at speed 10000 are 50 µs and 0.5 ms of wall time, which no poller keeps.
    """
    limits = SimulationConfig(speed=speed)
    tc_interval_s = max(thermocouple_interval_s, limits.min_interval_s)
    position_interval_s = max(interferometer_interval_s, limits.min_interval_s)
    temps = [SimulatedSensorConfig(name=n, role="temperature", interval_s=tc_interval_s,
                                   max_age_s=max(5.0, limits.min_max_age_s, 3 * tc_interval_s))
             for n in ("T1", "T2", "T3", "T4")]
    beams = [SimulatedSensorConfig(name=channel, role="position", interval_s=position_interval_s,
                                   max_age_s=max(1.0, limits.min_max_age_s, 3 * position_interval_s))
             for channel in position_channels(tuple(axes))]
    return [*temps, *beams]
