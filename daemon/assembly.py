"""The one place where a validated config becomes running driver objects.

Plugins are found by kind through the ``nanodrift.drivers`` entry points; nothing here names one.
The daemon gets :func:`build_drivers` handed in by ``nanodrift run`` (the service never imports
this module), the procedures get :func:`procedure_drivers`. The actuator comes from the plugin that
``[actuator] kind`` names; ``kind = "zenoh"`` is the core's: the daemon's published ``command`` is
the actuation (no actuator object), a procedure publishes its steps with :class:`ZenohActuator`.
A virtual cell (the simulated plugin) supplies its own clock: scaled wall time for the daemon, a
virtual clock for procedures, so a four-hour calibration takes seconds.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping
from typing import Any

from pydantic import BaseModel

from nanodrift.bus.actuator import ZenohActuator
from nanodrift.config import ZENOH_KIND, Config, parse_config
from nanodrift.drivers.base import (
    Actuator,
    Clock,
    DriverContext,
    DriverPlugin,
    DriverSetupError,
    MonotonicClock,
    SensorGroup,
    shared_output_problems,
)
from nanodrift.drivers.registry import load_plugin, owner_of_section, virtual_cell_plugin
from nanodrift.drivers_set import DriverSet
from nanodrift.output_record import OutputRecords, state_directory


def _plugins(config: Config) -> dict[str, DriverPlugin]:
    """Every plugin the config involves: its sensors' kinds, its actuator's and the owners of its sections."""
    plugins = {kind: load_plugin(kind) for kind in dict.fromkeys(s.kind for s in config.sensors)}
    for actuator in config.axis_actuators().values():
        if actuator.kind != ZENOH_KIND:
            plugins.setdefault(actuator.kind, load_plugin(actuator.kind))
    for name in config.sections:
        owner = owner_of_section(name, plugins)
        if owner is not None:
            plugins.setdefault(owner, load_plugin(owner))
    return plugins


def make_context(config: Config, *, virtual_start_s: float | None = None) -> DriverContext:
    """The clock, hubs and plugin sections the plugins share."""
    clock: Clock = MonotonicClock()
    label_clock: Callable[[], float] = time.time  # the wall clock labels records
    plugins = _plugins(config)
    found = virtual_cell_plugin(plugins, plugins.get)
    if found is not None:
        _, cell = found
        section: BaseModel | None = config.section(cell.section) if cell.section else None
        clock = cell.make_clock(section, virtual_start_s=virtual_start_s)
        label_clock = cell.label_clock(clock)
    return DriverContext(clock=clock, label_clock=label_clock, hubs={h.name: h for h in config.hubs},
                         sections=config.sections, axes=config.axis_names)


def build_drivers(config: Config, context: DriverContext | None = None, *,
                  virtual_start_s: float | None = None) -> DriverSet:
    """Sensor groups and each axis' output of ``config`` (from the plugin its actuator's ``kind`` names).

    ``context``: reuse a running one (a reload that keeps the simulated cell keeps its state).
    An axis with ``kind = "zenoh"`` has no output object: the daemon's own ``command`` publication is what
    the lab's output node applies. Raises :class:`DriverSetupError` naming the kind when a plugin
    refuses its sensors or its actuator.
    """
    context = context or make_context(config, virtual_start_s=virtual_start_s)
    groups: list[SensorGroup] = []
    plugins = _plugins(config)
    for kind, plugin in plugins.items():
        configs = [s for s in config.sensors if s.kind == kind]
        try:
            if configs:
                groups.extend(plugin.create(configs, context))
        except Exception as error:
            raise DriverSetupError(f"driver {kind!r}: {error}") from error
    actuators = _axis_actuators(config, plugins, context)  # after the sensors: they share their connections
    description = "simulated cell" if config.virtual_cell else "hardware"
    return DriverSet(
        context=context,
        groups=groups,
        roles={s.name: s.role for s in config.sensors},
        max_age_s={s.name: s.max_age_s for s in config.sensors},
        description=description,
        actuators=actuators,
        position_axes={config.sensor_axis(s.name): s.name for s in config.sensors if s.role == "position"},
    )


def _axis_actuators(config: Config, plugins: Mapping[str, DriverPlugin], context: DriverContext) -> dict[str, Actuator]:
    """Each axis' output (a one-axis cell's: ``x``), built by kind (:meth:`DriverPlugin.create_actuators`: the
    axes of one module or controller share its connection); a ``kind = "zenoh"`` axis has none."""
    configs = config.axis_actuators()
    shared = shared_output_problems([(f"axis {axis}", a.options) for axis, a in configs.items()
                                     if a.options is not None])
    if shared:  # refused when the config was read; a Config built otherwise is refused here all the same
        raise DriverSetupError("; ".join(shared))
    by_kind: dict[str, list[str]] = {}
    for axis, actuator in configs.items():
        if actuator.kind != ZENOH_KIND:
            by_kind.setdefault(actuator.kind, []).append(axis)
    built: dict[str, Actuator] = {}
    for kind, axes in by_kind.items():
        options = [configs[a].options for a in axes]
        try:
            if any(o is None for o in options):
                raise DriverSetupError("the actuator section was not validated by its plugin (use parse_config)")
            checked = [o for o in options if o is not None]
            plugin = plugins[kind]  # a one-axis cell's [actuator] is what create_actuator builds
            made = plugin.create_actuators(checked, context) if config.multi_axis else [
                plugin.create_actuator(checked[0], context)]
        except Exception as error:
            raise DriverSetupError(f"actuator kind {kind!r} (axis {', '.join(axes)}): {error}") from error
        built.update(zip(axes, made, strict=True))
    return {axis: built[axis] for axis in config.axis_names if axis in built}


def procedure_drivers(config: Config, *, start_s: float = 0.0) -> DriverSet:
    """What a calibration or validation drives: the config's drivers, a virtual clock for a simulated
    cell (scenario time ``start_s``). Every axis needs its own position sensor; with ``kind = "zenoh"`` a
    one-axis cell's steps are published on ``nanodrift/<cell>/command`` by :class:`ZenohActuator` for the
    lab's output node, while a multi-axis procedure drives each axis' own output (the Zenoh command of
    several axes is the daemon's)."""
    published = [axis for axis, actuator in config.axis_actuators().items() if actuator.kind == ZENOH_KIND]
    if published and config.multi_axis:
        raise DriverSetupError(f"axis {', '.join(published)}: [axes.actuator] kind = \"zenoh\" has no output a "
                               "procedure can drive; a multi-axis calibration drives each axis' own output "
                               "(kind = \"modbus\", \"serial_line\", ...)")
    drivers = build_drivers(config, virtual_start_s=start_s if config.virtual_cell else None)
    unmeasured = [axis for axis in config.axis_names if axis not in drivers.position_axes]
    if unmeasured:
        raise DriverSetupError(f"axis {', '.join(unmeasured)} has no position sensor (role = \"position\" on that "
                               "axis); a procedure measures every axis")
    if config.virtual_cell:
        drivers.description = "simulated cell (virtual clock)"
        return drivers
    # what the procedure writes to each output, where the daemon looks at its next start
    drivers.records = OutputRecords(state_directory(config.daemon.state_dir), config.cell)
    if published:
        zenoh = ZenohActuator(config)
        drivers.actuators = {published[0]: zenoh}
        drivers.description = f"hardware; stage commands published on {zenoh.key}"
    else:
        outputs = [f"{axis}: {actuator.description}" for axis, actuator in drivers.actuators.items()]
        drivers.description = "hardware; stage driven by " + (
            ", ".join(outputs) if config.multi_axis else f"the {drivers.actuators[config.axis_names[0]].description}")
    return drivers


def simulated_drivers(scenario: str = "train", effects: object = None, seed: int = 0, *, start_s: float = 0.0,
                      params: Mapping[str, float] | None = None, cell: str = "ideal") -> DriverSet:
    """The paper's cell, simulated, for a procedure: a virtual clock starting at scenario time ``start_s``;
    ``cell``: ``ideal`` or ``realistic`` (``[simulation] cell``)."""
    settings: dict[str, Any] = {"scenario": scenario, "seed": seed}
    if cell != "ideal":  # the ideal cell's config stays as it was
        settings["cell"] = cell
    if effects:
        settings["effects"] = effects if not isinstance(effects, str) else [effects]
    if params:
        settings["params"] = dict(params)
    return procedure_drivers(parse_config({"simulation": settings}, source="<simulated cell>"), start_s=start_s)
