"""The operator's TOML config, validated by pydantic (the contract in ARCHITECTURE.md).

Validation runs in two passes so every message names its field path: first the daemon's own
sections, then each ``[[sensors]]`` entry with the pydantic model of the driver plugin its ``kind``
names (a lab's own driver validates its own keys). Unknown keys are errors everywhere: a typo must
never pass silently. Errors are collected and reported together, each as
``<file>: <path>: <what was expected>``.
"""

from __future__ import annotations

import math
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, field_validator, model_validator

from daemon.errors import UserError
from drivers.base import HubConfig, SensorConfig
from drivers.registry import UnknownDriverError, load_plugin
from drivers.simulated.config import SimulationConfig

DATA_DIR = Path(__file__).resolve().parent / "data"
DEFAULT_MODEL_PATH = DATA_DIR / "default_model.json"
BUILTIN_SOURCE = "<built-in default config>"


class ConfigError(UserError):
    """An invalid config; ``problems`` holds one ``path: message`` line per problem."""

    def __init__(self, source: str, problems: Sequence[str]) -> None:
        self.source = source
        self.problems = list(problems)
        lines = "\n".join(f"{source}: {p}" for p in self.problems)
        super().__init__(lines)


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class ZenohSettings(_Strict):
    """How the daemon joins the Zenoh network; ``-l/-e/--mode`` on the command line override it."""

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=list, description="endpoints, e.g. tcp/0.0.0.0:7447")
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = Field(default=True, description="find peers by UDP multicast")
    config_file: Path | None = Field(default=None, description="a zenoh json5 config used as the base")


class ModelSettings(_Strict):
    path: Path = Field(default=DEFAULT_MODEL_PATH, description="the model file (nanodrift-model/1)")


class ActuatorConfig(_Strict):
    """Command q (um) -> PZT voltage, and the limits nothing published may exceed."""

    volts_per_um: float = 0.02
    offset_v: float = 0.0
    v_min: float = -2.0
    v_max: float = 12.0
    x_min_um: float = 0.0
    x_max_um: float = 500.0

    @field_validator("*")
    @classmethod
    def _finite(cls, value: float) -> float:
        if not math.isfinite(value):
            raise ValueError("must be a finite number")
        return value

    @model_validator(mode="after")
    def _ordered(self) -> ActuatorConfig:
        if self.volts_per_um == 0:
            raise ValueError("volts_per_um must not be 0")
        if self.v_min >= self.v_max:
            raise ValueError(f"v_min ({self.v_min}) must be below v_max ({self.v_max})")
        if self.x_min_um >= self.x_max_um:
            raise ValueError(f"x_min_um ({self.x_min_um}) must be below x_max_um ({self.x_max_um})")
        return self

    def voltage(self, q_um: float) -> float:
        return self.offset_v + self.volts_per_um * q_um


class Config(_Strict):
    """The whole operator config. ``sensors`` hold each plugin's own validated config object."""

    cell: str = Field(default="cell0", pattern=r"^[A-Za-z0-9_\-]+$", description="key prefix nanodrift/<cell>")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    model: ModelSettings = Field(default_factory=ModelSettings)
    actuator: ActuatorConfig = Field(default_factory=ActuatorConfig)
    simulation: SimulationConfig = Field(default_factory=SimulationConfig)
    hubs: list[HubConfig] = Field(default_factory=list)
    sensors: list[SensorConfig] = Field(default_factory=list)
    #: where it came from (a file path, or the built-in default); not a TOML key
    _source: str = PrivateAttr(default=BUILTIN_SOURCE)

    @property
    def source(self) -> str:
        return self._source

    @property
    def key_prefix(self) -> str:
        return f"nanodrift/{self.cell}"

    def kinds(self) -> list[str]:
        """Driver kinds in use, in first-appearance order."""
        return list(dict.fromkeys(s.kind for s in self.sensors))

    def sensor(self, name: str) -> SensorConfig | None:
        return next((s for s in self.sensors if s.name == name), None)


def _loc(prefix: str, loc: Sequence[Any]) -> str:
    path = prefix
    for part in loc:
        if isinstance(part, int):
            path += f"[{part}]"
        else:
            path += f".{part}" if path else str(part)
    return path or "(top level)"


def _problems(prefix: str, error: ValidationError) -> list[str]:
    out = []
    for item in error.errors(include_url=False):
        message = item["msg"]
        if item["type"] == "extra_forbidden":
            message = "unknown key (typo?)"
        out.append(f"{_loc(prefix, item['loc'])}: {message}")
    return out


def default_simulated_sensors() -> list[dict[str, Any]]:
    """The simulated cell's channels (four thermocouples, the interferometer), as TOML would give them."""
    from drivers.simulated.plugin import default_sensor_configs

    return [c.model_dump(exclude_defaults=False) for c in default_sensor_configs()]


def parse_config(data: Mapping[str, Any], source: str = BUILTIN_SOURCE, base_dir: Path | None = None) -> Config:
    """Validate a parsed TOML document; raise :class:`ConfigError` listing every problem."""
    if not isinstance(data, Mapping):
        raise ConfigError(source, ["(top level): expected a table"])
    data = dict(data)
    raw_sensors = data.pop("sensors", None)
    problems: list[str] = []

    try:
        config = Config.model_validate(data)
    except ValidationError as error:
        problems.extend(_problems("", error))
        config = None

    if raw_sensors is None:
        raw_sensors = default_simulated_sensors()
    indexed: list[tuple[int, SensorConfig]] = []
    if not isinstance(raw_sensors, list):
        problems.append("sensors: expected an array of tables ([[sensors]])")
        raw_sensors = []
    for index, raw in enumerate(raw_sensors):
        prefix = f"sensors[{index}]"
        if not isinstance(raw, Mapping):
            problems.append(f"{prefix}: expected a table")
            continue
        kind = raw.get("kind")
        if not isinstance(kind, str):
            problems.append(f"{prefix}.kind: required: the driver kind (simulated, modbus, serial_line, ...)")
            continue
        try:
            plugin = load_plugin(kind)
        except UnknownDriverError as error:
            problems.append(f"{prefix}.kind: {error}")
            continue
        except Exception as error:  # a broken third-party plugin must not hide the other problems
            problems.append(f"{prefix}.kind: driver {kind!r} failed to load: {error}")
            continue
        try:
            indexed.append((index, plugin.config_model.model_validate(dict(raw))))
        except ValidationError as error:
            problems.extend(_problems(prefix, error))

    seen: set[str] = set()
    for index, sensor in indexed:
        if sensor.name in seen:
            problems.append(f"sensors[{index}].name: {sensor.name!r} is used twice (names must be unique)")
        seen.add(sensor.name)
    positions = [s.name for _, s in indexed if s.role == "position"]
    if len(positions) > 1:
        problems.append(f"sensors: more than one position sensor ({', '.join(positions)}); the cell has one axis")
    if config is not None:
        hub_names = [h.name for h in config.hubs]
        for name in sorted({n for n in hub_names if hub_names.count(n) > 1}):
            problems.append(f"hubs: name {name!r} is used twice")
        for index, sensor in indexed:
            hub = getattr(sensor, "hub", None)
            if hub is not None and hub not in hub_names:
                known = ", ".join(hub_names) or "none defined"
                problems.append(f"sensors[{index}].hub: no [[hubs]] named {hub!r} (hubs: {known})")

    if problems:
        raise ConfigError(source, problems)
    assert config is not None
    base = base_dir or Path.cwd()
    updates: dict[str, Any] = {"sensors": [sensor for _, sensor in indexed]}
    if not config.model.path.is_absolute():
        updates["model"] = config.model.model_copy(update={"path": (base / config.model.path).resolve()})
    zfile = config.zenoh.config_file
    if zfile is not None and not zfile.is_absolute():
        updates["zenoh"] = config.zenoh.model_copy(update={"config_file": (base / zfile).resolve()})
    result = config.model_copy(update=updates)
    result._source = source
    return result


def load_config(path: str | Path | None) -> Config:
    """The config in ``path`` (TOML), or the built-in default (simulated cell) when ``path`` is None."""
    if path is None:
        return default_config()
    file = Path(path)
    try:
        text = file.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError(str(file), ["file not found"]) from None
    except (OSError, UnicodeDecodeError) as error:
        raise ConfigError(str(file), [f"cannot read: {error}"]) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(str(file), [f"not valid TOML: {error}"]) from None
    return parse_config(data, source=str(file), base_dir=file.resolve().parent)


def default_config() -> Config:
    """No file: the simulated cell in a room inside the shipped model's training range, served with that model.

    Extrapolation is then a finding, not the first thing a new user sees; ``[simulation] scenario``
    (``test5``, ``daily``) shows it on purpose.
    """
    return parse_config({"simulation": {"scenario": "room"}}, source=BUILTIN_SOURCE)


def missing_model_channels(config: Config, channels: Sequence[str]) -> list[str]:
    """Channels the model needs that no temperature sensor of the config provides."""
    have = {s.name for s in config.sensors if s.role == "temperature"}
    return [c for c in channels if c not in have]
