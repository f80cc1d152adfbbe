"""The small interfaces every device kind implements, in the spirit of python-can's bus.

A *sensor group* is the unit the daemon polls: one device request that yields readings for one or
more channels (a Modbus module answering eight thermocouples in one request is one group; a serial
interferometer is a group of one). A *plugin* turns validated sensor configs into groups, and is
found by name through the entry-point group ``nanodrift.drivers``.

Drivers report what the device said (``ok`` or ``fault`` with a reason). Whether the daemon believes
it is the daemon's judgement, not the driver's: ``stale`` (its age against ``max_age_s``, or a value
frozen for ``frozen_after_s``), ``fault`` (outside ``valid_min``..``valid_max``, non-finite, stamped
in the future). The keys are declared here so every plugin's sensors have them.
Connection-level trouble (port gone, timeout, socket closed) is raised as :class:`DeviceError` so
the daemon can reopen the group with backoff; a channel-level problem on a healthy device
(thermocouple burnout) is a ``fault`` reading.

Every config table a plugin validates is a :class:`StrictModel`. A plugin that *is* the cell (the
simulated one) is a :class:`VirtualCellPlugin`. Longer than most modules on purpose: this is the
whole contract a plugin author reads, in one file.
"""

from __future__ import annotations

import asyncio
import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any, ClassVar, Literal, Protocol, TypeVar

from pydantic import BaseModel, ConfigDict, Field, ValidationInfo, field_validator, model_validator


class State(StrEnum):
    OK = "ok"
    STALE = "stale"
    FAULT = "fault"


@dataclass(frozen=True, slots=True)
class Reading:
    """One timestamped value of one channel, with the device's verdict on it."""

    value: float  # NaN when state is FAULT
    t: float  # seconds on the group's clock (a monotonic clock labelled in unix seconds on real hardware)
    state: State = State.OK
    reason: str = ""
    unit: str = ""

    @classmethod
    def fault(cls, t: float, reason: str, unit: str = "") -> Reading:
        return cls(value=float("nan"), t=t, state=State.FAULT, reason=reason, unit=unit)


class DeviceError(Exception):
    """The device or its connection failed; the daemon closes and reopens the group with backoff."""


ConfigT = TypeVar("ConfigT", bound=BaseModel)


def as_config(config: BaseModel, model: type[ConfigT]) -> ConfigT:
    """``config`` as the plugin's own model (a caller may hand over the generic one, with the extra keys)."""
    return config if isinstance(config, model) else model.model_validate(config.model_dump())


def shown(text: bytes | str, max_chars: int = 80) -> str:
    """A device's text as an error message quotes it: repr, cut at ``max_chars`` (a garbage line can be long)."""
    text = text.decode("utf-8", "replace") if isinstance(text, bytes) else text
    return repr(text if len(text) <= max_chars else text[:max_chars] + "...")


class Clock(Protocol):
    """Where time comes from: monotonic real time, or a simulated one that runs faster than real time."""

    def now(self) -> float: ...

    async def sleep(self, seconds: float) -> None: ...


class MonotonicClock:
    """The daemon's time base: monotonic seconds, labelled in unix seconds at the moment it was made.

    Reading ages, stateful model terms (lag, rate, creep, dir), health windows, ramps and back-offs all
    run on this clock, so a step of the system clock (NTP, an operator's ``date -s``) in either
    direction changes none of them. It reads close to unix time (readings published with it look like
    unix seconds), but only the wall clock (``time.time()``) labels: payload ``t``, record dates.
    """

    #: one origin per process: every instance (a reload builds a new driver context) reads the same time
    _origin_unix_s = time.time()
    _origin_mono_s = time.monotonic()

    def now(self) -> float:
        return self._origin_unix_s + (time.monotonic() - self._origin_mono_s)

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))


#: bounds of a sensor's timing keys: physical values, so ``interval_s = 1e-300`` (the poller spins)
#: and ``max_age_s = 1e308`` (a reading of any age is fresh, as with inf) are refused naming the key
MIN_INTERVAL_S = 0.001
MAX_INTERVAL_S = 3600.0
MAX_AGE_S = 86400.0
#: ``frozen_after_s`` when a position sensor does not set it: a live interferometer's noise (tens of nm)
#: makes bit-identical readings for this long a dead instrument repeating its last value, not a stage at
#: rest. Temperatures default to 0 (off): a 0.1 °C module in a stable room legitimately repeats for hours.
POSITION_FROZEN_AFTER_S = 30.0


class StrictModel(BaseModel):
    """The base of every table of the operator's config: the daemon's own, and a plugin's (its sensors,
    hubs, section and actuator keys). A plugin's own tables subclass it (or :class:`SensorConfig`,
    :class:`ActuatorOptions`, which do).

    ``extra="forbid"``: a typo in an operator's config must be an error, never silently ignored.
    ``allow_inf_nan=False``: ``max_age_s = inf`` would make a reading of any age fresh.
    ``strict=True``: ``scale = "0.1"`` (a string) is refused, not read as a number; an int is a fine
    float (a path written as a string needs ``Strict(False)``). ``frozen``: a validated config is
    never changed in place.
    """

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False, strict=True)


class SensorConfig(StrictModel):
    """Keys common to every ``[[sensors]]`` entry. A plugin subclasses it with its own keys (strict, as
    every :class:`StrictModel`)."""

    name: str = Field(pattern=r"^[A-Za-z_][A-Za-z0-9_.\-]*$", description="channel name the model uses")
    role: Literal["temperature", "position"] = "temperature"
    kind: str
    interval_s: float = Field(default=0.5, ge=MIN_INTERVAL_S, le=MAX_INTERVAL_S,
                              description="poll period: 1 ms (faster only spins the loop) to 1 h")
    max_age_s: float = Field(default=5.0, gt=0, le=MAX_AGE_S,
                             description="older readings are stale; at least interval_s, at most a day")
    timeout_s: float = Field(default=1.0, gt=0, description="one poll may take this long")
    valid_min: float | None = Field(default=None, description="lowest believable value, in the sensor's unit "
                                    "(None: the role's default, see nanodrift.config.valid_range)")
    valid_max: float | None = Field(default=None, description="highest believable value, in the sensor's unit")
    frozen_after_s: float = Field(default=0.0, ge=0, le=MAX_AGE_S,
                                  description="a value bit-identical for longer is stale; 0 = off (the default "
                                  f"for temperatures; {POSITION_FROZEN_AFTER_S:g} s for a position sensor)")

    @model_validator(mode="before")
    @classmethod
    def _role_defaults(cls, data: Any) -> Any:
        """``frozen_after_s`` defaults by role: on for the interferometer (30 s, or ten polls when a poll is
        longer than 3 s), off for thermocouples."""
        if isinstance(data, Mapping) and "frozen_after_s" not in data and data.get("role") == "position":
            interval_s = data.get("interval_s")
            polls_s = 10.0 * interval_s if isinstance(interval_s, int | float) and math.isfinite(interval_s) else 0.0
            return {**data, "frozen_after_s": min(MAX_AGE_S, max(POSITION_FROZEN_AFTER_S, polls_s))}
        return data

    @field_validator("max_age_s")
    @classmethod
    def _at_least_one_interval(cls, value: float, info: ValidationInfo) -> float:
        interval_s = info.data.get("interval_s")  # absent when interval_s itself was refused
        if interval_s is not None and value < interval_s:
            raise ValueError(f"max_age_s = {value:g} s is below interval_s = {interval_s:g} s: every reading would "
                             "go stale before the next poll brings a new one; make max_age_s at least interval_s "
                             "(a few intervals is usual)")
        return value

    @field_validator("valid_max")
    @classmethod
    def _above_valid_min(cls, value: float | None, info: ValidationInfo) -> float | None:
        valid_min = info.data.get("valid_min")
        if value is not None and valid_min is not None and not valid_min < value:
            raise ValueError(f"valid_max = {value:g} is not above valid_min = {valid_min:g}: no reading could "
                             "be believed; make valid_min < valid_max (in the sensor's unit)")
        return value

    @field_validator("frozen_after_s")
    @classmethod
    def _off_or_longer_than_a_poll(cls, value: float, info: ValidationInfo) -> float:
        interval_s = info.data.get("interval_s")
        if value > 0 and interval_s is not None and value < interval_s:
            raise ValueError(f"frozen_after_s = {value:g} s is below interval_s = {interval_s:g} s: two readings "
                             "a poll apart would already count as frozen; use 0 (off) or at least interval_s "
                             "(many intervals is usual)")
        return value

    def hub_name(self) -> str | None:
        """The ``[[hubs]]`` entry this channel uses (None: none). A plugin with a ``hub_model`` declares
        its ``hub`` key and returns it here, so the config checks the hub exists and is used."""
        return None


_T = TypeVar("_T")


class SharedResources:
    """Objects a plugin shares between its sensor groups and its actuator (one connection per hub, one
    simulated cell), under keys the plugin chooses (``"<kind>.<what>"``).

    Typed on the way out: :meth:`get` checks the object is of the class asked for, so two plugins that
    chose one key get a ``TypeError`` naming it, never each other's object.
    """

    def __init__(self) -> None:
        self._objects: dict[str, object] = {}

    def get(self, key: str, cls: type[_T]) -> _T | None:
        """The object under ``key`` (None: none yet); a ``TypeError`` when it is not a ``cls``."""
        value = self._objects.get(key)
        if value is None:
            return None
        if not isinstance(value, cls):
            raise TypeError(f"shared resource {key!r} is a {type(value).__name__}, not a {cls.__name__}")
        return value

    def setdefault(self, key: str, default: _T) -> _T:
        """The object under ``key`` (checked as :meth:`get` does, against ``default``'s class), or
        ``default``, stored there first."""
        found = self.get(key, type(default))
        if found is None:
            self._objects[key] = default
            return default
        return found

    def put(self, key: str, value: object) -> None:
        """Store ``value`` under ``key``, replacing what was there."""
        self._objects[key] = value

    def per_name(self, key: str, name: str, make: Callable[[], _T]) -> _T:
        """The object ``name`` among those under ``key`` (one connection per hub or controller), made on first use."""
        made: dict[str, _T] = self.setdefault(key, {})
        if name not in made:
            made[name] = make()
        return made[name]


@dataclass
class DriverContext:
    """What a plugin may need besides its own sensor configs.

    ``hubs`` and ``sections`` were validated by the plugin that owns them (its ``hub_model`` and
    ``section_model``); ``resources`` holds the objects a plugin shares between its groups and its
    actuator (:class:`SharedResources`). ``label_clock`` labels what is recorded (the recorder's
    ``t_s`` and its day files): the wall clock, except on a virtual cell whose clock runs faster
    (:meth:`VirtualCellPlugin.label_clock`), where a record's day is the simulated lab's day.
    """

    clock: Clock = field(default_factory=MonotonicClock)
    label_clock: Callable[[], float] = time.time
    hubs: Mapping[str, BaseModel] = field(default_factory=dict)
    sections: Mapping[str, BaseModel] = field(default_factory=dict)
    resources: SharedResources = field(default_factory=SharedResources)
    #: the cell's axes in the config's order (``("x",)``: a one-axis cell); :meth:`DriverPlugin.create_actuators`
    #: gets one options table per axis of its kind in this order
    axes: tuple[str, ...] = ("x",)

    def hub(self, name: str, user: str) -> BaseModel:
        """The ``[[hubs]]`` entry ``name``; a :class:`DriverSetupError` naming ``user`` when there is none."""
        if name not in self.hubs:
            known = ", ".join(sorted(self.hubs)) or "none defined"
            raise DriverSetupError(f"{user}: no [[hubs]] named {name!r} (hubs: {known})")
        return self.hubs[name]


class SensorGroup(ABC):
    """Channels read together in one device transaction; polled by the daemon every ``interval_s``."""

    #: channel names this group yields, in a stable order
    names: tuple[str, ...]
    #: role of each channel ("temperature" | "position")
    roles: Mapping[str, str]
    interval_s: float
    timeout_s: float

    def set_channels(self, channels: Sequence[SensorConfig]) -> None:
        """``names`` and ``roles`` of the ``channels`` read together, in order, and their ``interval_s``: the
        fastest channel sets the pace (a slower one is read more often than it asked, never less)."""
        self.names = tuple(c.name for c in channels)
        self.roles = {c.name: c.role for c in channels}
        self.interval_s = min(c.interval_s for c in channels)

    @abstractmethod
    async def open(self) -> None:
        """Connect. Raise :class:`DeviceError` when the device cannot be reached."""

    @abstractmethod
    async def read(self) -> dict[str, Reading]:
        """One poll: a reading per channel in ``names``. Raise :class:`DeviceError` on link failure."""

    @abstractmethod
    async def close(self) -> None:
        """Release the device; safe to call twice and after a failed ``open``."""

    def true_values(self) -> Mapping[str, float]:
        """What the last :meth:`read`'s quantities truly were, per channel, when the group can know it.

        Optional: only a simulated cell knows the truth (the true attained position behind its
        interferometer reading), so a validation there can be scored against the truth as well as
        against the instrument. Hardware knows nothing: the default is empty.
        """
        return {}


class Actuator(ABC):
    """Puts the compensated command on the stage (its amplifier, its controller, or a simulated cell).

    The contract every kind keeps (the daemon and the procedures rely on it):

    - ``open`` connects; :class:`DeviceError` when the device cannot be reached. Calling it again
      after a failure retries.
    - ``command`` puts ``voltage_v`` (or ``q_um``, for a closed-loop controller) on the stage and
      returns once the device has it. It raises :class:`DeviceError` when the write fails or the
      device reads back something else than was written; the message names the device and what
      was expected versus what was read. It raises ``ValueError`` (and writes nothing) for a value
      the device cannot represent. The caller has already checked ``voltage_v`` against the
      operator's ``[v_min, v_max]``; an actuator never widens that.
      ``x_um`` is the target the command serves, when the caller knows it (``None``: a raw
      command, whose target is ``q_um``).
    - ``close`` releases the device; safe to call twice and after a failed ``open``.
    - ``read_back`` (optional; after ``open``): what the output holds now, ``("voltage_v", V)`` or
      ``("q_um", q)``, so that the first move after a start is ramped from where the stage is;
      None when the device cannot say (the default). :class:`DeviceError` as for ``command``.

    - ``check_command`` (optional, pure): ``ValueError`` when ``command`` would refuse these values (a
      template field outside its limits), so that a goal the device can never take is dropped before
      anything is written or recorded. The default takes every command.
    - ``sent_voltage`` (optional, pure): the voltage the device would actually receive for
      ``voltage_v`` once quantized or formatted (a DAC's count, a template's digits). The caller checks
      *that* against the limits before ``command``, and counts it as where the stage is after. The
      default: ``voltage_v`` itself (a device that takes the float as it is).

    ``description`` names the device in messages and in ``status``. ``limits_v`` is the operator's
    ``[v_min, v_max]``, set by whoever drives the actuator before ``open``: a device that quantizes
    (a DAC's counts) rounds a voltage near a limit towards the inside. ``limits_q_um`` is the command
    range those voltages mean (``[q(v_min), q(v_max)]``, set with it): a device that is sent positions
    (a controller's ``MOV``) keeps them within it the same way.
    """

    description: str = "actuator"
    limits_v: tuple[float, float] | None = None
    limits_q_um: tuple[float, float] | None = None

    async def on_target(self) -> bool:
        """Whether the stage has settled on the last value written: a closed-loop controller's own
        on-target state (GCS ``ONT?``). The daemon's ``done: reached`` waits for it, asking every ramp
        period. Default True: a device without one can say no more than that the write returned."""
        return True

    @abstractmethod
    async def open(self) -> None: ...

    @abstractmethod
    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None: ...

    @abstractmethod
    async def close(self) -> None: ...

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        return None

    def check_command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        return None

    def sent_voltage(self, voltage_v: float) -> float:
        return voltage_v


#: an output step (one count of a DAC) coarser than this share of ``[v_min, v_max]`` is refused: fewer
#: than a hundred distinct voltages is a wrong scale (volts per count taken for counts per volt, mV for V)
MAX_OUTPUT_STEP_FRACTION = 0.01
#: ... or coarser than the voltage of this much travel: the daemon corrects drift of tens of nanometres,
#: and an output that moves in steps of micrometres writes a 4.73 V command as 0 V with the status ok
MAX_OUTPUT_STEP_UM = 1.0


def output_step_problem(step_v: float, v_min: float, v_max: float, volts_per_um: float) -> str | None:
    """Why an output whose finest step in ``[v_min, v_max]`` is ``step_v`` volts is too coarse (None: fine).

    A refusal, not a warning: such an output silently serves other voltages than the commands (the
    status stays ok), which is the failure a config check exists to prevent; no DAC worth wiring to a
    piezo amplifier comes near it (12 bits over 10 V is 2.4 mV, 0.12 um at 0.02 V/um).
    """
    by_range_v = MAX_OUTPUT_STEP_FRACTION * (v_max - v_min)
    by_travel_v = MAX_OUTPUT_STEP_UM * abs(volts_per_um)
    exceeded: list[str] = []
    if step_v > by_range_v:
        exceeded.append(f"{by_range_v:.4g} V ({MAX_OUTPUT_STEP_FRACTION:.0%} of [v_min, v_max] = "
                        f"[{v_min:g}, {v_max:g}] V)")
    if step_v > by_travel_v:
        exceeded.append(f"{by_travel_v:.4g} V ({MAX_OUTPUT_STEP_UM:g} um of travel at volts_per_um = "
                        f"{volts_per_um:g})")
    if not exceeded:
        return None
    return (f"one output step is {step_v:.4g} V, coarser than {' and '.join(exceeded)}: a command would be written "
            f"up to {step_v:.4g} V off")


@dataclass(frozen=True)
class OutputClaim:
    """Outputs one actuator writes on one device: ``device`` names the device for messages and identifies it
    (``Modbus hub 'out', unit id 1``), ``outputs`` the outputs on it (``holding register 10``). Two axes
    claiming one output would each undo the other's commands, and neither's limits would hold."""

    device: str
    outputs: frozenset[str]


def shared_output_problems(actuators: Sequence[tuple[str, ActuatorOptions]]) -> list[str]:
    """Each output claimed by two actuators (``(where, options)``, e.g. ``("axes[1] (y).actuator", ...)``),
    named with both: one output drives one axis. The one check for every plugin (:meth:`ActuatorOptions.claims`)."""
    owners: dict[tuple[str, str], str] = {}
    problems: list[str] = []
    for where, options in actuators:
        for claim in options.claims():
            shared = sorted(output for output in claim.outputs if (claim.device, output) in owners)
            if shared:
                first = owners[(claim.device, shared[0])].removesuffix(".actuator")
                verb = "is" if len(shared) == 1 else "are"
                problems.append(f"{where}: {' and '.join(shared)} of {claim.device} {verb} already the output of "
                                f"{first}: one output drives one axis (give each axis its own)")
            for output in claim.outputs:
                owners.setdefault((claim.device, output), where)
    return problems


class ActuatorOptions(StrictModel):
    """The ``[actuator]`` keys a plugin owns (everything but the core's gain, limits and motion keys).

    A plugin subclasses it with its own keys and names it as ``actuator_model``. Strict (a
    :class:`StrictModel`): a misspelt key is an error naming ``actuator.<key>``, and no ``"0.001"``
    for 0.001.
    """

    kind: str

    def voltage_range_problem(self, v_min: float, v_max: float, volts_per_um: float) -> str | None:
        """Why the device cannot take every voltage in ``[v_min, v_max]`` finely enough (None: it can).

        Checked when the config is read, so a command the limits allow is never refused later, nor
        written as another voltage: an output whose one step is coarser than the stage can use (see
        :func:`output_step_problem`; ``volts_per_um`` is the ``[actuator]`` gain) is refused too.
        A problem that starts with one of this model's keys (``command: ...``) is reported as
        ``actuator.command: ...`` (the key's line), else as ``actuator: ...``.
        """
        return None

    def config_warnings(self, v_min: float, v_max: float, volts_per_um: float, offset_v: float) -> list[str]:
        """What ``check-config`` warns about (the daemon accepts it): e.g. a resolution coarser than the
        stage needs. Lines named like :meth:`voltage_range_problem`'s (``command: ...``)."""
        return []

    def hub_name(self) -> str | None:
        """The ``[[hubs]]`` entry the actuator shares with sensors (None: none); see :meth:`SensorConfig.hub_name`."""
        return None

    def claims(self) -> list[OutputClaim]:
        """The outputs this actuator writes (:class:`OutputClaim`): two axes claiming one are refused when the
        config is read (:func:`shared_output_problems`). The default: none (an output of its own, e.g. a
        simulated stage's axis); a plugin whose outputs share a device declares them."""
        return []


class DriverSetupError(ValueError):
    """A plugin refused its configuration or could not build its objects (the message names the kind)."""


class DriverPlugin(ABC):
    """What an entry point in ``nanodrift.drivers`` names: a driver kind, and what it can do.

    ``config_model`` validates one ``[[sensors]]`` entry of this kind (including the common keys);
    ``create`` gets every validated entry of this kind at once so it can share connections and
    merge contiguous channels into one request. The rest is declared, not discovered:

    - ``section``/``section_model``: a top-level table this plugin owns and validates
      (``[simulation]`` for the simulated cell);
    - ``hub_model``: validates the ``[[hubs]]`` its sensors (and its actuator) name with ``hub = ...``,
      which they report through ``hub_name()``;
    - ``actuator_model``: validates ``[actuator]`` when its ``kind`` names this plugin (None: this
      plugin cannot move the stage); ``create_actuator`` then builds the actuator, sharing the
      connections (``context.resources``) the plugin's sensor groups use.

    A plugin that *is* the cell (the simulated one) subclasses :class:`VirtualCellPlugin` instead.
    """

    name: ClassVar[str]
    config_model: ClassVar[type[SensorConfig]]
    section: ClassVar[str | None] = None
    section_model: ClassVar[type[BaseModel] | None] = None
    hub_model: ClassVar[type[BaseModel] | None] = None
    actuator_model: ClassVar[type[ActuatorOptions] | None] = None

    @abstractmethod
    def create(self, configs: Sequence[SensorConfig], context: DriverContext) -> list[SensorGroup]: ...

    def create_actuator(self, config: ActuatorOptions, context: DriverContext) -> Actuator:
        """The actuator ``[actuator]`` describes (``config`` validated by ``actuator_model``).

        Called after ``create`` built the sensor groups, so connections they opened are in
        ``context.resources`` to share (one lock per connection).
        """
        raise DriverSetupError(f"driver {self.name!r} cannot move the stage")

    def create_actuators(self, configs: Sequence[ActuatorOptions], context: DriverContext) -> list[Actuator]:
        """The actuators of several axes of one multi-axis cell (``[axes.actuator]`` of this kind, in the
        cell's axis order). The default: :meth:`create_actuator` for each. A plugin whose outputs share a
        device (one connection, one port) overrides it to build them on one object."""
        return [self.create_actuator(config, context) for config in configs]

    def config_problems(self, sensors: Sequence[tuple[int, SensorConfig]],
                        actuator: ActuatorOptions | None) -> list[str]:
        """Problems only seen across entries, found when the config is read (so check-config reports
        them): this kind's sensors (with their index in ``[[sensors]]``) and, when ``[actuator]`` is
        of this kind, its options. Each line names where, in the errors' form:
        ``sensors[2] (T3).port: ...`` or ``actuator.port: ...``."""
        return []

    def config_warnings(self, sensors: Sequence[tuple[int, SensorConfig]],
                        actuator: ActuatorOptions | None) -> list[str]:
        """What ``check-config`` warns about across entries (the daemon accepts it), named like
        :meth:`config_problems`' lines: e.g. a shared connection whose answers could be mismatched."""
        return []


class VirtualCellPlugin(DriverPlugin):
    """A plugin that *is* the cell (readings and stage simulated): optional, found with ``isinstance``
    (``nanodrift.drivers.registry.virtual_cell_plugin``).

    It supplies the clock (``make_clock``) and, when its section is present without ``[[sensors]]``,
    the sensors (``default_sensors``). A reload never switches between a virtual and a real cell, and a
    virtual cell's stage is moved only by its own actuator.
    """

    @abstractmethod
    def default_sensors(self, section: BaseModel) -> list[SensorConfig]:
        """Sensors implied by this plugin's section when the config lists none."""

    def default_sensor_axes(self, section: BaseModel) -> dict[str, str]:
        """The axis each of :meth:`default_sensors`' position sensors measures (``[[sensors]] axis``; none: x)."""
        return {}

    def default_axes(self, section: BaseModel) -> list[dict[str, Any]]:
        """``[[axes]]`` tables (as written in TOML) implied by this plugin's section when the config has none:
        a simulated multi-axis stage; empty (the default): a one-axis cell."""
        return []

    @abstractmethod
    def make_clock(self, section: BaseModel | None, *, virtual_start_s: float | None = None) -> Clock:
        """The cell's clock: scaled wall time for the daemon, or (``virtual_start_s`` given) a virtual
        clock whose sleeps take no wall time, for procedures."""

    def timing_warnings(self, section: BaseModel | None, sensors: Sequence[tuple[int, SensorConfig]]) -> list[str]:
        """What ``check-config`` warns about the sensors' timing on this cell's clock (every sensor: the
        daemon judges them all on it), e.g. a ``max_age_s`` a sped-up clock cannot keep fresh."""
        return []

    def label_clock(self, clock: Clock) -> Callable[[], float]:
        """What labels records on this cell (unix seconds): the wall clock, unless ``clock`` (from
        :meth:`make_clock`) runs faster than it, so that a simulated day is recorded as a day."""
        return time.time
