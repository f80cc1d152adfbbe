"""The Zenoh wire format in one place: keys, a target in, every payload out (README, Zenoh keys).

Bytes in, bytes out, no session: the contract can be tested (and is pinned byte for byte in
``tests/bus/test_payload_bytes.py``) without a network.

- :func:`key_prefix` and :class:`Keys`: the key expressions under ``<prefix>/<cell>/`` (``nanodrift/<cell>/``
  by default).
- :func:`parse_target`: a client's payload -> :class:`Target`, or a :class:`Refusal` saying what was
  wrong. The usual target is matched by a regular expression without building a dict.
- :class:`Command`: one answer on ``command``; :func:`encode_command` is the one encoder that turns
  it into bytes. :func:`encode_error` and :func:`encode_telemetry` write the other payloads.
- :func:`encode_done`: how a served command ended; :func:`parse_stop` / :func:`encode_stop_reply`: a
  client's ``stop`` and the answer to a ``stop`` query.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from operator import attrgetter
from types import MappingProxyType
from typing import Any

#: targets larger than this are refused unread (a target is ~40 bytes)
MAX_PAYLOAD_BYTES = 4096
#: longest string id echoed back
MAX_ID_CHARS = 200
_ID_LIMIT = 2**63


#: the contract's default key tree (``[zenoh] prefix``; the client's ``prefix=`` and ``--prefix``)
DEFAULT_PREFIX = "nanodrift"


def key_prefix(cell: str, prefix: str = DEFAULT_PREFIX) -> str:
    """``<prefix>/<cell>`` (``nanodrift/<cell>`` by default), under which every key of a cell lives
    (``cell`` ``*``: every cell's)."""
    return f"{prefix}/{cell}"


class Keys:
    """The contract's key expressions for one cell, under ``<prefix>/<cell>/`` (``[zenoh] prefix``, default
    ``nanodrift``; validated by :func:`nanodrift.settings.prefix_problem` where it comes in)."""

    def __init__(self, cell: str, prefix: str = DEFAULT_PREFIX) -> None:
        self.prefix = key_prefix(cell, prefix)
        self.target = f"{self.prefix}/target"
        self.command = f"{self.prefix}/command"
        self.error = f"{self.prefix}/error"
        self.compensate = f"{self.prefix}/compensate"
        self.status = f"{self.prefix}/status"
        self.alive = f"{self.prefix}/alive"
        self.health = f"{self.prefix}/health"
        self.done = f"{self.prefix}/done"
        self.stop = f"{self.prefix}/stop"

    def telemetry(self, role: str, channel: str, axis: str | None = None) -> str:
        """``sensors/temperature/<channel>``, ``sensors/position``; a multi-axis cell's position sensors each
        on ``sensors/position/<axis>`` (``axis`` given), so a client tells its axes apart."""
        if role == "position":
            return f"{self.prefix}/sensors/position" if axis is None else f"{self.prefix}/sensors/position/{axis}"
        return f"{self.prefix}/sensors/temperature/{channel}"


# --- a target in --------------------------------------------------------------------------------


class Refusal(Exception):
    """A target that gets an ``error`` instead of a ``command``; ``kind`` feeds the counters."""

    __slots__ = ("id", "kind", "message")

    def __init__(self, kind: str, message: str, target_id: Any = None) -> None:
        super().__init__(message)
        self.kind = kind
        self.message = message
        self.id = target_id


@dataclass(slots=True)
class Target:
    id: str | int | None
    x_um: float


class Oversized(bytes):
    """Stands for a payload too large to copy out of Zenoh at all; ``size`` is its length."""

    size: int

    @classmethod
    def of(cls, size: int) -> Oversized:
        marker = cls()
        marker.size = size
        return marker


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
    return validate_target(doc)


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


def validate_target(doc: Any) -> Target:
    """The full checks on a decoded document (what the fast path in :func:`parse_target` must agree with)."""
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


# --- payloads out -------------------------------------------------------------------------------


@dataclass(slots=True, kw_only=True)
class Command:
    """One answer on ``command`` (and a ``compensate`` reply), built by keyword only. The fields are
    the payload's keys, in wire order; the optional ones at the end are left out of the payload when
    None (a procedure step has a ``procedure`` and no ``extrapolating``; the daemon's command ends with
    ``q_sigma_um`` and, with ``[adapt] mode = "bias"``, ``correction_um`` and ``q_sigma_adapted_um``).
    Treat it as immutable once encoded."""

    id: str | int | None
    x_um: float
    q_um: float
    voltage_v: float
    temperatures_c: Mapping[str, float]
    model: str | None
    t: float  # unix seconds
    extrapolating: Sequence[str] | None = None  # names outside the model's training range ("x", channels)
    procedure: str | None = None  # the calibration or validation that sent this step
    q_sigma_um: float | None = None  # standard uncertainty of the model's q at this target and temperatures
    correction_um: float | None = None  # the bias tracker's correction, already inside q_um (adaptation on)
    #: the standard uncertainty of the corrected command, what the tracker leaves (adaptation on)
    q_sigma_adapted_um: float | None = None


_KEYS = tuple(f.name for f in fields(Command))
_OPTIONAL = frozenset(f.name for f in fields(Command) if f.default is None)
_values = attrgetter(*_KEYS)
_encode_string = json.JSONEncoder().encode  # a str (or None) -> its JSON literal (C fast path)
#: (temperatures, model, with a correction, the daemon's command as a %-template with the first two filled in)
_template_cache: tuple[object, object, bool, str] = (object(), object(), False, "")


def command_doc(command: Command) -> dict[str, Any]:
    """``command`` as the JSON object of the contract (what :func:`encode_command` writes)."""
    doc: dict[str, Any] = {}
    for key, value in zip(_KEYS, _values(command), strict=True):
        if value is None and key in _OPTIONAL:
            continue
        if key == "temperatures_c":
            value = dict(value)
        elif key == "extrapolating":
            value = list(value)
        doc[key] = value
    return doc


def _daemon_template(temps: Mapping[str, float], model: str | None, correction: bool) -> str:
    """The daemon's command (every required key, then ``extrapolating``, ``q_sigma_um`` and, when
    ``correction``, ``correction_um`` and ``q_sigma_adapted_um``) with its temperatures and model
    written in, the rest left as %-fields: id, x_um, q_um, voltage_v, t, extrapolating, q_sigma_um[,
    correction_um, q_sigma_adapted_um]."""
    parts = []
    for key in _KEYS:
        if key == "temperatures_c":
            value = dumps(dict(temps)).decode().replace("%", "%%")
        elif key == "model":
            value = _encode_string(model).replace("%", "%%")
        elif key == "extrapolating":
            value = "[%s]"
        elif key == "q_sigma_um" or (key in ("correction_um", "q_sigma_adapted_um") and correction):
            value = "%s"
        elif key in _OPTIONAL:
            continue
        else:
            value = "%s"
        parts.append(f"{_encode_string(key)}:{value}")
    return "{" + ",".join(parts) + "}"


def encode_command(command: Command) -> bytes:
    """``command`` as compact JSON, equal to :func:`dumps` of :func:`command_doc`.

    The daemon's commands (finite floats, an int/str/None id, temperatures in a read-only mapping)
    take one string format: ``json.dumps`` of a dict costs twice as much on the hot path. The
    format, with the temperatures and the model id written in, is kept while the same two objects
    come back (the compensator makes a new mapping once per sensor update, not per target).
    Anything else (a procedure step, numpy numbers, a NaN) goes through ``json``.
    """
    global _template_cache
    target_id, x, q, v, temps, model, t, extrapolating, procedure, sigma, correction, adapted = _values(command)
    c = 0.0 if correction is None else correction
    a = 0.0 if correction is None else adapted  # with a correction comes its σ (None: through json)
    if (type(x) is float and type(q) is float and type(v) is float and type(t) is float and type(sigma) is float
            and type(c) is float and type(a) is float and procedure is None and extrapolating is not None
            and (x + q + v + t + sigma + c + a) - (x + q + v + t + sigma + c + a) == 0.0):
        if target_id is None:
            id_json = "null"
        elif type(target_id) is int:
            id_json = int.__repr__(target_id)
        elif type(target_id) is str:
            id_json = _encode_string(target_id)
        else:
            return dumps(command_doc(command))
        corrected = correction is not None
        cached_temps, cached_model, cached_corrected, template = _template_cache
        if temps is not cached_temps or model is not cached_model or corrected is not cached_corrected:
            template = _daemon_template(temps, model, corrected)
            if type(temps) is MappingProxyType:  # read-only: safe to remember by identity
                _template_cache = (temps, model, corrected, template)
        names = ",".join([_encode_string(n) for n in extrapolating]) if extrapolating else ""
        if corrected:
            return (template % (id_json, x, q, v, t, names, sigma, c, a)).encode()
        return (template % (id_json, x, q, v, t, names, sigma)).encode()
    return dumps(command_doc(command))


def encode_error(refusal: Refusal) -> bytes:
    """The ``error`` payload (and a ``compensate`` reply error) for a refused target."""
    return dumps({"id": refusal.id, "error": refusal.message, "kind": refusal.kind})


def encode_telemetry(value: float | None, unit: str, t: float | None, state: str, reason: str = "") -> bytes:
    """A ``sensors/...`` sample; ``reason`` only when there is one (a fault, a stale channel)."""
    doc: dict[str, Any] = {"value": value, "unit": unit, "t": t, "state": state}
    if reason:
        doc["reason"] = reason
    return dumps(doc)


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


# --- how a served command ended, and a stop --------------------------------------------------------

#: the states a ``done`` reports (README, Zenoh keys ``done``)
DONE_STATES = ("reached", "superseded", "stopped", "failed")


def encode_done(target_id: str | int | None, state: str, t: float, voltage_v: float | Mapping[str, float | None] | None,
                error: str | None = None) -> bytes:
    """The ``done`` payload: ``{"id", "state", "t", "voltage_v", "error"}``, every key always present;
    ``voltage_v`` what the outputs hold (a number in a one-axis cell, ``{axis: V}`` in a cell of several,
    null where it is unknown), ``error`` null unless the state is ``failed``."""
    if state not in DONE_STATES:
        raise ValueError(f"done state {state!r} is not one of {', '.join(DONE_STATES)}")
    held = dict(voltage_v) if isinstance(voltage_v, Mapping) else voltage_v
    return dumps({"id": target_id, "state": state, "t": t, "voltage_v": held,
                  "error": error if state == "failed" else None})


@dataclass(slots=True)
class Stop:
    """A client's ``stop``: its id (None when it has none)."""

    id: str | int | None


def parse_stop(payload: bytes, max_bytes: int = MAX_PAYLOAD_BYTES) -> Stop:
    """Decode a ``stop``: ``{"id": string|int, optional}`` or an empty payload; other keys are ignored (a stop
    that says more still stops). A :class:`Refusal` (kind ``bad_payload``) for anything else."""
    if len(payload) > max_bytes or type(payload) is Oversized:
        size = payload.size if isinstance(payload, Oversized) else len(payload)
        raise Refusal("bad_payload", f"stop payload of {size} bytes exceeds the {max_bytes}-byte limit")
    if not payload.strip(b" \t\n\r"):
        return Stop(None)
    try:
        doc = json.loads(payload.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as error:
        reason = "not UTF-8 text" if isinstance(error, UnicodeDecodeError) else f"not valid JSON ({error})"
        raise Refusal("bad_payload", f"stop payload is {reason}; expected {{\"id\": ...}} or nothing") from None
    if not isinstance(doc, dict):
        raise Refusal("bad_payload", f"stop payload must be a JSON object, got {type(doc).__name__}")
    stop_id, problem = _id_of(doc)
    if problem:
        raise Refusal("bad_payload", f"stop: {problem}")
    return Stop(stop_id)


def encode_stop_reply(stop_id: str | int | None, voltage_v: float | Mapping[str, float | None] | None) -> bytes:
    """A ``stop`` query's reply, once every ramp has ended: ``{"id", "voltage_v", "held": true}``, ``voltage_v``
    what each output holds (a number in a one-axis cell, ``{axis: V}`` in a cell of several; null where
    unknown)."""
    held = dict(voltage_v) if isinstance(voltage_v, Mapping) else voltage_v
    return dumps({"id": stop_id, "voltage_v": held, "held": True})


def encode_stop_error(stop_id: str | int | None, message: str) -> bytes:
    """A ``stop`` query's reply error (a bad payload): ``{"id", "error", "kind": "bad_payload"}``."""
    return dumps({"id": stop_id, "error": message, "kind": "bad_payload"})


# --- a multi-axis cell --------------------------------------------------------------------------


@dataclass(slots=True)
class CellTarget:
    """A multi-axis target: every axis of the cell, ``positions_um`` in the cell's axis order."""

    id: str | int | None
    positions_um: dict[str, float]


def parse_cell_target(payload: bytes, axes: Sequence[str], max_bytes: int = MAX_PAYLOAD_BYTES) -> CellTarget:
    """Decode ``{"x_um": .., "y_um": .., "id": ..}`` for a cell with ``axes``; a :class:`Refusal` naming a
    missing or extra axis, or anything else wrong (the one-axis rules: finite numbers, the id's type)."""
    if len(payload) > max_bytes or type(payload) is Oversized:
        size = payload.size if isinstance(payload, Oversized) else len(payload)
        raise Refusal("bad_payload", f"payload of {size} bytes exceeds the {max_bytes}-byte limit")
    expected = ", ".join(f'"{a}_um": number' for a in axes)
    try:
        doc = json.loads(payload.decode("utf-8"))
    except (UnicodeDecodeError, ValueError, RecursionError) as error:
        reason = "not UTF-8 text" if isinstance(error, UnicodeDecodeError) else f"not valid JSON ({error})"
        raise Refusal("bad_payload", f"payload is {reason}; expected {{{expected}, \"id\": ...}}") from None
    if not isinstance(doc, dict):
        raise Refusal("bad_payload", f"payload must be a JSON object, got {type(doc).__name__}")
    target_id, id_problem = _id_of(doc)
    if id_problem:
        raise Refusal("bad_payload", id_problem)
    missing = [f"{a}_um" for a in axes if f"{a}_um" not in doc]
    if missing:
        raise Refusal("bad_payload", f"missing field {', '.join(repr(m) for m in missing)}: a target names every "
                      f"axis of the cell ({', '.join(axes)})", target_id)
    wanted = {f"{a}_um" for a in axes}
    extra = [k for k in doc if k not in wanted and k != "id"]
    if extra:
        axis_like = [k for k in extra if re.fullmatch(r"[a-z]_um", k)]
        what = (f"axis {', '.join(repr(k[0]) for k in axis_like)} is not an axis of this cell"
                if axis_like else f"unknown field {', '.join(repr(k) for k in extra)}")
        raise Refusal("bad_payload", f"{what} (axes: {', '.join(axes)})", target_id)
    positions: dict[str, float] = {}
    for axis in axes:
        key = f"{axis}_um"
        value = doc[key]
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise Refusal("bad_payload", f"'{key}' must be a number, got {type(value).__name__}", target_id)
        try:
            value = float(value)
        except OverflowError:
            value = math.inf
        if not math.isfinite(value):
            raise Refusal("bad_payload", f"'{key}' must be a finite number", target_id)
        positions[axis] = value
    return CellTarget(target_id, positions)


@dataclass(slots=True, kw_only=True)
class CellCommand:
    """One answer of a multi-axis cell on ``command``: every axis from one temperature snapshot. The
    payload (:func:`encode_cell_command`) is ``{"id", "<axis>_um"..., "q_um": {axis: ..}, "voltage_v": {..},
    "q_sigma_um": {..}, "temperatures_c", "model", "t", "extrapolating"[, "correction_um": {..},
    "q_sigma_adapted_um": {..}]}``."""

    id: str | int | None
    positions_um: Mapping[str, float]
    q_um: Mapping[str, float]
    voltage_v: Mapping[str, float]
    q_sigma_um: Mapping[str, float]
    temperatures_c: Mapping[str, float]
    model: str | None
    t: float  # unix seconds
    extrapolating: Sequence[str]  # axis names and channels outside the model's training range
    correction_um: Mapping[str, float] | None = None  # the bias correction per axis, inside q_um (adaptation on)
    #: per corrected axis, the standard uncertainty of its corrected command (adaptation on)
    q_sigma_adapted_um: Mapping[str, float] | None = None


def cell_command_doc(command: CellCommand) -> dict[str, Any]:
    """``command`` as the JSON object of the contract, keys in wire order."""
    doc: dict[str, Any] = {"id": command.id}
    for axis, value in command.positions_um.items():
        doc[f"{axis}_um"] = value
    doc["q_um"] = dict(command.q_um)
    doc["voltage_v"] = dict(command.voltage_v)
    doc["q_sigma_um"] = dict(command.q_sigma_um)
    doc["temperatures_c"] = dict(command.temperatures_c)
    doc["model"] = command.model
    doc["t"] = command.t
    doc["extrapolating"] = list(command.extrapolating)
    if command.correction_um is not None:
        doc["correction_um"] = dict(command.correction_um)
    if command.q_sigma_adapted_um is not None:
        doc["q_sigma_adapted_um"] = dict(command.q_sigma_adapted_um)
    return doc


def encode_cell_command(command: CellCommand) -> bytes:
    """A multi-axis ``command`` as compact JSON (``null`` for a non-finite number, as :func:`dumps`)."""
    return dumps(cell_command_doc(command))
