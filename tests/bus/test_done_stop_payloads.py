"""``done`` and ``stop`` on the wire without a network: the keys, the ``done`` payload (every key always
present), a ``stop``'s payload (empty, an id, or refused) and a ``stop`` query's reply."""

from __future__ import annotations

import json
from typing import Any

import pytest
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.bus.protocol import (
    DONE_STATES,
    Keys,
    Oversized,
    Refusal,
    dumps,
    encode_done,
    encode_stop_error,
    encode_stop_reply,
    parse_stop,
)


def test_done_and_stop_are_keys_of_the_cell() -> None:
    keys = Keys("c1")
    assert (keys.done, keys.stop) == ("nanodrift/c1/done", "nanodrift/c1/stop")


@pytest.mark.parametrize(("state", "voltage", "error", "expected_error"), [
    ("reached", 4.8, None, None),
    ("superseded", {"x": 1.0, "y": 2.5}, None, None),
    ("stopped", None, None, None),
    ("failed", 1.25, "wrote raw 1 (0.001 V), read back raw 8", "wrote raw 1 (0.001 V), read back raw 8"),
    ("reached", 1.0, "ignored unless failed", None),
])
def test_every_done_has_every_key_and_an_error_only_when_failed(
        state: str, voltage: object, error: str | None, expected_error: str | None) -> None:
    payload = encode_done(7, state, 1700000000.5, voltage, error)  # type: ignore[arg-type]
    doc = json.loads(payload)
    assert list(doc) == ["id", "state", "t", "voltage_v", "error"]
    assert doc == {"id": 7, "state": state, "t": 1700000000.5, "voltage_v": voltage, "error": expected_error}


def test_a_done_state_outside_the_contract_is_a_bug_not_a_payload() -> None:
    with pytest.raises(ValueError, match="not one of reached, superseded, stopped, failed"):
        encode_done(1, "done", 0.0, 1.0)


@settings(max_examples=examples(400), deadline=None)
@given(target_id=st.integers() | st.booleans() | st.none() | st.text(max_size=6),
       state=st.sampled_from(DONE_STATES), t=st.floats() | st.integers(),
       voltage=st.none() | st.floats() | st.integers() | st.dictionaries(st.sampled_from("xyz"), st.floats()),
       error=st.none() | st.text(max_size=6))
def test_a_done_is_the_bytes_the_shared_encoder_writes(target_id: Any, state: str, t: Any, voltage: Any,
                                                       error: str | None) -> None:
    """The one-axis integer-id form written by hand (the hot path) is byte for byte what ``dumps`` writes, and
    every other form goes through ``dumps``: ids of every type (a bool is not an int here), any float."""
    held = dict(voltage) if isinstance(voltage, dict) else voltage
    expected = dumps({"id": target_id, "state": state, "t": t, "voltage_v": held,
                      "error": error if state == "failed" else None})
    assert encode_done(target_id, state, t, voltage, error) == expected


def test_a_non_finite_held_voltage_is_null() -> None:
    assert json.loads(encode_done("a", "stopped", 1.0, {"x": float("nan"), "y": 2.0}))["voltage_v"] == \
        {"x": None, "y": 2.0}


@pytest.mark.parametrize(("payload", "stop_id"), [
    (b"", None), (b"  \n", None), (b"{}", None), (b'{"id": 12}', 12), (b'{"id": "halt-1"}', "halt-1"),
    (b'{"id": null}', None), (b'{"id": 3, "reason": "operator"}', 3),  # more keys: still a stop
])
def test_a_stop_is_empty_or_carries_an_id(payload: bytes, stop_id: object) -> None:
    assert parse_stop(payload).id == stop_id


@pytest.mark.parametrize(("payload", "words"), [
    (b"{not json", "not valid JSON"),
    (b"[1, 2]", "must be a JSON object, got list"),
    (b'{"id": 1.5}', "'id' must be a string or an integer"),
    (b"\xff\xfe", "not UTF-8 text"),
    (Oversized.of(10_000), "10000 bytes exceeds"),
])
def test_a_bad_stop_is_a_refusal_saying_what_was_wrong(payload: bytes, words: str) -> None:
    with pytest.raises(Refusal) as refused:
        parse_stop(payload)
    assert refused.value.kind == "bad_payload" and words in refused.value.message


def test_a_stop_query_is_answered_with_the_values_held() -> None:
    assert json.loads(encode_stop_reply(4, 2.5)) == {"id": 4, "voltage_v": 2.5, "held": True}
    assert json.loads(encode_stop_reply(None, {"x": 1.0, "y": None})) == {
        "id": None, "voltage_v": {"x": 1.0, "y": None}, "held": True}
    assert json.loads(encode_stop_error(None, "stop payload is not valid JSON")) == {
        "id": None, "error": "stop payload is not valid JSON", "kind": "bad_payload"}
