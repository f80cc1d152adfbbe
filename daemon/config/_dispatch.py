"""Plugin dispatch: which plugin validates which part of the document, and the checks across them.

Validation runs in two passes so every message names its field path: first the daemon's own tables
(:mod:`daemon.settings`), then each ``[[sensors]]`` entry with the pydantic model of the driver
plugin its ``kind`` names (a lab's own driver validates its own keys). ``[actuator]`` is split the
same way: the core keys (gain, limits, motion) by :class:`~daemon.settings.ActuatorConfig`, the
device keys by the ``actuator_model`` of the plugin its ``kind`` names; ``[[hubs]]`` by the plugin of
the sensors that use them; a top-level table by the plugin owning it
(:func:`drivers.registry.owner_of_section`). Every problem is collected, then all are raised together
as one :class:`~daemon.config._lines.ConfigError`.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, TypeVar

from pydantic import BaseModel, ValidationError

from daemon.config._checks import points_problems, valid_range_problems
from daemon.config._lines import ConfigError, problems_of, sensor_where
from daemon.settings import BUILTIN_SOURCE, STATE_MODEL_PATH, ZENOH_KIND, ActuatorConfig, Config
from drivers.base import ActuatorOptions, DriverPlugin, SensorConfig, VirtualCellPlugin
from drivers.registry import (
    UnknownDriverError,
    available,
    load_plugin,
    owner_of_section,
    quietly,
    virtual_cell_plugin,
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
        """The kind owning top-level table ``name`` (:func:`drivers.registry.owner_of_section`); a plugin
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
    raw_actuator = data.pop("actuator", {})
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

    config: Config | None
    try:
        config = Config.model_validate(data)
    except ValidationError as error:
        parse.problems.extend(problems_of("", error))
        config = None

    sensors = _parse_sensors(parse, raw_sensors, sections, owners)
    in_use = [*(s.kind for _, s in sensors), *owners.values()]  # each loaded above
    virtual_cell = virtual_cell_plugin(in_use, lambda kind: parse.plugin(kind, "sensors")) is not None
    actuator = _parse_actuator(parse, raw_actuator, virtual_cell)
    hub_user = actuator.options.hub_name() if actuator is not None and actuator.options is not None else None
    hubs = _parse_hubs(parse, raw_hubs, sensors,
                       actuator=(hub_user, actuator.kind) if actuator is not None and hub_user is not None else None)
    if config is not None and actuator is not None:
        parse.problems.extend(points_problems(config.procedure, actuator))
    _check_across(parse, sensors, actuator)
    if actuator is not None:
        parse.problems.extend(valid_range_problems(sensors, actuator))

    if parse.problems:
        raise ConfigError(source, parse.problems)
    assert config is not None and actuator is not None
    base = base_dir or Path.cwd()
    updates: dict[str, Any] = {"sensors": [sensor for _, sensor in sensors], "hubs": hubs, "actuator": actuator}
    if "path" not in config.model.model_fields_set and not virtual_cell:
        # the package's model belongs to the simulated cell: real hardware gets its own, calibrated one
        updates["model"] = config.model.model_copy(update={"path": STATE_MODEL_PATH})
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
    return result


def _actuator_kinds() -> list[str]:
    """Every ``[actuator] kind`` this installation offers (for messages)."""
    return [ZENOH_KIND, *(kind for kind in sorted(available()) if _moves_the_stage(quietly(kind)))]


def _moves_the_stage(plugin: DriverPlugin | None) -> bool:
    """A plugin with an ``actuator_model`` (None: it failed to load; it is reported where it is used)."""
    return plugin is not None and plugin.actuator_model is not None


def _parse_actuator(parse: _Parse, raw: Any, virtual_cell: bool) -> ActuatorConfig | None:
    """``[actuator]``: the core keys by :class:`ActuatorConfig`, the rest by the kind's plugin.

    The default kind is the virtual cell's own plugin for a simulated cell (its stage must move),
    else ``zenoh``. A simulated stage is never driven by a hardware output, nor the reverse.
    """
    if not isinstance(raw, Mapping):
        parse.problems.append("actuator: expected a table")
        return None
    core = {k: v for k, v in raw.items() if k in ActuatorConfig.model_fields}
    rest = {k: v for k, v in raw.items() if k not in ActuatorConfig.model_fields}
    if "kind" not in core:
        core["kind"] = _virtual_kind() if virtual_cell else ZENOH_KIND
    kind = core["kind"]
    actuator = parse.validate(ActuatorConfig, core, "actuator")
    if not isinstance(kind, str):
        return None  # reported by the line above
    options: ActuatorOptions | None = None
    if kind == ZENOH_KIND:
        parse.problems.extend(f"actuator.{key}: unknown key (typo?); kind = {ZENOH_KIND!r} takes no device keys"
                              for key in rest)
        if virtual_cell:
            parse.problems.append(f"actuator.kind: {ZENOH_KIND!r} would leave the simulated stage unmoved; a simulated "
                                  "cell is driven by its own plugin (remove kind)")
    elif kind not in available():
        parse.problems.append(f"actuator.kind: unknown actuator kind {kind!r}; kinds: {', '.join(_actuator_kinds())}")
    else:
        plugin = parse.plugin(kind, "actuator.kind")
        if plugin is None:
            return None
        if plugin.actuator_model is None:
            parse.problems.append(f"actuator.kind: driver {kind!r} cannot move the stage; kinds that can: "
                                  f"{', '.join(_actuator_kinds())}")
            return None
        if isinstance(plugin, VirtualCellPlugin) != virtual_cell:
            cell = "simulated" if virtual_cell else "real hardware"
            parse.problems.append(f"actuator.kind: {kind!r} cannot drive this cell: its sensors are {cell}")
        validated = parse.validate(plugin.actuator_model, {**rest, "kind": kind}, "actuator")
        options = validated if isinstance(validated, ActuatorOptions) else None
        if options is not None and actuator is not None:
            problem = options.voltage_range_problem(actuator.v_min, actuator.v_max, actuator.volts_per_um)
            if problem:
                parse.problems.append(actuator_line(options, problem))
    return actuator.with_options(options) if actuator is not None else None


def actuator_line(options: ActuatorOptions, message: str) -> str:
    """``actuator.command: ...`` for a plugin's message that starts with one of its keys, else ``actuator: ...``."""
    key = message.split(":", 1)[0]
    return f"actuator.{message}" if key in type(options).model_fields else f"actuator: {message}"


def _virtual_kind() -> str:
    """The installed virtual-cell plugin that can move its stage (the simulated one)."""
    movers = [kind for kind in sorted(available()) if _moves_the_stage(quietly(kind))]
    found = virtual_cell_plugin(movers, quietly)
    return found[0] if found is not None else ZENOH_KIND


def _check_across(parse: _Parse, sensors: Sequence[tuple[int, SensorConfig]],
                  actuator: ActuatorConfig | None) -> None:
    """Each plugin's :meth:`~drivers.base.DriverPlugin.config_problems` over its sensors and its actuator."""
    options = actuator.options if actuator is not None else None
    kinds = dict.fromkeys([s.kind for _, s in sensors] + ([options.kind] if options is not None else []))
    for kind in kinds:
        plugin = parse._plugins.get(kind)  # loaded (or reported) where the entries were validated
        if plugin is None:
            continue
        mine = [(i, s) for i, s in sensors if s.kind == kind]
        parse.problems.extend(plugin.config_problems(mine, options if options is not None and options.kind == kind
                                                     else None))


def _parse_sensors(parse: _Parse, raw_sensors: Any, sections: Mapping[str, BaseModel],
                   owners: Mapping[str, str]) -> list[tuple[int, SensorConfig]]:
    indexed: list[tuple[int, SensorConfig]] = []
    if raw_sensors is None:  # a virtual cell's table without sensors: the plugin's own
        for name, section in sections.items():
            owner = parse.plugin(owners[name], name)  # loaded when its section was validated
            if isinstance(owner, VirtualCellPlugin):
                indexed.extend(enumerate(owner.default_sensors(section)))
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
        sensor = parse.validate(plugin.config_model, raw, prefix)
        if sensor is not None:
            indexed.append((index, sensor))

    seen: set[str] = set()
    for index, sensor in indexed:
        if sensor.name in seen:
            parse.problems.append(
                f"{sensor_where(index, sensor)}.name: {sensor.name!r} is used twice (names must be unique)")
        seen.add(sensor.name)
    positions = [s.name for _, s in indexed if s.role == "position"]
    if len(positions) > 1:
        parse.problems.append(
            f"sensors: more than one position sensor ({', '.join(positions)}); the cell has one axis")
    return indexed


def _parse_hubs(parse: _Parse, raw_hubs: Any, sensors: Sequence[tuple[int, SensorConfig]], *,
                actuator: tuple[str, str] | None = None) -> list[Any]:
    """Each ``[[hubs]]`` entry validated by the plugin of the sensors (and the actuator) that name it.

    ``actuator``: (hub, kind) when ``[actuator]`` names a hub: it is a user of that hub like a sensor.
    """
    if not isinstance(raw_hubs, list):
        parse.problems.append("hubs: expected an array of tables ([[hubs]])")
        return []
    names = [h.get("name") if isinstance(h, Mapping) else None for h in raw_hubs]
    for twice in sorted({n for n in names if isinstance(n, str) and names.count(n) > 1}):
        parse.problems.append(f"hubs: name {twice!r} is used twice")
    users: dict[str, list[str]] = {}
    for index, sensor in sensors:
        hub = sensor.hub_name()
        if hub is None:
            continue
        if hub not in names:
            known = ", ".join(n for n in names if isinstance(n, str)) or "none defined"
            parse.problems.append(f"{sensor_where(index, sensor)}.hub: no [[hubs]] named {hub!r} (hubs: {known})")
        users.setdefault(hub, [])
        if sensor.kind not in users[hub]:
            users[hub].append(sensor.kind)
    if actuator is not None:
        hub, kind = actuator
        if hub not in names:
            known = ", ".join(n for n in names if isinstance(n, str)) or "none defined"
            parse.problems.append(f"actuator.hub: no [[hubs]] named {hub!r} (hubs: {known})")
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

