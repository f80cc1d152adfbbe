"""The Zenoh wire format in one place: keys, a target in, every payload out (README, Zenoh keys).

Bytes in, bytes out, no session: the contract can be tested (and is pinned byte for byte in
``tests/bus/test_payload_bytes.py``) without a network. The domain types (:class:`nanodrift.compensation.Target`,
``Command``, ``Refusal``) live in the pure core: this module only parses and encodes them, a cell without
``[[axes]]`` in the one-axis shapes (scalar ``q_um``, ``voltage_v``...), a cell of several per axis.
"""

from __future__ import annotations

import json
import math
import re
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from types import MappingProxyType
from typing import Any

from nanodrift.compensation import ONE_AXIS, Command, Refusal, Target, one_axis
from nanodrift.model.json_unique import DuplicateKeyError, loads_unique

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


def _decode(payload: bytes, max_bytes: int, expected: str, what: str = "payload") -> Any:
    """The JSON document of a payload of at most ``max_bytes``; a :class:`Refusal` saying what was expected."""
    if len(payload) > max_bytes or type(payload) is Oversized:
        size = payload.size if isinstance(payload, Oversized) else len(payload)
        raise Refusal("bad_payload", f"{what} of {size} bytes exceeds the {max_bytes}-byte limit")
    try:
        return loads_unique(payload.decode("utf-8"))  # NaN/Infinity parse, so the id survives; numbers are checked
    except DuplicateKeyError as error:
        raise Refusal("bad_payload", f"{what} names {error.key!r} twice (which value is meant cannot be told); "
                      f"expected {expected}") from None
    except (UnicodeDecodeError, ValueError, RecursionError) as error:
        reason = "not UTF-8 text" if isinstance(error, UnicodeDecodeError) else f"not valid JSON ({error})"
        raise Refusal("bad_payload", f"{what} is {reason}; expected {expected}") from None


def parse_target(payload: bytes, axes: Sequence[str] = ONE_AXIS, max_bytes: int = MAX_PAYLOAD_BYTES) -> Target:
    """Decode a target: ``{"x_um": number, "id": string|int}`` for a one-axis cell, or
    ``{"x_um": .., "y_um": .., "id": ..}`` naming every one of ``axes`` exactly; a :class:`Refusal` for
    anything else (a missing or extra axis named)."""
    if one_axis(axes) and len(payload) <= max_bytes and type(payload) is not Oversized:
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
                return Target(target_id, {"x": x})
    expected = ", ".join(f'"{a}_um": number' for a in axes)
    return validate_target(_decode(payload, max_bytes, f"{{{expected}, \"id\": ...}}"), axes)


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


def validate_target(doc: Any, axes: Sequence[str] = ONE_AXIS) -> Target:
    """The full checks on a decoded document (what the fast path in :func:`parse_target` must agree with).
    A one-axis cell ignores other keys; a cell of several refuses them."""
    if not isinstance(doc, dict):
        raise Refusal("bad_payload", f"payload must be a JSON object, got {type(doc).__name__}")
    target_id, id_problem = _id_of(doc)
    if id_problem:
        raise Refusal("bad_payload", id_problem)
    if one_axis(axes):
        if "x_um" not in doc:
            raise Refusal("bad_payload", "missing field 'x_um' (target position in um)", target_id)
    else:
        missing = [f"{a}_um" for a in axes if f"{a}_um" not in doc]
        if missing:
            raise Refusal("bad_payload", f"missing field {', '.join(repr(m) for m in missing)}: a target names "
                          f"every axis of the cell ({', '.join(axes)})", target_id)
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
    return Target(target_id, positions)


# --- payloads out -------------------------------------------------------------------------------

#: a one-axis cell's command: the payload's keys in wire order (the optional ones, from ``extrapolating``
#: on, are left out when None); each per-axis mapping of :class:`Command` is written as its ``x`` number
_KEYS = ("id", "x_um", "q_um", "voltage_v", "temperatures_c", "model", "t", "extrapolating", "procedure",
         "q_sigma_um", "correction_um", "q_sigma_adapted_um")
_OPTIONAL = frozenset(_KEYS[7:])
_PER_AXIS = ("q_um", "voltage_v", "q_sigma_um", "correction_um", "q_sigma_adapted_um")
#: the per-axis numbers that may be non-finite by design (a model without a covariance has no σ); a non-finite
#: position, q or voltage is refused before a command exists
_SIGMAS = frozenset(("q_sigma_um", "q_sigma_adapted_um"))
_encode_string = json.JSONEncoder().encode  # a str (or None) -> its JSON literal (C fast path)
#: (temperatures, model, with a correction, the daemon's command as a %-template with the first two filled in)
_template_cache: tuple[object, object, bool, str] = (object(), object(), False, "")


def _x(values: Mapping[str, float] | None) -> float | None:
    return values["x"] if values is not None else None


def _number(value: float | None) -> float | None:
    """A non-finite number (the σ of a model without a covariance) as the null the wire has for it, written
    into the document: :func:`dumps`' first pass then succeeds instead of raising and walking the document
    again: a 3-axis command of a model without σ took 21 µs, now 11 µs (``timeit``, hot; the daemon's
    answers run on a CPU just woken, several times slower; benchmarks/daemon_latency.py ``--axes 3``)."""
    return value if value is None or math.isfinite(value) else None


def _axis_values(key: str, per_axis: Mapping[str, float] | None) -> dict[str, float | None]:
    if key in _SIGMAS:
        return {axis: _number(value) for axis, value in (per_axis or {}).items()}
    return dict(per_axis or {})


def command_doc(command: Command) -> dict[str, Any]:
    """``command`` as the JSON object of the contract (what :func:`encode_command` writes): a one-axis
    cell's with numbers, or a cell of several's, ``<axis>_um`` each and per-axis objects."""
    if not one_axis(command.positions_um):
        doc: dict[str, Any] = {"id": command.id}
        doc.update({f"{axis}_um": value for axis, value in command.positions_um.items()})
        for key in ("q_um", "voltage_v", "q_sigma_um"):
            doc[key] = _axis_values(key, getattr(command, key))
        doc.update(temperatures_c=dict(command.temperatures_c), model=command.model, t=command.t,
                   extrapolating=list(command.extrapolating or ()))
        for key in ("correction_um", "q_sigma_adapted_um"):
            if getattr(command, key) is not None:
                doc[key] = _axis_values(key, getattr(command, key))
        return doc
    doc = {}
    for key in _KEYS:
        value: Any = command.positions_um["x"] if key == "x_um" else getattr(command, key)
        if key in _PER_AXIS:
            value = _x(value)
        if value is None and key in _OPTIONAL:
            continue
        if key == "temperatures_c":
            value = dict(value)
        elif key == "extrapolating":
            value = list(value)
        elif key in _SIGMAS:
            value = _number(value)
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

    A one-axis cell's commands (finite floats, an int/str/None id, temperatures in a read-only mapping)
    take one string format: ``json.dumps`` of a dict costs twice as much on the hot path. The
    format, with the temperatures and the model id written in, is kept while the same two objects
    come back (the compensator makes a new mapping once per sensor update, not per target).
    Anything else (a procedure step, numpy numbers, a NaN, a cell of several) goes through ``json``.
    """
    global _template_cache
    if not one_axis(command.positions_um):
        return dumps(command_doc(command))
    x, q, v, sigma = command.positions_um["x"], command.q_um["x"], command.voltage_v["x"], _x(command.q_sigma_um)
    target_id, temps, model, t, extrapolating = (command.id, command.temperatures_c, command.model, command.t,
                                                 command.extrapolating)
    correction, adapted = _x(command.correction_um), _x(command.q_sigma_adapted_um)
    c = 0.0 if correction is None else correction
    a = 0.0 if correction is None else adapted  # with a correction comes its σ (None: through json)
    if (type(x) is float and type(q) is float and type(v) is float and type(t) is float and type(sigma) is float
            and type(c) is float and type(a) is float and command.procedure is None and extrapolating is not None
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


#: made once: ``json.dumps`` given any option builds a new encoder at every call (~1.5 µs of each ``done``)
_COMPACT = json.JSONEncoder(allow_nan=False, separators=(",", ":"))
_COMPACT_NAN = json.JSONEncoder(separators=(",", ":"))


def dumps(doc: Mapping[str, Any]) -> bytes:
    """JSON for the bus; non-finite floats (a faulted reading) become null."""
    try:
        return _COMPACT.encode(doc).encode()
    except ValueError:
        return _COMPACT_NAN.encode(_finite(doc)).encode()


def _finite_float(value: Any) -> bool:
    return type(value) is float and math.isfinite(value)


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
    if type(target_id) is int and state != "failed" and _finite_float(t) and (
            voltage_v is None or _finite_float(voltage_v)):
        # a one-axis cell's done of an integer id, in the bytes ``dumps`` writes (a float's repr, compact):
        # it is told in the loop's write cycle and after each answer, mostly on a cold CPU just woken, where
        # the encoder's code took ~140 µs and this ~50 µs (a stretch targets wait behind: daemon_latency's p99)
        voltage = "null" if voltage_v is None else repr(voltage_v)
        return f'{{"id":{target_id},"state":"{state}","t":{t!r},"voltage_v":{voltage},"error":null}}'.encode()
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
    if len(payload) <= max_bytes and type(payload) is not Oversized and not payload.strip(b" \t\n\r"):
        return Stop(None)
    doc = _decode(payload, max_bytes, '{"id": ...} or nothing', "stop payload")
    if not isinstance(doc, dict):
        raise Refusal("bad_payload", f"stop payload must be a JSON object, got {type(doc).__name__}")
    stop_id, problem = _id_of(doc)
    if problem:
        raise Refusal("bad_payload", f"stop: {problem}")
    return Stop(stop_id)


def wire_voltage(held: Mapping[str, float | None], axes: Sequence[str]) -> float | dict[str, float | None] | None:
    """What the outputs hold as ``done`` and a stop's reply carry it: a one-axis cell's number, else ``{axis: V}``."""
    return held.get("x") if one_axis(axes) else dict(held)


def encode_stop_reply(stop_id: str | int | None, voltage_v: float | Mapping[str, float | None] | None) -> bytes:
    """A ``stop`` query's reply, once every ramp has ended: ``{"id", "voltage_v", "held": true}``, ``voltage_v``
    what each output holds (a number in a one-axis cell, ``{axis: V}`` in a cell of several; null where
    unknown)."""
    held = dict(voltage_v) if isinstance(voltage_v, Mapping) else voltage_v
    return dumps({"id": stop_id, "voltage_v": held, "held": True})


def encode_stop_error(stop_id: str | int | None, message: str) -> bytes:
    """A ``stop`` query's reply error (a bad payload): ``{"id", "error", "kind": "bad_payload"}``."""
    return dumps({"id": stop_id, "error": message, "kind": "bad_payload"})
