"""The daemon's decisions, without Zenoh or asyncio: testable with plain calls.

- :class:`SensorTable`: the last reading of every channel and its state (ok / stale / fault +
  reason); staleness is judged here, with the driver context's clock, not by the drivers.
- :func:`parse_target`: a client's payload -> :class:`Target`, or a :class:`Refusal` saying what
  was wrong (never an exception the caller has not planned for).
- :class:`Compensator`: target -> the command dict of the Zenoh contract, or a refusal (stale or
  faulted channel, outside the workspace, voltage outside the actuator's limits, no model).
"""

from __future__ import annotations

import json
import math
import re
from collections import Counter
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from daemon.config import ActuatorConfig
from daemon.model.model import Evaluator, Model
from drivers.base import Reading, SensorConfig, State

#: targets larger than this are refused unread (a target is ~40 bytes)
MAX_PAYLOAD_BYTES = 4096
#: longest string id echoed back
MAX_ID_CHARS = 200

UNITS = {"temperature": "degC", "position": "um"}


class Refusal(Exception):
    """A target that gets an ``error`` instead of a ``command``; ``kind`` feeds the counters."""

    __slots__ = ("id", "kind", "message")

    def __init__(self, kind: str, message: str, target_id: Any = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.id = target_id

    def payload(self) -> dict[str, Any]:
        return {"id": self.id, "error": self.message, "kind": self.kind}


@dataclass(slots=True)
class Target:
    id: str | int | None
    x_um: float


# --- sensors ----------------------------------------------------------------------------------


@dataclass(slots=True)
class ChannelEntry:
    name: str
    role: str
    unit: str
    max_age_s: float
    value: float | None = None
    t: float | None = None
    device_state: State = State.STALE  # STALE here means: nothing read yet
    reason: str = "no reading yet"


class SensorTable:
    """The latest reading of each configured channel."""

    def __init__(self, sensors: Sequence[SensorConfig]) -> None:
        self.entries: dict[str, ChannelEntry] = {
            s.name: ChannelEntry(s.name, s.role, UNITS.get(s.role, ""), s.max_age_s) for s in sensors
        }
        #: bumped by every change, so readers can cache what they derive from the entries
        self.version = 0

    def update(self, name: str, reading: Reading) -> ChannelEntry | None:
        entry = self.entries.get(name)
        if entry is None:
            return None
        self.version += 1
        entry.t = reading.t
        if reading.state == State.OK and math.isfinite(reading.value):
            entry.value = float(reading.value)
            entry.device_state = State.OK
            entry.reason = ""
        else:
            entry.device_state = State.FAULT
            entry.reason = reading.reason or ("non-finite value" if reading.state == State.OK else "fault")
        if reading.unit:
            entry.unit = reading.unit
        return entry

    def mark_fault(self, names: Iterable[str], reason: str) -> None:
        """The device behind these channels failed; they are faulted until a reading arrives."""
        self.version += 1
        for name in names:
            entry = self.entries.get(name)
            if entry is not None:
                entry.device_state = State.FAULT
                entry.reason = reason

    def state(self, name: str, now: float) -> tuple[State, str]:
        entry = self.entries.get(name)
        if entry is None:
            return State.FAULT, "no sensor configured for this channel"
        if entry.device_state == State.FAULT:
            return State.FAULT, entry.reason
        if entry.t is None or entry.device_state != State.OK:
            return State.STALE, entry.reason or "no reading yet"
        age = now - entry.t
        if age > entry.max_age_s:
            return State.STALE, f"last reading {age:.1f} s old (max_age_s {entry.max_age_s:g})"
        return State.OK, ""

    def snapshot(self, now: float) -> dict[str, dict[str, Any]]:
        out = {}
        for name, entry in self.entries.items():
            state, reason = self.state(name, now)
            out[name] = {
                "role": entry.role,
                "value": entry.value,
                "unit": entry.unit,
                "t": entry.t,
                "age_s": None if entry.t is None else round(now - entry.t, 6),
                "max_age_s": entry.max_age_s,
                "state": state.value,
                "reason": reason,
            }
        return out

    def position_channel(self) -> str | None:
        return next((e.name for e in self.entries.values() if e.role == "position"), None)


# --- targets ----------------------------------------------------------------------------------


def _id_of(doc: dict[str, Any]) -> tuple[Any, str | None]:
    """The target's id and, if it is unusable, why."""
    if "id" not in doc or doc["id"] is None:
        return None, None
    value = doc["id"]
    if isinstance(value, bool) or not isinstance(value, str | int):
        return None, f"'id' must be a string or an integer, got {type(value).__name__}"
    if isinstance(value, str) and len(value) > MAX_ID_CHARS:
        return None, f"'id' longer than {MAX_ID_CHARS} characters"
    if isinstance(value, int) and abs(value) >= _ID_LIMIT:
        return None, "'id' integer out of range (|id| < 2^63)"
    return value, None


_ID_LIMIT = 2**63


_WS = rb"[ \t\n\r]*"  # JSON's whitespace (not \s: \f and \v are not JSON)
_NUMBER = rb"(-?(?:0|[1-9][0-9]*)(?:\.[0-9]+)?(?:[eE][+-]?[0-9]+)?)"
_ID = rb'(?:(-?(?:0|[1-9][0-9]{0,17}))|"([A-Za-z0-9_.:/+@#-]{0,200})"|null)'  # no escapes: literal == value
_X_FIELD = rb'"x_um"' + _WS + rb":" + _WS + _NUMBER
_ID_FIELD = rb'"id"' + _WS + rb":" + _WS + _ID
#: the usual target, ``{"x_um": 12.5, "id": 7}`` in either order, matched without building a dict;
#: anything else (escapes, extra keys, odd ids, errors) goes through json.loads and full checks
_FAST_X_ID = re.compile(rb"\{" + _WS + _X_FIELD + _WS + rb"(?:," + _WS + _ID_FIELD + _WS + rb")?\}" + _WS)
_FAST_ID_X = re.compile(
    rb"\{" + _WS + _ID_FIELD.replace(b"(?:(", b"(?:(?P<i>", 1).replace(b'"(', b'"(?P<s>', 1) + _WS + rb"," + _WS
    + _X_FIELD.replace(b"(-?(?:0", b"(?P<x>-?(?:0", 1) + _WS + rb"\}" + _WS
)


class Oversized(bytes):
    """Stands for a payload too large to copy out of Zenoh at all; ``size`` is its length."""

    size: int

    @classmethod
    def of(cls, size: int) -> Oversized:
        marker = cls()
        marker.size = size
        return marker


def parse_target(payload: bytes, max_bytes: int = MAX_PAYLOAD_BYTES) -> Target:
    """Decode ``{"x_um": number, "id": string|int}``; a :class:`Refusal` for anything else."""
    if len(payload) > max_bytes or type(payload) is Oversized:
        size = payload.size if isinstance(payload, Oversized) else len(payload)
        raise Refusal("bad_payload", f"payload of {size} bytes exceeds the {max_bytes}-byte limit")
    match = _FAST_X_ID.fullmatch(payload.lstrip(b" \t\n\r"))
    if match is not None:
        x_text, int_id, str_id = match.groups()
    else:
        match = _FAST_ID_X.fullmatch(payload.lstrip(b" \t\n\r"))
        if match is not None:
            x_text, int_id, str_id = match["x"], match["i"], match["s"]
    if match is not None:
        x = float(x_text)
        if x - x == 0.0:  # finite (1e999 parses to inf: the full path words the refusal)
            target_id = int(int_id) if int_id is not None else (str_id.decode() if str_id is not None else None)
            return Target(target_id, x)
    try:
        doc = json.loads(payload.decode("utf-8"))  # NaN/Infinity parse, so the id survives; x is checked below
    except (UnicodeDecodeError, ValueError, RecursionError) as error:
        reason = "not UTF-8 text" if isinstance(error, UnicodeDecodeError) else f"not valid JSON ({error})"
        raise Refusal("bad_payload", f"payload is {reason}; expected {{\"x_um\": number, \"id\": ...}}") from None
    return _validate_target(doc)


def _validate_target(doc: Any) -> Target:
    if not isinstance(doc, dict):
        raise Refusal("bad_payload", f"payload must be a JSON object, got {type(doc).__name__}")
    target_id, id_problem = _id_of(doc)
    if id_problem:
        raise Refusal("bad_payload", id_problem)
    if "x_um" not in doc:
        raise Refusal("bad_payload", "missing field 'x_um' (target position in um)", target_id)
    x = doc["x_um"]
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise Refusal("bad_payload", f"'x_um' must be a number, got {type(x).__name__}", target_id)
    try:
        x = float(x)
    except OverflowError:
        x = math.inf
    if not math.isfinite(x):
        raise Refusal("bad_payload", "'x_um' must be a finite number", target_id)
    return Target(target_id, x)


# --- compensation -----------------------------------------------------------------------------


class Counters:
    """What the service did, for ``status``."""

    def __init__(self) -> None:
        self.targets = 0
        self.commands = 0
        self.errors: Counter[str] = Counter()
        self.reloads = 0
        self.reload_failures = 0

    def as_dict(self) -> dict[str, Any]:
        return {
            "targets": self.targets,
            "commands": self.commands,
            "errors": dict(self.errors),
            "errors_total": sum(self.errors.values()),
            "reloads": self.reloads,
            "reload_failures": self.reload_failures,
        }


class Compensator:
    """Turns a target into a command with the loaded model, the sensor table and actuator limits."""

    def __init__(
        self, model: Model | None, actuator: ActuatorConfig, table: SensorTable, model_problem: str = ""
    ) -> None:
        self.model = model
        self.actuator = actuator
        self.table = table
        self.model_problem = model_problem
        self.evaluator: Evaluator | None = model.evaluator() if model is not None else None
        self.channels: tuple[str, ...] = model.channels if model is not None else ()
        self.missing = tuple(c for c in self.channels if c not in table.entries)
        self.last_extrapolating: list[str] = []
        # the hot path: channel entries, training ranges and the command's JSON template, prepared once
        self._entries = tuple((c, table.entries[c]) for c in self.channels if c in table.entries)
        training = model.training if model is not None else None
        self._x_range = training.x_range if training is not None else (-math.inf, math.inf)
        self._ranges = tuple(
            (c, *training.channel_ranges[c]) for c in self.channels if training and c in training.channel_ranges
        )
        self._temps_fmt = "{" + ",".join(json.dumps(c).replace("%", "%%") + ":%r" for c in self.channels) + "}"
        model_json = json.dumps(model.id if model is not None else None).replace("%", "%%")
        self._command_fmt = (
            '{"id":%s,"x_um":%r,"q_um":%r,"voltage_v":%r,"temperatures_c":%s,"model":' + model_json
            + ',"t":%r,"extrapolating":[%s]}'
        )
        # what the model's channels say, derived once per table change instead of once per target
        self._version = -1
        self._fresh_until = -math.inf  # cell-clock time until which every model channel is ok
        self._temps: dict[str, float] = {}
        self._temps_json = "{}"
        self._temps_outside: list[str] = []  # channels outside their training range

    def _snapshot(self) -> None:
        self._version = self.table.version
        fresh_until = math.inf
        temps: dict[str, float] = {}
        for _, entry in self._entries:
            if entry.device_state is not State.OK or entry.t is None or entry.value is None:
                fresh_until = -math.inf
                break
            fresh_until = min(fresh_until, entry.t + entry.max_age_s)
            temps[entry.name] = entry.value
        if fresh_until == -math.inf or self.missing:
            self._fresh_until, self._temps, self._temps_json, self._temps_outside = -math.inf, {}, "{}", []
            return
        self._fresh_until = fresh_until
        self._temps = temps
        self._temps_json = self._temps_fmt % tuple(temps.values())
        self._temps_outside = [name for name, lo, hi in self._ranges if not lo <= temps[name] <= hi]

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        if self.evaluator is not None and temps:
            self.evaluator.observe(t, temps)

    def compensate(self, target: Target, now: float, unix_now: float) -> dict[str, Any]:
        """The command for ``target`` at ``now`` (the cell clock); raises :class:`Refusal`."""
        actuator = self.actuator
        x = target.x_um
        if not actuator.x_min_um <= x <= actuator.x_max_um:
            raise Refusal(
                "out_of_workspace",
                f"x_um {x:g} outside the workspace [{actuator.x_min_um:g}, {actuator.x_max_um:g}] um",
                target.id,
            )
        if self.evaluator is None or self.model is None:
            raise Refusal("no_model", f"no model loaded ({self.model_problem or 'none configured'})", target.id)
        if self.missing:
            raise Refusal(
                "missing_channel",
                f"channel {', '.join(self.missing)} needed by model {self.model.id} has no configured sensor",
                target.id,
            )
        if self._version != self.table.version:
            self._snapshot()
        if not now <= self._fresh_until:
            for name, _ in self._entries:  # say which channel and why
                state, reason = self.table.state(name, now)
                if state is not State.OK:
                    raise Refusal(state.value, f"channel {name} is {state.value}: {reason}", target.id)
            raise Refusal("stale", "temperatures not ready", target.id)
        temps = self._temps
        q = self.evaluator.value(x, now)
        voltage = actuator.offset_v + actuator.volts_per_um * q
        if not (actuator.v_min <= voltage <= actuator.v_max):  # NaN fails this too
            raise Refusal(
                "voltage_limit",
                f"command q {q:.4f} um needs {voltage:.4f} V, outside [{actuator.v_min:g}, {actuator.v_max:g}] V",
                target.id,
            )
        self.evaluator.moved(x, now)  # only a command that goes out moves the stage
        lo, hi = self._x_range
        extrapolating = [*self._temps_outside] if lo <= x <= hi else ["x", *self._temps_outside]
        self.last_extrapolating = extrapolating
        return {
            "id": target.id,
            "x_um": x,
            "q_um": q,
            "voltage_v": voltage,
            "temperatures_c": temps,
            "model": self.model.id,
            "t": unix_now,
            "extrapolating": extrapolating,
        }

    def encode(self, command: Mapping[str, Any]) -> bytes:
        """``command`` (from :meth:`compensate`) as compact JSON, equal to ``json.dumps`` of it, in one
        string format (json.dumps of the dict costs twice as much on the hot path)."""
        target_id = command["id"]
        if target_id is None:
            id_json = "null"
        elif type(target_id) is int:
            id_json = int.__repr__(target_id)
        else:
            id_json = _encode_string(target_id)
        temps = command["temperatures_c"]
        temps_json = self._temps_json if temps is self._temps else self._temps_fmt % tuple(temps.values())
        extrapolating = command["extrapolating"]
        return (self._command_fmt % (
            id_json, command["x_um"], command["q_um"], command["voltage_v"], temps_json, command["t"],
            ",".join([_encode_string(n) for n in extrapolating]) if extrapolating else "",
        )).encode()

    def model_info(self) -> dict[str, Any] | None:
        if self.model is None:
            return None
        training = self.model.training
        return {
            "id": self.model.id,
            "terms": self.model.term_names(),
            "channels": list(self.channels),
            "missing_channels": list(self.missing),
            "training": {
                "x_um": list(training.x_range),
                "channels": {c: list(r) for c, r in training.channel_ranges.items()},
                "rows": training.rows,
                "t_span_s": training.t_span_s,
            },
            "ready": self.evaluator.ready if self.evaluator is not None else False,
        }

    def extrapolating_now(self, now: float) -> list[str]:
        """Channels whose current reading lies outside the training range."""
        if self.model is None:
            return []
        temps = {
            name: entry.value
            for name in self.channels
            if (entry := self.table.entries.get(name)) is not None and entry.value is not None
        }
        return self.model.out_of_range(None, temps)


#: compact JSON encoder built once (``json.dumps`` with options builds one per call)
encode_json = json.JSONEncoder(separators=(",", ":"), check_circular=False).encode
_encode_string = json.JSONEncoder().encode  # a str -> its JSON literal (C fast path)


def dumps(doc: Mapping[str, Any]) -> bytes:
    """JSON for the bus; non-finite floats (a faulted reading) become null."""
    try:
        return json.dumps(doc, allow_nan=False, separators=(",", ":")).encode()
    except ValueError:
        return json.dumps(_finite(doc), separators=(",", ":")).encode()


def _finite(value: Any) -> Any:
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, Mapping):
        return {k: _finite(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_finite(v) for v in value]
    return value
