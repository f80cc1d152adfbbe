"""Plugin dispatch: which plugin validates which part of the document, and the checks across them.

Validation runs in two passes so every message names its field path: first the daemon's own tables
(:mod:`nanodrift.settings`), then each ``[[sensors]]`` entry with the pydantic model of the driver
plugin its ``kind`` names (a lab's own driver validates its own keys). ``[actuator]`` is split the
same way: the core keys (gain, limits, motion) by :class:`~nanodrift.settings.ActuatorConfig`, the
device keys by the ``actuator_model`` of the plugin its ``kind`` names; ``[[hubs]]`` by the plugin of
the sensors that use them; a top-level table by the plugin owning it
(:func:`nanodrift.drivers.registry.owner_of_section`). Every problem is collected, then all are raised together
as one :class:`~nanodrift.config._lines.ConfigError`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from nanodrift.config._checks import points_problems, valid_range_problems
from nanodrift.config._lines import ConfigError, problems_of, sensor_where
from nanodrift.drivers.base import (
    ActuatorOptions,
    DriverPlugin,
    SensorConfig,
    VirtualCellPlugin,
    shared_output_problems,
)
from nanodrift.drivers.registry import (
    UnknownDriverError,
    available,
    load_plugin,
    owner_of_section,
    quietly,
    virtual_cell_plugin,
)
from nanodrift.settings import (
    BUILTIN_SOURCE,
    DATA_DIR,
    STATE_MODEL_PATH,
    ZENOH_KIND,
    ActuatorConfig,
    AxisConfig,
    AxisKeys,
    Config,
)

_Model = TypeVar("_Model", bound=BaseModel)


class _Parse:
    """One validation of a document: collects every problem instead of stopping at the first."""

    def __init__(self) -> None:
        self.problems: list[str] = []
        self._plugins: dict[str, DriverPlugin] = {}

    def plugin(self, kind: str, where: str) -> DriverPlugin | None:
        if kind in self._plugins:
            return self._plugins[kind]
        try:
            plugin = load_plugin(kind)
        except UnknownDriverError as error:
            self.problems.append(f"{where}: {error}")
            return None
        except Exception as error:  # a broken third-party plugin must not hide the other problems
            self.problems.append(f"{where}: driver {kind!r} failed to load: {error}")
            return None
        self._plugins[kind] = plugin
        return plugin

    def section_owner(self, name: str, kinds: Sequence[str]) -> str | None:
        """The kind owning top-level table ``name`` (:func:`nanodrift.drivers.registry.owner_of_section`); a plugin
        that fails to load is a problem at ``sensors`` (a kind in use) or at ``name``."""
        return owner_of_section(name, kinds, lambda kind: self.plugin(kind, "sensors" if kind in kinds else name))

    def validate(self, model: type[_Model], raw: Any, where: str) -> _Model | None:
        if not isinstance(raw, Mapping):
            self.problems.append(f"{where}: expected a table")
            return None
        try:
            return model.model_validate(dict(raw))
        except ValidationError as error:
            self.problems.extend(problems_of(where, error))
            return None


def _sensor_kinds(raw_sensors: Any) -> list[str]:
    if not isinstance(raw_sensors, list):
        return []
    kinds = [r.get("kind") for r in raw_sensors if isinstance(r, Mapping)]
    return list(dict.fromkeys(k for k in kinds if isinstance(k, str)))


def parse_config(data: Mapping[str, Any], source: str = BUILTIN_SOURCE, base_dir: Path | None = None) -> Config:
    """Validate a parsed TOML document; raise :class:`ConfigError` listing every problem.

    Sensors, hubs and plugin-owned tables are validated by their plugin. A document with no
    ``[[sensors]]`` is a cell without sensors (monitoring only), unless a virtual-cell plugin's
    table is present (``[simulation]``): then that plugin supplies the sensors.
    """
    if not isinstance(data, Mapping):
        raise ConfigError(source, ["(top level): expected a table"])
    data = dict(data)
    raw_sensors = data.pop("sensors", None)
    raw_hubs = data.pop("hubs", [])
    has_actuator = "actuator" in data
    raw_actuator = data.pop("actuator", {})
    raw_axes = data.pop("axes", None)
    parse = _Parse()
    kinds = _sensor_kinds(raw_sensors)

    sections: dict[str, BaseModel] = {}
    owners: dict[str, str] = {}  # section -> the kind owning it
    for name in [k for k in data if k not in Config.model_fields]:
        kind = parse.section_owner(name, kinds)
        owner = parse.plugin(kind, name) if kind is not None else None  # loaded by section_owner
        if kind is None or owner is None or owner.section_model is None:
            continue  # left in: Config reports it as an unknown key
        value = parse.validate(owner.section_model, data.pop(name), name)
        if value is not None:
            sections[name], owners[name] = value, kind

    implied_axes = False  # [[axes]] supplied by a virtual cell's table (``[simulation] axes = "xy"``)
    if raw_axes is None:
        for name, section in sections.items():
            owner = parse.plugin(owners[name], name)  # loaded when its section was validated
            if isinstance(owner, VirtualCellPlugin) and owner.default_axes(section):
                raw_axes, implied_axes = owner.default_axes(section), True

    config: Config | None
    try:
        config = Config.model_validate(data)
    except ValidationError as error:
        parse.problems.extend(problems_of("", error))
        config = None

    sensor_axes: dict[str, str] = {}
    sensors = _parse_sensors(parse, raw_sensors, sections, owners, sensor_axes)
    in_use = [*(s.kind for _, s in sensors), *owners.values()]  # each loaded above
    in_cell = virtual_cell_plugin(in_use, lambda kind: parse.plugin(kind, "sensors"))
    virtual_cell = in_cell is not None
    # the kind a simulated cell's [actuator] defaults to: the cell's own plugin when it moves the stage (no
    # other plugin is loaded: a daemon starts faster), else any installed virtual cell that can
    virtual_kind = None if in_cell is None else in_cell[0] if _moves_the_stage(in_cell[1]) else _virtual_kind()
    axes: list[AxisConfig] = []
    if raw_axes is None:
        actuator = _parse_actuator(parse, raw_actuator, virtual_kind)
        actuators = [("actuator", actuator)] if actuator is not None else []
    else:
        if has_actuator and implied_axes:
            axes_text = ", ".join(a["name"] for a in raw_axes)
            parse.problems.append(f"actuator: the simulated cell has axes {axes_text} (its [simulation] axes): each "
                                  "axis has its own output; remove [actuator] (or describe each axis with [[axes]] "
                                  "and its [axes.actuator])")
        elif has_actuator:
            keys = ", ".join(raw_actuator) if isinstance(raw_actuator, Mapping) else ""
            parse.problems.append(
                "actuator: a cell with [[axes]] has one actuator per axis: move the keys of [actuator]"
                + (f" ({keys})" if keys else "") + " into each axis' [axes.actuator] and remove [actuator]")
        axes = _parse_axes(parse, raw_axes, virtual_kind)
        actuators = [(f"{_axis_where(i, a.name)}.actuator", a.actuator) for i, a in enumerate(axes)]
        actuator = next((a.actuator for a in axes if a.name == "x"), None)
    axis_names = [a.name for a in axes]
    if raw_axes is not None and isinstance(raw_axes, list):  # an axis refused for its actuator is still an axis
        axis_names = [r["name"] for r in raw_axes if isinstance(r, Mapping) and isinstance(r.get("name"), str)]
    _sensor_axis_problems(parse, sensors, sensor_axes, axis_names)
    hubs = _parse_hubs(parse, raw_hubs, sensors, actuators=[
        (where, hub, a.kind) for where, a in actuators
        if a.options is not None and (hub := a.options.hub_name()) is not None])
    if config is not None and actuator is not None:
        parse.problems.extend(points_problems(config.procedure, actuator))
    for where, each in actuators:
        _check_across(parse, sensors, each, where)
    parse.problems.extend(shared_output_problems([(where, a.options) for where, a in actuators
                                                  if a is not None and a.options is not None]))
    for axis_actuator, mine in _sensors_by_workspace(sensors, sensor_axes, axes, actuator):
        for problem in valid_range_problems(mine, axis_actuator):
            if problem not in parse.problems:
                parse.problems.append(problem)

    if parse.problems:
        raise ConfigError(source, parse.problems)
    assert config is not None and actuator is not None
    base = base_dir or Path.cwd()
    updates: dict[str, Any] = {"sensors": [sensor for _, sensor in sensors], "hubs": hubs, "actuator": actuator,
                               "axes": axes}
    if "path" not in config.model.model_fields_set and not virtual_cell:
        # the package's model belongs to the simulated cell: real hardware gets its own, calibrated one
        updates["model"] = config.model.model_copy(update={"path": STATE_MODEL_PATH})
    elif "path" not in config.model.model_fields_set and axes:
        # the simulated stacked stage's own shipped model (fitted on it: daemon/data/default_model_xy.json)
        shipped = DATA_DIR / f"default_model_{''.join(a.name for a in axes)}.json"
        if shipped.is_file():
            updates["model"] = config.model.model_copy(update={"path": shipped})
    elif not config.model.path.is_absolute():
        updates["model"] = config.model.model_copy(update={"path": (base / config.model.path).resolve()})
    record_dir = config.health.record_dir
    if record_dir and not Path(record_dir).is_absolute():
        updates["health"] = config.health.model_copy(update={"record_dir": str((base / record_dir).resolve())})
    zfile = config.zenoh.config_file
    if zfile is not None and not zfile.is_absolute():
        updates["zenoh"] = config.zenoh.model_copy(update={"config_file": (base / zfile).resolve()})
    result = config.model_copy(update=updates)
    result._source = source
    result._sections = sections
    result._virtual_cell = virtual_cell
    result._sensor_axes = {name: axis for name, axis in sensor_axes.items() if axis != "x"}
    return result


def _sensor_axis_problems(parse: _Parse, sensors: Sequence[tuple[int, SensorConfig]], sensor_axes: Mapping[str, str],
                          axes: Sequence[str]) -> None:
    """``[[sensors]] axis``: a known axis, on a position sensor only, and one position sensor per axis."""
    names = set(axes) or {"x"}
    by_axis: dict[str, list[str]] = {}
    for index, sensor in sensors:
        axis = sensor_axes.get(sensor.name, "x")
        if axis not in names:
            parse.problems.append(f"{sensor_where(index, sensor)}.axis: unknown axis {axis!r}; the cell's axes: "
                                  f"{', '.join(axes) or 'x (a one-axis cell)'}")
        elif sensor.role != "position" and sensor.name in sensor_axes:
            parse.problems.append(f"{sensor_where(index, sensor)}.axis: only a position sensor (role = "
                                  "\"position\") measures an axis")
        if sensor.role == "position":
            by_axis.setdefault(axis, []).append(sensor.name)
    for axis, positions in by_axis.items():
        if len(positions) > 1:
            parse.problems.append(
                f"sensors: more than one position sensor ({', '.join(positions)})"
                + ("; the cell has one axis" if not axes else f" on axis {axis} (one per axis: set axis = ...)"))


def _sensors_by_workspace(sensors: Sequence[tuple[int, SensorConfig]], sensor_axes: Mapping[str, str],
                          axes: Sequence[AxisConfig], actuator: ActuatorConfig | None,
                          ) -> list[tuple[ActuatorConfig, list[tuple[int, SensorConfig]]]]:
    """Which workspace judges each sensor's default valid range: its axis' for a position sensor."""
    if not axes:
        return [(actuator, list(sensors))] if actuator is not None else []
    out = []
    for axis in axes:
        mine = [(i, s) for i, s in sensors
                if (s.role != "position" and axis.name == "x")
                or (s.role == "position" and sensor_axes.get(s.name, "x") == axis.name)]
        out.append((axis.actuator, mine))
    return out


def _actuator_kinds() -> list[str]:
    """Every ``[actuator] kind`` this installation offers (for messages)."""
    return [ZENOH_KIND, *(kind for kind in sorted(available()) if _moves_the_stage(quietly(kind)))]


def _moves_the_stage(plugin: DriverPlugin | None) -> bool:
    """A plugin with an ``actuator_model`` (None: it failed to load; it is reported where it is used)."""
    return plugin is not None and plugin.actuator_model is not None


def _parse_actuator(parse: _Parse, raw: Any, virtual_kind: str | None,
                    where: str = "actuator") -> ActuatorConfig | None:
    """``[actuator]``: the core keys by :class:`ActuatorConfig`, the rest by the kind's plugin.

    The default kind is the virtual cell's own plugin for a simulated cell (its stage must move),
    else ``zenoh``. A simulated stage is never driven by a hardware output, nor the reverse.
    ``virtual_kind``: the simulated cell's plugin that moves its stage, None for a real cell.
    """
    virtual_cell = virtual_kind is not None
    if not isinstance(raw, Mapping):
        parse.problems.append(f"{where}: expected a table")
        return None
    core = {k: v for k, v in raw.items() if k in ActuatorConfig.model_fields}
    rest = {k: v for k, v in raw.items() if k not in ActuatorConfig.model_fields}
    if "kind" not in core:
        core["kind"] = virtual_kind or ZENOH_KIND
    kind = core["kind"]
    actuator = parse.validate(ActuatorConfig, core, where)
    if not isinstance(kind, str):
        return None  # reported by the line above
    options: ActuatorOptions | None = None
    if kind == ZENOH_KIND:
        parse.problems.extend(f"{where}.{key}: unknown key (typo?); kind = {ZENOH_KIND!r} takes no device keys"
                              for key in rest)
        if virtual_cell:
            parse.problems.append(f"{where}.kind: {ZENOH_KIND!r} would leave the simulated stage unmoved; a simulated "
                                  "cell is driven by its own plugin (remove kind)")
    elif kind not in available():
        parse.problems.append(f"{where}.kind: unknown actuator kind {kind!r}; kinds: {', '.join(_actuator_kinds())}")
    else:
        plugin = parse.plugin(kind, f"{where}.kind")
        if plugin is None:
            return None
        if plugin.actuator_model is None:
            parse.problems.append(f"{where}.kind: driver {kind!r} cannot move the stage; kinds that can: "
                                  f"{', '.join(_actuator_kinds())}")
            return None
        if isinstance(plugin, VirtualCellPlugin) != virtual_cell:
            cell = "simulated" if virtual_cell else "real hardware"
            parse.problems.append(f"{where}.kind: {kind!r} cannot drive this cell: its sensors are {cell}")
        validated = parse.validate(plugin.actuator_model, {**rest, "kind": kind}, where)
        options = validated if isinstance(validated, ActuatorOptions) else None
        if options is not None and actuator is not None:
            problem = options.voltage_range_problem(actuator.v_min, actuator.v_max, actuator.volts_per_um)
            if problem:
                parse.problems.append(actuator_line(options, problem, where))
    return actuator.with_options(options) if actuator is not None else None


def actuator_line(options: ActuatorOptions, message: str, where: str = "actuator") -> str:
    """``actuator.command: ...`` for a plugin's message that starts with one of its keys, else ``actuator: ...``."""
    key = message.split(":", 1)[0]
    return f"{where}.{message}" if key in type(options).model_fields else f"{where}: {message}"


def _axis_where(index: int, name: Any) -> str:
    """``axes[1] (y)``: the index in the file's order (0-based) and the axis' name when it has one."""
    return f"axes[{index}] ({name})" if isinstance(name, str) and name else f"axes[{index}]"


#: ``[axes.actuator]`` keys that belong to the axis itself
_WORKSPACE_KEYS = {"x_min_um": "min_um", "x_max_um": "max_um"}


def _parse_axes(parse: _Parse, raw_axes: Any, virtual_kind: str | None) -> list[AxisConfig]:
    """``[[axes]]``: each axis' name and workspace, and its ``[axes.actuator]`` validated as an ``[actuator]``
    (the workspace is the axis'). Names are unique; an x axis is required (the CSV contract's positions)."""
    if not isinstance(raw_axes, list) or not raw_axes:
        parse.problems.append("axes: expected an array of tables ([[axes]]), one per axis")
        return []
    axes: list[AxisConfig] = []
    seen: set[str] = set()
    for index, raw in enumerate(raw_axes):
        where = _axis_where(index, raw.get("name") if isinstance(raw, Mapping) else None)
        if not isinstance(raw, Mapping):
            parse.problems.append(f"{where}: expected a table")
            continue
        raw = dict(raw)
        raw_actuator = raw.pop("actuator", {})
        keys = parse.validate(AxisKeys, raw, where)
        if isinstance(raw_actuator, Mapping):
            for key, instead in _WORKSPACE_KEYS.items():
                if key in raw_actuator:
                    parse.problems.append(f"{where}.actuator.{key}: the axis' workspace is its own {instead} "
                                          "(in [[axes]], not in [axes.actuator])")
            raw_actuator = {k: v for k, v in raw_actuator.items() if k not in _WORKSPACE_KEYS}
            if keys is not None:
                raw_actuator = {**raw_actuator, "x_min_um": keys.min_um, "x_max_um": keys.max_um}
        actuator = _parse_actuator(parse, raw_actuator, virtual_kind, f"{where}.actuator")
        if keys is None:
            continue
        if keys.name in seen:
            parse.problems.append(f"{where}.name: axis {keys.name!r} is named twice (axis names are unique)")
            continue
        seen.add(keys.name)
        if actuator is not None:
            axes.append(AxisConfig(name=keys.name, actuator=actuator))
    if len(raw_axes) == 1:
        parse.problems.append("axes: one [[axes]] table: a one-axis cell is written without [[axes]] (its "
                              "[actuator] table configures the x axis)")
    if seen and "x" not in seen:
        parse.problems.append(f"axes: no axis named x (axes: {', '.join(sorted(seen))}); a multi-axis cell needs "
                              "an x axis: the calibration CSV's positions start with x_um")
    return axes


def _virtual_kind() -> str:
    """The installed virtual-cell plugin that can move its stage (the simulated one)."""
    found = virtual_cell_plugin(_actuator_kinds()[1:], quietly)  # the kinds that move a stage, but zenoh
    return found[0] if found is not None else ZENOH_KIND


def _check_across(parse: _Parse, sensors: Sequence[tuple[int, SensorConfig]],
                  actuator: ActuatorConfig | None, where: str = "actuator") -> None:
    """Each plugin's :meth:`~nanodrift.drivers.base.DriverPlugin.config_problems` over its sensors and its actuator
    (once per axis' actuator in a multi-axis cell: a problem seen twice is listed once)."""
    options = actuator.options if actuator is not None else None
    kinds = dict.fromkeys([s.kind for _, s in sensors] + ([options.kind] if options is not None else []))
    for kind in kinds:
        plugin = parse._plugins.get(kind)  # loaded (or reported) where the entries were validated
        if plugin is None:
            continue
        mine = [(i, s) for i, s in sensors if s.kind == kind]
        for problem in plugin.config_problems(mine, options if options is not None and options.kind == kind
                                              else None):
            if where != "actuator" and problem.startswith("actuator"):
                problem = where + problem[len("actuator"):]
            if problem not in parse.problems:
                parse.problems.append(problem)


def _parse_sensors(parse: _Parse, raw_sensors: Any, sections: Mapping[str, BaseModel],
                   owners: Mapping[str, str], sensor_axes: dict[str, str]) -> list[tuple[int, SensorConfig]]:
    """Each ``[[sensors]]`` entry by its kind's plugin; ``axis`` (the daemon's key: which axis a position
    sensor measures) is taken out first into ``sensor_axes``."""
    indexed: list[tuple[int, SensorConfig]] = []
    if raw_sensors is None:  # a virtual cell's table without sensors: the plugin's own
        for name, section in sections.items():
            owner = parse.plugin(owners[name], name)  # loaded when its section was validated
            if isinstance(owner, VirtualCellPlugin):
                indexed.extend(enumerate(owner.default_sensors(section)))
                sensor_axes.update(owner.default_sensor_axes(section))
        return indexed
    if not isinstance(raw_sensors, list):
        parse.problems.append("sensors: expected an array of tables ([[sensors]])")
        return indexed
    for index, raw in enumerate(raw_sensors):
        prefix = sensor_where(index, raw)
        if not isinstance(raw, Mapping):
            parse.problems.append(f"{prefix}: expected a table")
            continue
        kind = raw.get("kind")
        if not isinstance(kind, str):
            parse.problems.append(f"{prefix}.kind: required: the driver kind (simulated, modbus, serial_line, ...)")
            continue
        plugin = parse.plugin(kind, f"{prefix}.kind")
        if plugin is None:
            continue
        raw = dict(raw)
        axis = raw.pop("axis", None)
        if axis is not None and not isinstance(axis, str):
            parse.problems.append(f"{prefix}.axis: expected an axis name (a lowercase letter), got {axis!r}")
            axis = None
        sensor = parse.validate(plugin.config_model, raw, prefix)
        if sensor is not None:
            indexed.append((index, sensor))
            if axis is not None:
                sensor_axes[sensor.name] = axis

    seen: set[str] = set()
    for index, sensor in indexed:
        if sensor.name in seen:
            parse.problems.append(
                f"{sensor_where(index, sensor)}.name: {sensor.name!r} is used twice (names must be unique)")
        seen.add(sensor.name)
    return indexed


def _parse_hubs(parse: _Parse, raw_hubs: Any, sensors: Sequence[tuple[int, SensorConfig]], *,
                actuators: Sequence[tuple[str, str, str]] = ()) -> list[Any]:
    """Each ``[[hubs]]`` entry validated by the plugin of the sensors (and the actuators) that name it.

    ``actuators``: (where, hub, kind) of each actuator naming a hub: a user of that hub like a sensor.
    """
    if not isinstance(raw_hubs, list):
        parse.problems.append("hubs: expected an array of tables ([[hubs]])")
        return []
    names = [h.get("name") if isinstance(h, Mapping) else None for h in raw_hubs]
    for twice in sorted({n for n in names if isinstance(n, str) and names.count(n) > 1}):
        parse.problems.append(f"hubs: name {twice!r} is used twice")
    users: dict[str, list[str]] = {}  # hub -> the kinds using it, in the order they name it
    sensor_users = [(sensor_where(index, sensor), hub, sensor.kind) for index, sensor in sensors
                    if (hub := sensor.hub_name()) is not None]
    for where, hub, kind in [*sensor_users, *actuators]:
        if hub not in names:
            known = ", ".join(n for n in names if isinstance(n, str)) or "none defined"
            parse.problems.append(f"{where}.hub: no [[hubs]] named {hub!r} (hubs: {known})")
        if kind not in users.setdefault(hub, []):
            users[hub].append(kind)
    hubs: list[Any] = []
    for index, (raw, name) in enumerate(zip(raw_hubs, names, strict=True)):
        where = f"hubs[{index}]"
        if not isinstance(name, str):
            parse.problems.append(f"{where}.name: required: the name sensors give as hub = ...")
            continue
        where = f"hubs[{index}] ({name})"
        if name not in users:
            parse.problems.append(f"{where}: no sensor uses this hub (set hub = {name!r} on one, or remove"
                                  " the hub)")
            continue
        for kind in users[name]:
            plugin = parse.plugin(kind, where)
            if plugin is None or plugin.hub_model is None:
                parse.problems.append(f"{where}: driver {kind!r} takes no hubs")
                continue
            entry = parse.validate(plugin.hub_model, raw, where)
            if entry is not None and kind == users[name][0]:
                hubs.append(entry)
    return hubs
