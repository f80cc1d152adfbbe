"""The wire format without a network: keys, target parsing (the regex fast path against json), the
one command encoder (its fast path against json), the other payloads."""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import replace
from types import MappingProxyType
from typing import Any

import numpy as np
import pytest
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.bus.protocol import (
    MAX_PAYLOAD_BYTES,
    Keys,
    Oversized,
    command_doc,
    dumps,
    encode_command,
    encode_error,
    encode_telemetry,
    parse_target,
    validate_target,
)
from nanodrift.compensation import Command, Refusal, Target


def test_keys_follow_the_contract() -> None:
    keys = Keys("c1")
    assert (keys.target, keys.command, keys.error) == ("nanodrift/c1/target", "nanodrift/c1/command",
                                                       "nanodrift/c1/error")
    assert (keys.compensate, keys.status, keys.alive) == ("nanodrift/c1/compensate", "nanodrift/c1/status",
                                                          "nanodrift/c1/alive")
    assert keys.telemetry("temperature", "T3") == "nanodrift/c1/sensors/temperature/T3"
    assert keys.telemetry("position", "interferometer") == "nanodrift/c1/sensors/position"


def test_keys_under_a_prefix_keep_nothing_under_nanodrift() -> None:
    keys = Keys("c1", "femto/lab3/stages")
    assert keys.prefix == "femto/lab3/stages/c1"
    names = [keys.target, keys.command, keys.error, keys.compensate, keys.status, keys.alive, keys.health,
             keys.done, keys.stop, keys.telemetry("temperature", "T3"), keys.telemetry("position", "p", "y")]
    assert all(name.startswith("femto/lab3/stages/c1/") for name in names), names
    assert Keys("c1", "nanodrift").command == Keys("c1").command == "nanodrift/c1/command"


def test_an_oversized_marker_is_refused_with_its_real_size() -> None:
    with pytest.raises(Refusal) as caught:
        parse_target(Oversized.of(10_000_000))
    assert "payload of 10000000 bytes exceeds" in caught.value.message



@pytest.mark.parametrize(
    ("payload", "expected"),
    [
        (b'{"x_um": 12.5, "id": "a"}', Target("a", {"x": 12.5})),
        (b'{"x_um": 3}', Target(None, {"x": 3.0})),
        (b'{"x_um": 3, "id": null, "note": "extra keys are allowed"}', Target(None, {"x": 3.0})),
        (b'{"x_um": 0, "id": -4}', Target(-4, {"x": 0.0})),
    ],
)
def test_good_targets_parse(payload: bytes, expected: Target) -> None:
    assert parse_target(payload) == expected


@pytest.mark.parametrize(
    ("payload", "target_id", "words"),
    [
        (b"", None, "not valid JSON"),
        (b"\x00\xff", None, "not UTF-8"),
        (b"12", None, "JSON object"),
        (b'{"x_um": NaN, "id": 1}', 1, "finite"),
        (b'{"x_um": 1e400, "id": 2}', 2, "finite"),
        (b'{"x_um": ' + b"9" * 400 + b', "id": 3}', 3, "finite"),  # a huge integer overflows float
        (b'{"x_um": false, "id": 4}', 4, "number"),
        (b'{"x_um": [1], "id": 5}', 5, "number"),
        (b'{"id": "q"}', "q", "missing"),
        (b'{"x_um": 1, "id": {"a": 1}}', None, "'id'"),
        (b'{"x_um": 1, "id": 9223372036854775808}', None, "out of range"),
        (b'{"x_um": 1, "id": "' + b"z" * 300 + b'"}', None, "longer"),
        (b" " * (MAX_PAYLOAD_BYTES + 1), None, "exceeds"),
    ],
)
def test_bad_targets_are_refusals_not_exceptions(payload: bytes, target_id: object, words: str) -> None:
    with pytest.raises(Refusal) as caught:
        parse_target(payload)
    assert caught.value.kind == "bad_payload"
    assert caught.value.id == target_id
    assert words in caught.value.message
    assert json.loads(encode_error(caught.value))["id"] == target_id


def outcome(parse: Callable[[], Target]) -> object:
    try:
        return parse()
    except (ValueError, Refusal) as error:
        return ("refused", getattr(error, "id", None))


def test_the_regex_fast_path_agrees_with_json_on_every_variant() -> None:
    """parse_target's fast path must give exactly what json.loads + full validation give."""
    xs = ["0", "-0", "12", "12.5", "1e2", "1E-3", "-4.25e+1", "01", "1.", ".5", "1e999", "NaN", '"3"', "true"]
    ids = [None, "7", "-7", "0", "12345678901234567890", '"abc"', '"a b"', '"a\\"b"', '"\\u00e9"', "null", "1.5",
           '""', "true"]
    spaces = ["", " ", "\n\t", "\f"]
    checked = 0
    for x in xs:
        for target_id in ids:
            for ws in spaces:
                for order in (0, 1):
                    fields = [f'"x_um"{ws}:{ws}{x}'] + ([] if target_id is None else [f'"id":{ws}{target_id}'])
                    text = "{" + ws + f",{ws}".join(fields if order == 0 else fields[::-1]) + ws + "}"
                    expected = outcome(lambda text=text: validate_target(json.loads(text)))
                    assert outcome(lambda text=text: parse_target(text.encode())) == expected, text
                    checked += 1
    assert checked > 1000



def command(target_id: object = "k", **changes: object) -> Command:
    """A one-axis cell's command; ``changes`` as the payload's keys (numbers for the per-axis values)."""
    temps = MappingProxyType({"T1": 21.8, "T2": 21.9})
    base = Command(id=target_id, positions_um={"x": 240.0}, q_um={"x": 236.5}, voltage_v={"x": 4.73},
                   temperatures_c=temps, model="m-1", t=1.7e9 + 0.123456789, extrapolating=[])
    if "x_um" in changes:
        changes["positions_um"] = {"x": changes.pop("x_um")}
    for key in ("q_um", "voltage_v", "q_sigma_um", "correction_um", "q_sigma_adapted_um"):
        if changes.get(key) is not None:
            changes[key] = {"x": changes[key]}
    return replace(base, **changes)


@pytest.mark.parametrize("target_id", [None, 0, -(2**62), "plain", 'quo"te\\ and \u00e9\u4e2d \x01'])
def test_the_fast_command_encoder_writes_the_same_json_as_json_dumps(target_id: object) -> None:
    value = command(target_id, extrapolating=["x", 'we"ird'])
    encoded = encode_command(value)
    expected = {"id": target_id, "x_um": 240.0, "q_um": 236.5, "voltage_v": 4.73,
                "temperatures_c": {"T1": 21.8, "T2": 21.9}, "model": "m-1", "t": 1.7e9 + 0.123456789,
                "extrapolating": ["x", 'we"ird']}
    assert json.loads(encoded) == expected
    assert encoded == json.dumps(expected, separators=(",", ":")).encode()


@pytest.mark.parametrize(
    "changes",
    [
        {},
        {"model": None, "extrapolating": ["T2"]},
        {"model": "m%s", "temperatures_c": MappingProxyType({"T%d": 1.0}), "extrapolating": ["T%d"]},
        {"temperatures_c": {"T1": 21.8}},  # a plain dict: encoded each time, never remembered
        {"temperatures_c": MappingProxyType({"T1": math.nan})},  # a NaN reading becomes null
        {"x_um": math.inf},  # non-finite numbers: the json path (null), never an invalid literal
        {"q_um": np.float64(236.5), "voltage_v": 4},  # numpy and int numbers: the json path
        {"extrapolating": None, "procedure": "calibration", "model": None, "temperatures_c": {}},
        {"q_sigma_um": 0.0125},  # the daemon's command: its uncertainty last ...
        {"q_sigma_um": 0.0125, "correction_um": -0.3},  # ... then the correction (adaptation on)
        {"q_sigma_um": 0.0125, "correction_um": 0.0, "extrapolating": ["T4"]},
        {"q_sigma_um": math.nan},  # a model that cannot say: null
        {"q_sigma_um": np.float64(0.02), "correction_um": 0.1},
        {"q_sigma_um": 0.0125, "correction_um": -0.3, "q_sigma_adapted_um": 0.031},  # the tracker's σ last
        {"q_sigma_um": 0.0125, "correction_um": -0.3, "q_sigma_adapted_um": math.nan},
        {"q_sigma_um": 0.0125, "correction_um": -0.3, "q_sigma_adapted_um": np.float64(0.031)},
    ],
    ids=["daemon", "no-model", "percent", "dict-temps", "nan-temp", "inf", "numpy", "procedure", "sigma",
         "sigma-correction", "zero-correction", "nan-sigma", "numpy-sigma", "adapted-sigma", "nan-adapted",
         "numpy-adapted"],
)
def test_every_command_encodes_as_json_of_its_document(changes: dict[str, object]) -> None:
    value = command(**changes)
    doc = command_doc(value)
    assert encode_command(value) == dumps(doc)
    assert list(doc) == [k for k in ("id", "x_um", "q_um", "voltage_v", "temperatures_c", "model", "t",
                                     "extrapolating", "procedure", "q_sigma_um", "correction_um",
                                     "q_sigma_adapted_um") if k in doc]
    assert ("correction_um" in doc) == (value.correction_um is not None)
    assert ("q_sigma_adapted_um" in doc) == (value.q_sigma_adapted_um is not None)
    assert ("extrapolating" in doc) == (value.extrapolating is not None)
    assert ("procedure" in doc) == (value.procedure is not None)


@pytest.mark.parametrize("axes", [("x",), ("x", "y", "z")])
def test_a_command_without_sigma_is_a_document_json_takes_in_one_pass(axes: tuple[str, ...]) -> None:
    """A model without a covariance has a NaN σ: the document already holds the null the wire has for it, so
    the encoder's first (strict) pass takes it instead of raising and walking the document again."""
    per_axis = dict.fromkeys(axes, 1.0)
    value = replace(command(), positions_um=per_axis, q_um=per_axis, voltage_v=per_axis,
                    q_sigma_um=dict.fromkeys(axes, math.nan), correction_um=per_axis,
                    q_sigma_adapted_um=dict.fromkeys(axes, math.inf))
    doc = command_doc(value)
    assert json.dumps(doc, allow_nan=False, separators=(",", ":")).encode() == encode_command(value)
    sigma, adapted = json.loads(encode_command(value))["q_sigma_um"], doc["q_sigma_adapted_um"]
    assert (sigma, adapted) == ((None, None) if len(axes) == 1 else (dict.fromkeys(axes), dict.fromkeys(axes)))


def test_the_remembered_temperatures_follow_a_new_mapping() -> None:
    first = encode_command(command(temperatures_c=MappingProxyType({"T1": 21.8})))
    again = encode_command(command(temperatures_c=MappingProxyType({"T1": 22.5})))
    assert json.loads(first)["temperatures_c"] == {"T1": 21.8}
    assert json.loads(again)["temperatures_c"] == {"T1": 22.5}


def test_error_and_telemetry_payloads() -> None:
    assert json.loads(encode_error(Refusal("stale", "channel T1 is stale", 7))) == {
        "id": 7, "error": "channel T1 is stale", "kind": "stale"}
    assert json.loads(encode_telemetry(21.5, "degC", 1.0, "ok")) == {"value": 21.5, "unit": "degC", "t": 1.0,
                                                                     "state": "ok"}
    assert json.loads(encode_telemetry(math.nan, "degC", 2.0, "fault", "burnout"))["value"] is None


def test_dumps_turns_non_finite_floats_into_null() -> None:
    assert json.loads(dumps({"value": math.nan, "t": 1.0})) == {"value": None, "t": 1.0}


# --- dumps: every payload's JSON ---------------------------------------------------------------------------------

_JSON_LEAVES = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8)
_JSON_VALUES = st.recursive(_JSON_LEAVES, lambda inner: st.lists(inner, max_size=4)
                            | st.dictionaries(st.text(max_size=6), inner, max_size=4), max_leaves=12)


def _nulled(value: Any) -> Any:
    """What the bus promises of a value: every non-finite float is null (computed here, not by the code)."""
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, dict):
        return {k: _nulled(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_nulled(v) for v in value]
    return value


@settings(max_examples=examples(300), deadline=None)
@given(st.dictionaries(st.text(max_size=6), _JSON_VALUES, max_size=5))
def test_dumps_writes_compact_json_with_every_non_finite_float_as_null(doc: dict[str, Any]) -> None:
    """The shared encoder (made once for the hot path) writes what ``json.dumps`` with the same options writes."""
    assert dumps(doc) == json.dumps(_nulled(doc), separators=(",", ":"), allow_nan=False).encode()
