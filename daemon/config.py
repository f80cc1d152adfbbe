"""The operator's TOML config, validated by pydantic (the contract in the README).

Validation runs in two passes so every message names its field path: first the daemon's own
sections, then each ``[[sensors]]`` entry with the pydantic model of the driver plugin its ``kind``
names (a lab's own driver validates its own keys). ``[actuator]`` is split the same way: the core
keys (gain, limits, motion) here, the device keys by the ``actuator_model`` of the plugin its
``kind`` names. Unknown keys are errors everywhere: a typo must
never pass silently, and numbers are strict: ``scale = "0.1"`` (a string) is an error, not 0.1.
Errors are collected and reported together, each as ``<file>:<line>: <path>: <what was expected>``,
e.g. ``lab.toml:42: sensors[5] (T6).scale: Input should be a valid number``. ``tomllib`` keeps no
positions, so the line is found in the text: the n-th ``[[sensors]]`` header, then the key inside it.

Longer than most modules on purpose: every section of the operator contract and the checks across
sections (an actuator's hub, procedure points inside the workspace) read in one place.
"""

from __future__ import annotations

import ipaddress
import math
import re
import tomllib
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Annotated, Any, Literal, TypeVar

from pydantic import (
    AllowInfNan,
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    Strict,
    ValidationError,
    field_validator,
    model_validator,
)

from daemon import motion
from daemon.calibration.plans import CALIBRATION_POINTS_UM, PAPER_TIMING, StepTiming
from daemon.errors import UserError
from drivers.base import ActuatorOptions, DriverPlugin, SensorConfig
from drivers.registry import UnknownDriverError, available, load_plugin

DATA_DIR = Path(__file__).resolve().parent / "data"
#: the simulated cell's model, shipped with the package (a config that runs the simulator uses it by default)
DEFAULT_MODEL_PATH = DATA_DIR / "default_model.json"
#: where a real cell's model lives by default: the unit's state directory (see the README's install steps)
STATE_MODEL_PATH = Path("/var/lib/nanodrift/model.json")
BUILTIN_SOURCE = "<built-in default config>"


class ConfigError(UserError):
    """An invalid config; ``problems`` holds one ``path: message`` line per problem, ``lines`` the
    line of the file each one is at (None when unknown); the message shows ``file:line: problem``."""

    def __init__(self, source: str, problems: Sequence[str], lines: Sequence[int | None] | None = None) -> None:
        self.source = source
        self.problems = list(problems)
        self.lines = list(lines) if lines is not None else [None] * len(self.problems)
        text = "\n".join(f"{source}:{line}: {p}" if line else f"{source}: {p}"
                         for p, line in zip(self.problems, self.lines, strict=True))
        super().__init__(text)


class _Strict(BaseModel):
    """No unknown keys, no inf/nan, and no strings for numbers (pydantic's strict mode: an int is a
    fine float, ``"0.1"`` is not)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


#: a path written as a TOML string (strict mode would take only a Path object)
PathText = Annotated[Path, Strict(False)]


class ZenohSettings(_Strict):
    """How the daemon joins the Zenoh network; ``-l/-e/--mode`` on the command line override it."""

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=list, description="endpoints, e.g. tcp/0.0.0.0:7447")
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = Field(default=True, description="find peers by UDP multicast")
    config_file: PathText | None = Field(default=None, description="a zenoh json5 config used as the base")


class ModelSettings(_Strict):
    path: PathText = Field(default=DEFAULT_MODEL_PATH, description=(
        "the model file (nanodrift-model/1); default: the package's model for the simulated cell, "
        "/var/lib/nanodrift/model.json for hardware"))


#: a host name's label (RFC 1123): 1 to 63 letters, digits and inner hyphens
_HOST_LABEL = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


class MetricsSettings(_Strict):
    """``[metrics]``: Prometheus metrics over HTTP (``daemon.service.metrics``); off unless ``listen`` is set.

    The host is checked here (an IP address, ``[v6]`` in brackets, or a host name of 1-63 character
    labels and 253 characters in all), so that a mistyped one is refused by ``check-config`` rather
    than failing in the resolver at start."""

    listen: str = Field(default="", description='"" = off; else "HOST:PORT", e.g. "127.0.0.1:9464" (/metrics)')

    @field_validator("listen")
    @classmethod
    def _host_port(cls, value: str) -> str:
        if value == "":
            return value
        match = re.fullmatch(r"(?P<host>\[[^\]]*\]|[^:\[\]]+):(?P<port>\d{1,5})", value)
        if match is None or not 0 < int(match["port"]) < 65536:
            raise ValueError('expected "HOST:PORT" with a port from 1 to 65535, e.g. "127.0.0.1:9464" '
                             '("[::1]:9464" for IPv6)')
        host = match["host"]
        if not cls._valid_host(host):
            shown = host if len(host) <= 40 else f"{host[:40]}... ({len(host)} characters)"
            raise ValueError(f"host {shown!r} is not an IP address (IPv6 in brackets) or a host name (labels of "
                             "1 to 63 letters, digits or inner '-', at most 253 characters)")
        return value

    @classmethod
    def _valid_host(cls, host: str) -> bool:
        if host.startswith("["):
            try:
                ipaddress.IPv6Address(host[1:-1])
            except ValueError:
                return False
            return True
        labels = host.split(".")
        if all(label.isdigit() for label in labels):  # looks like IPv4: must be one
            try:
                ipaddress.IPv4Address(host)
            except ValueError:
                return False
            return True
        return len(host) <= 253 and all(_HOST_LABEL.fullmatch(label) for label in labels)

    @property
    def host(self) -> str:
        """The host of ``listen`` without IPv6 brackets ("" when off)."""
        return self.listen.rpartition(":")[0].strip("[]")


#: ``[health] record_keep_days`` at most: a century. The retention date (today minus the days) must be a
#: date Python can hold (1,000,000 days failed every row with "date value out of range"), and no lab keeps
#: its recorded operation longer than the instrument lives.
MAX_RECORD_KEEP_DAYS = 36_500


class HealthSettings(_Strict):
    """``[health]``: the model's health from the position sensor (``daemon.service.health``); needs a
    ``role = "position"`` sensor, else the state stays ``unknown``. ``record_dir``/``record_keep_days``:
    recorded operation (daily CSVs of every settled target; a relative path is relative to the config
    file's folder)."""

    settle_s: float = Field(default=3.0, ge=0, description="the residual is read this long after a held command")
    window_s: float = Field(default=2.0, gt=0, description="... averaged over this window: mean position - target")
    history: int = Field(default=50, ge=1, le=100_000, description="rolling statistics over the last N residuals")
    alarm_rms_nm: float = Field(default=100.0, gt=0, description="RMS above this: state degraded")
    record_dir: str = Field(default="", description='"" = off; else daily CSVs of every settled target')
    record_keep_days: int = Field(default=90, ge=0, le=MAX_RECORD_KEEP_DAYS,
                                  description="delete day files older than this; 0 = keep all")

    @field_validator("record_dir")
    @classmethod
    def _a_path(cls, value: str) -> str:
        if "\x00" in value:
            raise ValueError("must be a folder path (no NUL character)")
        return value


class AdaptSettings(_Strict):
    """``[adapt]``: correct every command by the tracked settled residual (``mode = "bias"``), off by default."""

    mode: Literal["off", "bias"] = Field(default="off", description="off | bias")
    tau_s: float = Field(default=600.0, gt=0, description="the bias tracker's time constant")
    max_um: float = Field(default=1.0, gt=0, description="clamp on the correction (um)")


#: ``[actuator] kind`` handled by the core: the daemon publishes ``command`` and an output node applies it
ZENOH_KIND = "zenoh"


#: systemd/nanodrift.service's ``TimeoutStopSec``: systemd kills the daemon this long after SIGTERM
#: (tests/service/test_systemd.py holds the two equal)
STOP_TIMEOUT_S = 30.0
#: what the safe ramp to ``safe_voltage_v`` at shutdown may take of it; the rest is for stopping the
#: pollers, the recorder and Zenoh. A config whose full-stroke ramp takes longer is a check-config warning.
SAFE_RAMP_BUDGET_S = 20.0


#: the slowest ``max_slew_um_per_s`` other than 0 (off). A ramp writes every ``RAMP_PERIOD_S`` (20 ms):
#: at 0.01 um/s a write moves 0.2 nm, so one count of a 16-bit output (10 nm at 0.02 V/um over 14 V)
#: already takes a second of identical writes, and a full 500 um stroke 14 h. Slower is no longer a ramp
#: but a stage that looks stuck; at 1e-300 a step vanished in floating point (48 identical writes a
#: second, the stage never moved, the status ok).
MIN_SLEW_UM_PER_S = 0.01


class ActuatorConfig(_Strict):
    """Command q (um) -> PZT voltage, the limits nothing published may exceed, and who applies it.

    ``kind`` names the output path: ``zenoh`` (the core's: an external node applies the published
    ``command``) or a driver plugin with an ``actuator_model``, whose validated keys are
    :attr:`options`.
    """

    kind: str = Field(default=ZENOH_KIND, description="zenoh | modbus | serial_line | simulated | a plugin kind")
    volts_per_um: float = 0.02
    offset_v: float = 0.0
    v_min: float = -2.0
    v_max: float = 12.0
    x_min_um: float = 0.0
    x_max_um: float = 500.0
    max_slew_um_per_s: float = Field(default=0.0, ge=0, description=(
        f"0 = off; else larger jumps are ramped (at least {MIN_SLEW_UM_PER_S:g} um/s)"))
    safe_voltage_v: Annotated[float, AllowInfNan(True)] = Field(
        default=math.nan, description="written on shutdown when finite; nan = leave the stage where it is")
    #: the plugin's validated device keys (None for kind = "zenoh"); not a TOML key of its own
    _options: ActuatorOptions | None = PrivateAttr(default=None)

    @field_validator("max_slew_um_per_s")
    @classmethod
    def _off_or_physical(cls, value: float) -> float:
        if 0 < value < MIN_SLEW_UM_PER_S:
            raise ValueError(f"must be 0 (off) or at least {MIN_SLEW_UM_PER_S:g} um/s, got {value:g}: a slower ramp "
                             "writes the same output value for seconds (or never moves, at 1e-300)")
        return value

    @field_validator("safe_voltage_v")
    @classmethod
    def _nan_or_finite(cls, value: float) -> float:
        if math.isnan(value):
            return math.nan  # the one NaN object: two configs that both say nan compare equal
        if not math.isfinite(value):
            raise ValueError("must be a finite voltage, or nan (leave the stage where it is)")
        return value

    @model_validator(mode="after")
    def _ordered(self) -> ActuatorConfig:
        if self.volts_per_um == 0:
            raise ValueError("volts_per_um must not be 0")
        if self.v_min >= self.v_max:
            raise ValueError(f"v_min ({self.v_min}) must be below v_max ({self.v_max})")
        if self.x_min_um >= self.x_max_um:
            raise ValueError(f"x_min_um ({self.x_min_um}) must be below x_max_um ({self.x_max_um})")
        if math.isfinite(self.safe_voltage_v) and not self.within_limits(self.safe_voltage_v):
            raise ValueError(f"safe_voltage_v ({self.safe_voltage_v:g}) must be inside [v_min, v_max] = "
                             f"[{self.v_min:g}, {self.v_max:g}]")
        return self

    @property
    def options(self) -> ActuatorOptions | None:
        return self._options

    @property
    def workspace_um(self) -> tuple[float, float]:
        """``[x_min_um, x_max_um]``: where targets may go (and, widened, where a position reading is believed)."""
        return self.x_min_um, self.x_max_um

    def with_options(self, options: ActuatorOptions | None) -> ActuatorConfig:
        copy = self.model_copy()
        copy._options = options
        return copy

    @property
    def safe_q_um(self) -> float | None:
        """The command that puts ``safe_voltage_v`` on the stage (None when it is nan)."""
        if math.isnan(self.safe_voltage_v):
            return None
        return self.q_um_for(self.safe_voltage_v)

    def safe_ramp(self) -> tuple[float, float, float] | None:
        """The longest ramp to ``safe_voltage_v`` at shutdown: ``(seconds, um, from_v)`` from the limit
        farthest from it at ``max_slew_um_per_s``; None when nothing is ramped (nan, or the slew limit off).

        The stage is somewhere in ``[v_min, v_max]``, so this is the worst case the stop must allow for
        (check-config compares it with :data:`SAFE_RAMP_BUDGET_S`).
        """
        if math.isnan(self.safe_voltage_v) or self.max_slew_um_per_s <= 0:
            return None
        from_v = max((self.v_min, self.v_max), key=lambda v: abs(v - self.safe_voltage_v))
        distance_um = abs(from_v - self.safe_voltage_v) / abs(self.volts_per_um)
        return distance_um / self.max_slew_um_per_s, distance_um, from_v

    def voltage(self, q_um: float) -> float:
        """What the amplifier gets for command ``q_um`` (:func:`daemon.motion.voltage_for`)."""
        return motion.voltage_for(self, q_um)

    def q_um_for(self, voltage_v: float) -> float:
        """The command whose voltage is ``voltage_v``: the inverse of :meth:`voltage`."""
        return motion.q_um_for(self, voltage_v)

    def within_limits(self, voltage_v: float) -> bool:
        """Nothing outside ``[v_min, v_max]`` is ever published or written (NaN is outside)."""
        return motion.within_limits(self, voltage_v)

    def checked_voltage(self, q_um: float) -> float:
        """:meth:`voltage`, or a :class:`~daemon.motion.VoltageLimitError` naming the command and the limits."""
        return motion.checked_voltage(self, q_um)


class ProcedureSettings(_Strict):
    """``[procedure]``: the trajectory and step timing of ``calibrate`` and ``validate`` (the paper's by default).

    A stiff stage that settles fast can be calibrated in much less than four hours by shortening
    ``hold_s``; ``average_s`` is the end of the hold that is averaged. ``follow_*``: during the first
    ``follow_steps`` moves the position sensor must move by the commanded step within
    ``follow_tolerance`` (a fraction of the step), else the procedure stops (an amplifier that is off
    or miswired must not cost a four-hour run).
    """

    points: list[float] | None = Field(default=None, description="calibration targets (um); default 0, 30, ..., 480")
    step_um: float | None = Field(default=None, gt=0, description="or: targets 0, step_um, ... up to max_um")
    max_um: float | None = Field(default=None, gt=0)
    cycles: int = Field(default=24, ge=1, description="calibration sweeps (calibrate --cycles overrides it)")
    trajectory: Literal["forward", "bidirectional"] = Field(
        default="forward", description="calibration sweeps: forward (the paper's, up only) or up and down")
    rise_s: float = Field(default=PAPER_TIMING.ramp_s, ge=0, description="the command ramps to the next target")
    hold_s: float = Field(default=PAPER_TIMING.hold_s, gt=0, description="then holds it this long")
    average_s: float = Field(default=PAPER_TIMING.window_s, gt=0, description="the last average_s of the hold")
    follow_tolerance: float = Field(default=0.5, gt=0, description="fraction of the commanded step")
    follow_steps: int = Field(default=3, ge=0, description="moves checked at the start; 0 = off")

    @model_validator(mode="after")
    def _consistent(self) -> ProcedureSettings:
        if self.points is not None and (self.step_um is not None or self.max_um is not None):
            raise ValueError("give points, or step_um and max_um, not both")
        if self.points is not None:
            if len(self.points) < 2:
                raise ValueError("points: at least two targets (the model needs the stage to move)")
            if len(set(self.points)) != len(self.points):
                raise ValueError("points: a target is listed twice")
        if self.average_s > self.hold_s:
            raise ValueError(f"average_s ({self.average_s:g}) must not exceed hold_s ({self.hold_s:g})")
        return self

    @property
    def calibration_points(self) -> tuple[float, ...]:
        if self.points is not None:
            return tuple(self.points)
        if self.step_um is None and self.max_um is None:
            return CALIBRATION_POINTS_UM
        step = self.step_um if self.step_um is not None else 30.0
        top = self.max_um if self.max_um is not None else max(CALIBRATION_POINTS_UM)
        count = math.floor(top / step + 1e-9) + 1
        return tuple(round(k * step, 9) for k in range(count))

    @property
    def timing(self) -> StepTiming:
        return StepTiming(ramp_s=self.rise_s, hold_s=self.hold_s, window_s=self.average_s)


class Config(_Strict):
    """The whole operator config.

    ``sensors`` hold each plugin's own validated config object, ``hubs`` the ``[[hubs]]`` entries
    validated by the plugin whose sensors use them, ``section(name)`` a top-level table a plugin
    owns (``[simulation]``). None of these are typed here: the core knows no plugin by name.
    """

    cell: str = Field(default="cell0", pattern=r"^[A-Za-z0-9_\-]+$", description="key prefix nanodrift/<cell>")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    model: ModelSettings = Field(default_factory=ModelSettings)
    actuator: ActuatorConfig = Field(default_factory=ActuatorConfig)
    procedure: ProcedureSettings = Field(default_factory=ProcedureSettings)
    metrics: MetricsSettings = Field(default_factory=MetricsSettings)
    health: HealthSettings = Field(default_factory=HealthSettings)
    adapt: AdaptSettings = Field(default_factory=AdaptSettings)
    hubs: list[Any] = Field(default_factory=list)
    sensors: list[Any] = Field(default_factory=list)
    #: where it came from (a file path, or the built-in default); not a TOML key
    _source: str = PrivateAttr(default=BUILTIN_SOURCE)
    #: plugin-owned top-level tables, validated by their plugin; not typed here
    _sections: dict[str, BaseModel] = PrivateAttr(default_factory=dict)
    #: the cell is simulated by a plugin (``virtual_cell``): a reload never switches this
    _virtual_cell: bool = PrivateAttr(default=False)

    @property
    def source(self) -> str:
        return self._source

    @property
    def sections(self) -> dict[str, BaseModel]:
        return dict(self._sections)

    @property
    def virtual_cell(self) -> bool:
        return self._virtual_cell

    def section(self, name: str) -> BaseModel | None:
        return self._sections.get(name)

    def with_section(self, name: str, value: BaseModel) -> Config:
        """A copy with one plugin section replaced (command-line overrides of ``[simulation]``)."""
        copy = self.model_copy()
        copy._sections = {**self._sections, name: value}
        return copy

    def kinds(self) -> list[str]:
        """Driver kinds in use, in first-appearance order."""
        return list(dict.fromkeys(s.kind for s in self.sensors))

    def sensor(self, name: str) -> SensorConfig | None:
        return next((s for s in self.sensors if s.name == name), None)


#: pydantic puts the union member that failed in ``loc`` (``effects.list[str]``, ``port.int``): it names no key
_UNION_MEMBER = re.compile(r"^(?:[a-z][a-z-]*\[.*\]|int|float|str|bool|none)$")


def _loc(prefix: str, loc: Sequence[Any], unknown_key: bool = False) -> str:
    path = prefix
    for position, part in enumerate(loc):
        last_is_the_key = unknown_key and position == len(loc) - 1  # a key the user wrote, whatever it is
        if isinstance(part, str) and _UNION_MEMBER.match(part) and not last_is_the_key:
            continue
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
        out.append(f"{_loc(prefix, item['loc'], item['type'] == 'extra_forbidden')}: {message}")
    return out


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

    def section_owner(self, name: str, kinds: Sequence[str]) -> DriverPlugin | None:
        """The plugin owning top-level table ``name``: the kinds in use first, then every installed one."""
        for kind in kinds:
            plugin = self.plugin(kind, "sensors")
            if plugin is not None and plugin.section == name:
                return plugin
        for kind in available():
            if kind not in kinds:
                plugin = self.plugin(kind, name)
                if plugin is not None and plugin.section == name:
                    return plugin
        return None

    def validate(self, model: type[_Model], raw: Any, where: str) -> _Model | None:
        if not isinstance(raw, Mapping):
            self.problems.append(f"{where}: expected a table")
            return None
        try:
            return model.model_validate(dict(raw))
        except ValidationError as error:
            self.problems.extend(_problems(where, error))
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
    owners: dict[str, DriverPlugin] = {}
    for name in [k for k in data if k not in Config.model_fields]:
        owner = parse.section_owner(name, kinds)
        if owner is None or owner.section_model is None:
            continue  # left in: Config reports it as an unknown key
        value = parse.validate(owner.section_model, data.pop(name), name)
        if value is not None:
            sections[name], owners[name] = value, owner

    config: Config | None
    try:
        config = Config.model_validate(data)
    except ValidationError as error:
        parse.problems.extend(_problems("", error))
        config = None

    sensors = _parse_sensors(parse, raw_sensors, sections, owners)
    used = [parse.plugin(s.kind, "sensors") for _, s in sensors]
    virtual_cell = any(p is not None and p.virtual_cell for p in [*used, *owners.values()])
    actuator = _parse_actuator(parse, raw_actuator, virtual_cell)
    hub_user = actuator.options.hub_name() if actuator is not None and actuator.options is not None else None
    hubs = _parse_hubs(parse, raw_hubs, sensors,
                       actuator=(hub_user, actuator.kind) if actuator is not None and hub_user is not None else None)
    if config is not None and actuator is not None:
        _check_points(parse, config.procedure, actuator)
    _check_across(parse, sensors, actuator)
    if actuator is not None:
        _check_valid_ranges(parse, sensors, actuator)

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
    kinds = [ZENOH_KIND]
    for kind in sorted(available()):
        try:
            if load_plugin(kind).actuator_model is not None:
                kinds.append(kind)
        except Exception:  # a broken third-party plugin is reported where it is used, not here
            continue
    return kinds


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
        if plugin.virtual_cell != virtual_cell:
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
    for kind in sorted(available()):
        try:
            plugin = load_plugin(kind)
        except Exception:
            continue
        if plugin.virtual_cell and plugin.actuator_model is not None:
            return kind
    return ZENOH_KIND


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


def _check_points(parse: _Parse, procedure: ProcedureSettings, actuator: ActuatorConfig) -> None:
    outside = [x for x in procedure.calibration_points if not actuator.x_min_um <= x <= actuator.x_max_um]
    if outside:
        parse.problems.append(
            f"procedure.points: {', '.join(f'{x:g}' for x in outside)} um outside the workspace "
            f"[x_min_um, x_max_um] = [{actuator.x_min_um:g}, {actuator.x_max_um:g}]")


#: a temperature sensor's believable range when it declares none (°C): wider than any lab and than a piezo
#: stage's rated range (at most ~150 °C), narrower than the codes a module sends for a broken thermocouple
#: (3276.7, -3276.8, 850); a lab measuring a hotter part sets valid_min/valid_max
DEFAULT_TEMPERATURE_RANGE_C = (-50.0, 150.0)
#: a position sensor's believable range when it declares none: the workspace widened by this share of
#: the stroke on each side (the stage overshoots and drifts a little beyond where targets may go)
POSITION_RANGE_MARGIN = 0.1


def valid_range(sensor: SensorConfig, workspace_um: tuple[float, float] | None) -> tuple[float, float]:
    """The values of ``sensor`` the daemon believes: its ``valid_min``/``valid_max``, each bound it leaves
    out from its role (position: the workspace with :data:`POSITION_RANGE_MARGIN`; temperature:
    :data:`DEFAULT_TEMPERATURE_RANGE_C`); unbounded for a position sensor when no workspace is known."""
    if sensor.role == "position":
        if workspace_um is None:
            default = (-math.inf, math.inf)
        else:
            margin = POSITION_RANGE_MARGIN * (workspace_um[1] - workspace_um[0])
            default = (workspace_um[0] - margin, workspace_um[1] + margin)
    else:
        default = DEFAULT_TEMPERATURE_RANGE_C
    low = sensor.valid_min if sensor.valid_min is not None else default[0]
    high = sensor.valid_max if sensor.valid_max is not None else default[1]
    return low, high


def _check_valid_ranges(parse: _Parse, sensors: Sequence[tuple[int, SensorConfig]],
                        actuator: ActuatorConfig) -> None:
    """A bound set against its role's default (``valid_min = 600`` with the workspace's 550 above it)."""
    for index, sensor in sensors:
        low, high = valid_range(sensor, actuator.workspace_um)
        if low < high:
            continue
        key = "valid_min" if sensor.valid_min is not None else "valid_max"
        parse.problems.append(
            f"{_sensor_where(index, sensor)}.{key}: the valid range would be [{low:g}, {high:g}] (the other bound "
            f"is the {sensor.role} default): no reading could be believed; set both valid_min and valid_max")


def _sensor_where(index: int, sensor: Any) -> str:
    """``sensors[5] (T6)``: the index in the file's order (0-based) and the sensor's name when it has one."""
    name = sensor.get("name") if isinstance(sensor, Mapping) else getattr(sensor, "name", None)
    return f"sensors[{index}] ({name})" if isinstance(name, str) and name else f"sensors[{index}]"


def _parse_sensors(parse: _Parse, raw_sensors: Any, sections: Mapping[str, BaseModel],
                   owners: Mapping[str, DriverPlugin]) -> list[tuple[int, SensorConfig]]:
    indexed: list[tuple[int, SensorConfig]] = []
    if raw_sensors is None:  # a virtual cell's table without sensors: the plugin's own
        for name, section in sections.items():
            if owners[name].virtual_cell:
                indexed.extend(enumerate(owners[name].default_sensors(section)))
        return indexed
    if not isinstance(raw_sensors, list):
        parse.problems.append("sensors: expected an array of tables ([[sensors]])")
        return indexed
    for index, raw in enumerate(raw_sensors):
        prefix = _sensor_where(index, raw)
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
                f"{_sensor_where(index, sensor)}.name: {sensor.name!r} is used twice (names must be unique)")
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
            parse.problems.append(f"{_sensor_where(index, sensor)}.hub: no [[hubs]] named {hub!r} (hubs: {known})")
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
    try:  # a hostile file ('x = ' + '[' * 100000) must be a message, never a traceback or a dead reload
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as error:
        raise ConfigError(str(file), [f"not valid TOML: {error}"]) from None
    except RecursionError:
        raise ConfigError(str(file), [TOO_DEEP]) from None
    except MemoryError:
        raise ConfigError(str(file), ["not valid TOML: too large to parse"]) from None
    except ValueError as error:  # tomllib's other refusals (an out-of-range date, ...)
        raise ConfigError(str(file), [f"not valid TOML: {error}"]) from None
    try:
        return parse_config(data, source=str(file), base_dir=file.resolve().parent)
    except ConfigError as error:
        raise ConfigError(error.source, error.problems, [locate(text, p) for p in error.problems]) from None
    except RecursionError:
        raise ConfigError(str(file), [TOO_DEEP]) from None


#: the problem line of a config whose arrays or inline tables nest deeper than the parser can follow
TOO_DEEP = "not valid TOML: nested too deeply (a nanodrift config nests a few levels of [ and {, not hundreds)"


_PROBLEM_PATH = re.compile(r"^(?P<table>[A-Za-z_][\w-]*)(?:\[(?P<index>\d+)\])?(?: \([^)]*\))?(?:\.(?P<key>[\w-]+))?")
_ARRAY_HEADER = re.compile(r"^\s*\[\[\s*(?P<name>[\w.-]+)\s*\]\]")
_TABLE_HEADER = re.compile(r"^\s*\[\s*(?P<name>[\w.-]+)\s*\]")


def locate(text: str, problem: str) -> int | None:
    """The 1-based line of ``text`` a problem (``sensors[5] (T6).scale: ...``) is at, or None.

    The key's own line when it is written in its table, else the line where the table starts (the
    n-th ``[[sensors]]`` header for ``sensors[n]``); a top-level key's line before any table.
    """
    match = _PROBLEM_PATH.match(problem)
    if match is None:
        return None
    table, index, key = match["table"], match["index"], match["key"]
    lines = text.splitlines()
    headers: list[tuple[int, str, bool]] = []  # (0-based line, name, is an array of tables)
    for number, line in enumerate(lines):
        header = _ARRAY_HEADER.match(line) or _TABLE_HEADER.match(line)
        if header:
            headers.append((number, header["name"], header.re is _ARRAY_HEADER))
    if index is not None:
        starts = [n for n, name, array in headers if name == table and array]
        start = starts[int(index)] if int(index) < len(starts) else None
    else:
        start = next((n for n, name, array in headers if name == table and not array), None)
    if start is None:  # a top-level key (``cell = ...``, ``sensors = 3``), written before any table
        end = headers[0][0] if headers else len(lines)
        return _key_line(lines, table, 0, end)
    if key is None:
        return start + 1
    end = next((n for n, _, _ in headers if n > start), len(lines))
    return _key_line(lines, key, start + 1, end) or start + 1


def _key_line(lines: Sequence[str], key: str, start: int, end: int) -> int | None:
    pattern = re.compile(rf"^\s*{re.escape(key)}\s*=")
    return next((n + 1 for n in range(start, end) if pattern.match(lines[n])), None)


#: the built-in config of ``nanodrift run`` with no ``--config``: the simulated cell's table (data, not an import)
BUILTIN_CONFIG: dict[str, Any] = {"simulation": {"scenario": "room"}}


def default_config() -> Config:
    """No file: the simulated cell in a room inside the shipped model's training range, served with that model.

    Extrapolation is then a finding, not the first thing a new user sees; ``[simulation] scenario``
    (``test5``, ``daily``) shows it on purpose.
    """
    return parse_config(BUILTIN_CONFIG, source=BUILTIN_SOURCE)


def missing_model_channels(config: Config, channels: Sequence[str]) -> list[str]:
    """Channels the model needs that no temperature sensor of the config provides."""
    have = {s.name for s in config.sensors if s.role == "temperature"}
    return [c for c in channels if c not in have]
