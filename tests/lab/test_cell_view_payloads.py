"""What the bridges read from the network (``command``, ``sensors/position`` and ``status`` payloads, which any
peer may publish) never raises and yields only finite numbers: :mod:`nanodrift.cell_view`'s parsers, over
arbitrary JSON (Hypothesis), and over the daemon's own payload shapes.
"""

from __future__ import annotations

import math
from typing import Any

from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.cell_view import axes_of, axis_value, cell_state, measured_of, number, setpoints_of

JSON = st.recursive(st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=5),
                    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=5), children,
                                                                                      max_size=3),
                    max_leaves=10)
KEYS = st.sampled_from(["x_um", "y_um", "t", "value", "state", "q_um", "voltage_v", "axes", "sensors", "actuator",
                        "healthy", "model", "model_problem", "extrapolating", "min_um", "max_um", "role"])
DOCS = st.dictionaries(KEYS | st.text(max_size=4), JSON, max_size=8)
STATES = {"ok", "degraded", "extrapolating", "no-model", "stalled"}


@settings(max_examples=examples(40))
@given(DOCS)
def test_a_command_payload_gives_only_finite_setpoints_of_known_axes(doc: dict[str, Any]) -> None:
    found = setpoints_of(doc, ("x", "y"))
    assert set(found) <= {"x", "y"}
    for axis, value in found.items():
        raw = doc[f"{axis}_um"]
        assert not isinstance(raw, bool) and math.isfinite(value) and value == raw
    for key in ("q_um", "voltage_v"):
        value = axis_value(doc, key, "x")
        assert math.isnan(value) or math.isfinite(value)


@settings(max_examples=examples(40))
@given(DOCS)
def test_a_position_payload_is_a_sample_only_when_ok_and_numeric(doc: dict[str, Any]) -> None:
    measured = measured_of(doc)
    if measured is not None:
        assert doc.get("state", "ok") == "ok"
        assert measured.value_um == doc["value"] and measured.t == doc["t"]
        assert math.isfinite(measured.value_um) and math.isfinite(measured.t)


@settings(max_examples=examples(40))
@given(DOCS)
def test_a_status_payload_gives_axes_or_says_why_and_always_a_state(doc: dict[str, Any]) -> None:
    try:
        axes = axes_of(doc)
    except ValueError as error:
        assert "has 'axes' but no axis described in it" in str(error)
    else:
        assert axes and not any(math.isnan(info.min_um) or math.isnan(info.max_um) for info in axes.values())
    assert cell_state(doc) in STATES


def test_numbers_are_finite_json_numbers_only() -> None:
    assert [number(v) for v in (1, 2.5, True, "3", None, math.nan, math.inf)] == [1.0, 2.5, None, None, None, None,
                                                                                  None]


def test_the_daemons_payloads_one_axis_and_xy() -> None:
    one = {"id": 1, "x_um": 240.0, "q_um": 239.7, "voltage_v": 4.794, "q_sigma_um": 0.05, "t": 1.0}
    assert setpoints_of(one, ("x",)) == {"x": 240.0}
    assert axis_value(one, "voltage_v", "x") == 4.794
    xy = {"id": 2, "x_um": 100.0, "y_um": 200.0, "q_um": {"x": 99.8, "y": 200.1}, "voltage_v": {"x": 1.996, "y": 4.002},
          "t": 2.0}
    assert setpoints_of(xy, ("x", "y")) == {"x": 100.0, "y": 200.0}
    assert axis_value(xy, "voltage_v", "y") == 4.002 and math.isnan(axis_value(xy, "q_sigma_um", "y"))
    assert measured_of({"value": 12.5, "unit": "um", "t": 3.0, "state": "ok"}) is not None
    assert measured_of({"value": 12.5, "unit": "um", "t": 3.0, "state": "stale"}) is None
    status = {"axes": {"x": {"min_um": 0.0, "max_um": 480.0, "position_sensor": "ifm_x"},
                       "y": {"min_um": 0.0, "max_um": 480.0, "position_sensor": None}}}
    axes = axes_of(status)
    assert list(axes) == ["x", "y"] and axes["x"].position_sensor == "ifm_x" and axes["y"].position_sensor is None
    one_axis = axes_of({"actuator": {"x_min_um": 0.0, "x_max_um": 500.0},
                        "sensors": {"T1": {"role": "temperature"}, "ifm": {"role": "position"}}})
    assert one_axis["x"].max_um == 500.0 and one_axis["x"].position_sensor == "ifm"
