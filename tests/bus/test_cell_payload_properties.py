"""Property-based: a multi-axis cell's targets from a hostile client.

``parse_target`` with the cell's axes on arbitrary bytes and on arbitrary JSON objects gives a :class:`Target` with a
finite position for exactly the cell's axes, or a ``bad_payload`` :class:`Refusal` naming what is wrong
(a missing axis, an axis the cell does not have, a field that is not a finite number); never another
exception. The expected outcome is computed from what was generated, not by the code under test.
"""

from __future__ import annotations

import json
import math
from typing import Any

from helpers.budget import examples
from hypothesis import example, given, settings
from hypothesis import strategies as st

from nanodrift.bus.protocol import parse_target
from nanodrift.compensation import Refusal, Target

AXES = ("x", "y", "z")
KEYS = st.sampled_from(["x_um", "y_um", "z_um", "w_um", "id", "q_um", "x", "X_um", ""])
VALUES = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(min_value=-(10**400), max_value=10**400),
    st.booleans(), st.none(), st.text(max_size=5), st.lists(st.integers(), max_size=2),
)


@settings(max_examples=examples(300), deadline=None)
@given(st.binary(max_size=200))
def test_any_bytes_give_a_target_or_a_bad_payload_refusal(payload: bytes) -> None:
    try:
        target = parse_target(payload, AXES)
    except Refusal as refusal:
        assert refusal.kind == "bad_payload" and refusal.message
        return
    assert set(target.positions_um) == set(AXES) and all(map(math.isfinite, target.positions_um.values()))


def _finite_number(value: Any) -> bool:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return False
    try:
        return math.isfinite(float(value))
    except OverflowError:
        return False


@settings(max_examples=examples(400), deadline=None)
@given(st.dictionaries(KEYS, VALUES, max_size=6))
@example({"x_um": None, "y_um": 0.0, "z_um": None, "X_um": 0.0, "w_um": None})  # once named only the axis-like extra
def test_a_json_object_is_served_only_when_it_names_every_axis_with_a_finite_number(doc: dict[str, Any]) -> None:
    doc.pop("id", None)  # the id's own rules are the one-axis ones (tests/bus/test_payload_properties.py)
    payload = json.dumps(doc).encode()
    wanted = {f"{a}_um" for a in AXES}
    try:
        target = parse_target(payload, AXES)
    except Refusal as refusal:
        assert refusal.kind == "bad_payload"
        missing = wanted - set(doc)
        extra = set(doc) - wanted
        bad = [k for k in sorted(wanted & set(doc)) if not _finite_number(doc[k])]
        assert missing or extra or bad, f"refused a good target {doc}: {refusal.message}"
        # The message names the first missing axis, else one of the extra fields (an axis-like one by its
        # letter), else a field that is not a finite number.
        named = sorted(missing)[:1] or [n for k in sorted(extra) for n in (k, repr(k[:1]))] or bad
        assert any(n in refusal.message for n in named), (doc, refusal.message)
        return
    assert isinstance(target, Target) and set(doc) == wanted
    assert target.positions_um == {a: float(doc[f"{a}_um"]) for a in AXES}
