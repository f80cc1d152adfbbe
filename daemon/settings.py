"""The daemon's own config tables as plain pydantic models: ``[zenoh]``, ``[model]``, ``[actuator]``'s
core keys, ``[procedure]``, ``[metrics]``, ``[health]``, ``[adapt]``, and :class:`Config`, which holds them.

Plain on purpose: no plugin machinery (no ``nanodrift.drivers.registry``, no entry points), so the bus and any
other importer of a table (``nanodrift.bus.session`` takes :class:`ZenohSettings`) loads without plugin
discovery. Validating a whole document, where plugins validate their own tables, is
:mod:`nanodrift.config`'s job, which re-exports everything here: callers import from ``nanodrift.config``.
Every table is a :class:`nanodrift.drivers.base.StrictModel` (no unknown keys, no inf/nan, no strings for
numbers).
"""

from __future__ import annotations

import ipaddress
import math
import re
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AllowInfNan, BaseModel, Field, PrivateAttr, Strict, field_validator, model_validator
from pydantic.functional_validators import AfterValidator

import nanodrift.motion as motion
from nanodrift.calibration.plans import CALIBRATION_POINTS_UM, PAPER_TIMING, StepTiming
from nanodrift.drivers.base import ActuatorOptions, SensorConfig, StrictModel

DATA_DIR = Path(__file__).resolve().parent / "data"
#: the simulated cell's model, shipped with the package (a config that runs the simulator uses it by default)
DEFAULT_MODEL_PATH = DATA_DIR / "default_model.json"
#: where a real cell's model lives by default: the unit's state directory (see the README's install steps)
STATE_MODEL_PATH = Path("/var/lib/nanodrift/model.json")
BUILTIN_SOURCE = "<built-in default config>"


#: the key tree every cell's keys live under unless ``[zenoh] prefix`` says otherwise (the contract's default)
DEFAULT_PREFIX = "nanodrift"
#: one chunk of a key prefix: characters a Zenoh key expression takes literally (no ``*``, ``$``, ``#``, ``?``)
_PREFIX_CHUNK = re.compile(r"[A-Za-z0-9_.\-]+")


def prefix_problem(value: str) -> str | None:
    """Why ``value`` is not a usable key prefix (``[zenoh] prefix``, ``--prefix``, ``Client(prefix=)``), or None.

    One or more ``/``-separated chunks of letters, digits, ``_``, ``.``, ``-``: no wildcard or other
    special character of Zenoh's key expressions, no empty chunk, no leading or trailing ``/``."""
    expected = ('expected one or more "/"-separated chunks of letters, digits, "_", "." or "-", '
                'e.g. "nanodrift" or "femto/lab3/stages"')
    if not value:
        return f"empty; {expected}"
    if value.startswith("/") or value.endswith("/"):
        return f"{value!r} starts or ends with '/'; {expected}"
    for chunk in value.split("/"):
        if not chunk:
            return f"{value!r} has an empty chunk ('//'); {expected}"
        if not _PREFIX_CHUNK.fullmatch(chunk):
            bad = sorted({c for c in chunk if not _PREFIX_CHUNK.fullmatch(c)})
            what = "a wildcard or special character" if set(bad) & set("*$#?") else "character(s)"
            return f"{value!r} has {what} {' '.join(repr(c) for c in bad)} in chunk {chunk!r}; {expected}"
    return None


def checked_prefix(value: str, *, label: str = "", error: type[Exception] = ValueError) -> str:
    """``value`` when it is a usable key prefix, else ``error`` saying why (after ``label``)."""
    problem = prefix_problem(value)
    if problem:
        raise error(f"{label}{problem}")
    return value


#: a path written as a TOML string (strict mode would take only a Path object)
PathText = Annotated[Path, Strict(False)]


class ZenohSettings(StrictModel):
    """How the daemon joins the Zenoh network; ``-l/-e/--mode`` on the command line override it."""

    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = Field(default_factory=list, description="endpoints, e.g. tcp/0.0.0.0:7447")
    connect: list[str] = Field(default_factory=list)
    multicast_scouting: bool = Field(default=True, description="find peers by UDP multicast")
    config_file: PathText | None = Field(default=None, description="a zenoh json5 config used as the base")
    prefix: Annotated[str, AfterValidator(checked_prefix)] = Field(default=DEFAULT_PREFIX, description=(
        "the key tree of the cell: its keys are <prefix>/<cell>/...; one or more chunks, e.g. femto/lab3/stages"))


class ModelSettings(StrictModel):
    path: PathText = Field(default=DEFAULT_MODEL_PATH, description=(
        "the model file (nanodrift-model/1); default: the package's model for the simulated cell, "
        "/var/lib/nanodrift/model.json for hardware"))


#: a host name's label (RFC 1123): 1 to 63 letters, digits and inner hyphens
_HOST_LABEL = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9-]{0,61}[A-Za-z0-9])?")


class MetricsSettings(StrictModel):
    """``[metrics]``: Prometheus metrics over HTTP (``nanodrift.service.metrics``); off unless ``listen`` is set.

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
        labels = host.split(".")
        try:
            if host.startswith("["):
                ipaddress.IPv6Address(host[1:-1])
            elif all(label.isdigit() for label in labels):  # looks like IPv4: must be one
                ipaddress.IPv4Address(host)
            else:
                return len(host) <= 253 and all(_HOST_LABEL.fullmatch(label) for label in labels)
        except ValueError:
            return False
        return True

    @property
    def host(self) -> str:
        """The host of ``listen`` without IPv6 brackets ("" when off)."""
        return self.listen.rpartition(":")[0].strip("[]")


#: ``[health] record_keep_days`` at most: a century. The retention date (today minus the days) must be a
#: date Python can hold (1,000,000 days failed every row with "date value out of range"), and no lab keeps
#: its recorded operation longer than the instrument lives.
MAX_RECORD_KEEP_DAYS = 36_500


class HealthSettings(StrictModel):
    """``[health]``: the model's health from the position sensor (``nanodrift.service.health_unit``); needs a
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


class AdaptSettings(StrictModel):
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


class ActuatorConfig(StrictModel):
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
    power_up_voltage_v: Annotated[float, AllowInfNan(True)] = Field(default=0.0, description=(
        "what the output holds after the module powers up: on a first start (no state kept) a read-back is "
        "believed only when it equals this; nan = never (every first start is confirmed by an operator)"))
    read_back_tolerance_v: float = Field(default=motion.READ_BACK_TOLERANCE_V, gt=0, le=1.0, description=(
        "a read-back this close to what the daemon last wrote (or to power_up_voltage_v) is believed"))
    position_proof_tolerance_um: Annotated[float, AllowInfNan(True)] = Field(default=math.nan, description=(
        "at start, a read-back nothing on record confirms is believed when the axis' position sensor, fresh, reads "
        "within this of the command the voltage means ((V - offset_v) / volts_per_um): the model's largest "
        "correction |q - x| plus the sensor's uncertainty, as the operator states them; nan = never"))
    #: the plugin's validated device keys (None for kind = "zenoh"); not a TOML key of its own
    _options: ActuatorOptions | None = PrivateAttr(default=None)

    @field_validator("max_slew_um_per_s")
    @classmethod
    def _off_or_physical(cls, value: float) -> float:
        if 0 < value < MIN_SLEW_UM_PER_S:
            raise ValueError(f"must be 0 (off) or at least {MIN_SLEW_UM_PER_S:g} um/s, got {value:g}: a slower ramp "
                             "writes the same output value for seconds (or never moves, at 1e-300)")
        return value

    @field_validator("position_proof_tolerance_um")
    @classmethod
    def _nan_or_positive(cls, value: float) -> float:
        if math.isnan(value):
            return math.nan
        if not 0 < value < math.inf:
            raise ValueError("must be a positive, finite distance in um, or nan (a position sensor proves nothing)")
        return value

    @field_validator("safe_voltage_v", "power_up_voltage_v")
    @classmethod
    def _nan_or_finite(cls, value: float) -> float:
        if math.isnan(value):
            return math.nan  # the one NaN object: two configs that both say nan compare equal
        if not math.isfinite(value):
            raise ValueError("must be a finite voltage, or nan")
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
        """What the amplifier gets for command ``q_um`` (:func:`nanodrift.motion.voltage_for`)."""
        return motion.voltage_for(self, q_um)

    def q_um_for(self, voltage_v: float) -> float:
        """The command whose voltage is ``voltage_v``: the inverse of :meth:`voltage`."""
        return motion.q_um_for(self, voltage_v)

    def within_limits(self, voltage_v: float) -> bool:
        """Nothing outside ``[v_min, v_max]`` is ever published or written (NaN is outside)."""
        return motion.within_limits(self, voltage_v)

    def checked_voltage(self, q_um: float) -> float:
        """:meth:`voltage`, or a :class:`~nanodrift.motion.VoltageLimitError` naming the command and the limits."""
        return motion.checked_voltage(self, q_um)


#: letters an axis may take (``nanodrift.model.cell_model.AXIS_LETTERS``: not q, ``q_um`` is the one-axis command)
AXIS_NAME_PATTERN = r"^[a-pr-z]$"


class AxisKeys(StrictModel):
    """``[[axes]]``' own keys (its ``[axes.actuator]`` is validated as an ``[actuator]`` table)."""

    name: str = Field(pattern=AXIS_NAME_PATTERN, description="one lowercase letter (not q): positions are <name>_um")
    min_um: float = 0.0
    max_um: float = 500.0

    @model_validator(mode="after")
    def _ordered(self) -> AxisKeys:
        if self.min_um >= self.max_um:
            raise ValueError(f"min_um ({self.min_um:g}) must be below max_um ({self.max_um:g})")
        return self


class AxisConfig(BaseModel):
    """One axis of a multi-axis cell: its name and its actuator (whose ``x_min_um``/``x_max_um`` are the
    axis' ``min_um``/``max_um``: every motion rule of a one-axis cell applies per axis unchanged)."""

    model_config = {"frozen": True}

    name: str
    actuator: ActuatorConfig

    @property
    def workspace_um(self) -> tuple[float, float]:
        return self.actuator.workspace_um


class ProcedureSettings(StrictModel):
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


class DaemonSettings(StrictModel):
    """``[daemon]``: where the daemon keeps its state when systemd does not say (``$STATE_DIRECTORY`` wins)."""

    state_dir: PathText | None = Field(default=None, description=(
        "the directory of the record of what each output was last written (nanodrift.output_record); "
        "$STATE_DIRECTORY (systemd's StateDirectory=) takes precedence; unset: every start is a first start"))


class Config(StrictModel):
    """The whole operator config.

    ``sensors`` hold each plugin's own validated config object, ``hubs`` the ``[[hubs]]`` entries
    validated by the plugin whose sensors use them, ``section(name)`` a top-level table a plugin
    owns (``[simulation]``). None of these are typed here: the core knows no plugin by name.
    """

    cell: str = Field(default="cell0", pattern=r"^[A-Za-z0-9_\-]+$",
                      description="the cell's keys are <[zenoh] prefix>/<cell>/...")
    zenoh: ZenohSettings = Field(default_factory=ZenohSettings)
    model: ModelSettings = Field(default_factory=ModelSettings)
    actuator: ActuatorConfig = Field(default_factory=ActuatorConfig)
    procedure: ProcedureSettings = Field(default_factory=ProcedureSettings)
    metrics: MetricsSettings = Field(default_factory=MetricsSettings)
    health: HealthSettings = Field(default_factory=HealthSettings)
    adapt: AdaptSettings = Field(default_factory=AdaptSettings)
    daemon: DaemonSettings = Field(default_factory=DaemonSettings)
    hubs: list[Any] = Field(default_factory=list)
    sensors: list[Any] = Field(default_factory=list)
    #: ``[[axes]]`` (validated by ``nanodrift.config``): empty for a one-axis cell, whose axis is ``[actuator]``'s x
    axes: list[Any] = Field(default_factory=list)
    #: where it came from (a file path, or the built-in default); not a TOML key
    _source: str = PrivateAttr(default=BUILTIN_SOURCE)
    #: plugin-owned top-level tables, validated by their plugin; not typed here
    _sections: dict[str, BaseModel] = PrivateAttr(default_factory=dict)
    #: the cell is simulated by a plugin (``virtual_cell``): a reload never switches this
    _virtual_cell: bool = PrivateAttr(default=False)
    #: position sensor name -> the axis it measures (``[[sensors]] axis``, default x)
    _sensor_axes: dict[str, str] = PrivateAttr(default_factory=dict)

    @property
    def multi_axis(self) -> bool:
        """A cell with ``[[axes]]`` (an XY or XYZ stage); without, today's one-axis cell."""
        return bool(self.axes)

    @property
    def axis_names(self) -> tuple[str, ...]:
        """The cell's axes in their config order (``("x",)`` for a one-axis cell)."""
        return tuple(a.name for a in self.axes) if self.axes else ("x",)

    def axis_actuators(self) -> dict[str, ActuatorConfig]:
        """Each axis' actuator (a one-axis cell: ``{"x": [actuator]}``)."""
        if not self.axes:
            return {"x": self.actuator}
        return {a.name: a.actuator for a in self.axes}

    def sensor_axis(self, name: str) -> str:
        """The axis a position sensor measures (x unless it says otherwise)."""
        return self._sensor_axes.get(name, "x")

    def sensor_workspaces(self) -> dict[str, tuple[float, float]]:
        """Each position sensor's axis workspace (its default valid range); empty for a one-axis cell."""
        if not self.axes:
            return {}
        actuators = self.axis_actuators()
        return {s.name: actuators[self.sensor_axis(s.name)].workspace_um for s in self.sensors
                if s.role == "position" and self.sensor_axis(s.name) in actuators}

    def position_sensors(self) -> dict[str, SensorConfig]:
        """axis -> its position sensor (at most one per axis)."""
        return {self.sensor_axis(s.name): s for s in self.sensors if s.role == "position"}

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
