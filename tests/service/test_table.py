"""The sensor table judges every reading (issue 16, problem 10): a lying instrument is not believed.

Out of its valid range or non-finite: ``fault`` naming the value and the range; stamped in the future:
``fault``; bit-identical for longer than ``frozen_after_s``: ``stale``. The value an ``ok`` channel
offers the compensator and the health unit is always finite and inside the range (a property test).
"""

from __future__ import annotations

import math
from pathlib import Path

import pytest
from helpers.budget import examples
from helpers.daemon_harness import TEMPS, write_test_model
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.compensation import Compensator, Refusal, Target
from nanodrift.config import DEFAULT_TEMPERATURE_RANGE_C, parse_config, valid_range
from nanodrift.drivers.base import POSITION_FROZEN_AFTER_S, Reading, SensorConfig, State
from nanodrift.service.table import FUTURE_TOLERANCE_S, SensorTable


def ifm(**keys: float) -> SensorConfig:
    return SensorConfig(name="ifm", kind="x", role="position", interval_s=0.1, max_age_s=5.0, **keys)


def test_a_reading_outside_the_valid_range_is_a_fault_naming_the_value_and_the_range() -> None:
    table = SensorTable([ifm(valid_min=-10.0, valid_max=510.0)])
    table.update("ifm", Reading(240.0, t=100.0), now=100.0)
    assert table.state("ifm", 100.0) == (State.OK, "")

    entry = table.update("ifm", Reading(1e200, t=100.1, unit="um"), now=100.1)
    assert entry is not None
    state, reason = table.state("ifm", 100.1)
    assert state is State.FAULT
    assert reason == "reading 1e+200 um outside the valid range [-10, 510] um (valid_min/valid_max)"
    assert entry.value == 240.0  # the last believed value is kept, never the lie
    table.update("ifm", Reading(-10.5, t=100.2), now=100.2)
    assert table.state("ifm", 100.2)[0] is State.FAULT and "-10.5" in table.state("ifm", 100.2)[1]
    table.update("ifm", Reading(510.0, t=100.3), now=100.3)  # the bounds themselves are believed
    assert table.state("ifm", 100.3) == (State.OK, "") and table.entries["ifm"].value == 510.0


@pytest.mark.parametrize("value", [math.nan, math.inf, -math.inf])
def test_a_non_finite_reading_the_device_calls_ok_is_a_fault(value: float) -> None:
    table = SensorTable([SensorConfig(name="T1", kind="x")])
    table.update("T1", Reading(21.5, t=10.0), now=10.0)
    table.update("T1", Reading(value, t=10.5), now=10.5)
    assert table.state("T1", 10.5) == (State.FAULT, f"non-finite value {value}")
    assert table.entries["T1"].value == 21.5 and table.latest_temperatures() is None


def test_a_temperature_outside_the_generous_default_range_is_a_fault() -> None:
    """A thermocouple module's burnout code (3276.7 °C) is no temperature."""
    table = SensorTable([SensorConfig(name="T1", kind="x")])
    low, high = DEFAULT_TEMPERATURE_RANGE_C
    table.update("T1", Reading(3276.7, t=1.0, unit="degC"), now=1.0)
    assert table.state("T1", 1.0) == (
        State.FAULT, f"reading 3276.7 degC outside the valid range [{low:g}, {high:g}] degC (valid_min/valid_max)")
    table.update("T1", Reading(high, t=2.0), now=2.0)
    assert table.state("T1", 2.0) == (State.OK, "")


def test_a_reading_stamped_in_the_future_is_a_fault() -> None:
    table = SensorTable([ifm()])
    table.update("ifm", Reading(240.0, t=1005.0), now=1000.0)
    assert table.state("ifm", 1000.0) == (State.FAULT, "reading stamped 5.0 s in the future (tolerance 1 s)")
    assert table.entries["ifm"].value is None
    table.update("ifm", Reading(240.0, t=1000.0 + 0.9 * FUTURE_TOLERANCE_S), now=1000.0)  # a little ahead: fine
    assert table.state("ifm", 1000.0) == (State.OK, "")


def test_a_value_bit_identical_for_longer_than_frozen_after_s_is_stale_until_it_moves() -> None:
    table = SensorTable([ifm(frozen_after_s=2.0)])
    for k in range(5):  # 0.0 .. 2.0 s: not longer than frozen_after_s yet
        table.update("ifm", Reading(123.456, t=50.0 + 0.5 * k), now=50.0 + 0.5 * k)
        assert table.state("ifm", 50.0 + 0.5 * k) == (State.OK, ""), k
    table.update("ifm", Reading(123.456, t=52.5), now=52.5)
    assert table.state("ifm", 52.5) == (State.STALE, "value frozen at 123.456 um for 2 s (frozen_after_s 2)")
    table.update("ifm", Reading(math.nan, t=53.0, state=State.FAULT, reason="beam lost"), now=53.0)
    table.update("ifm", Reading(123.456, t=53.5), now=53.5)  # a fault between changes nothing: still the same value
    assert table.state("ifm", 53.5)[0] is State.STALE
    table.update("ifm", Reading(123.457, t=54.0), now=54.0)  # it moves: believed again
    assert table.state("ifm", 54.0) == (State.OK, "")


def test_frozen_defaults_on_for_position_and_off_for_temperatures() -> None:
    assert ifm().frozen_after_s == POSITION_FROZEN_AFTER_S
    assert SensorConfig(name="T1", kind="x").frozen_after_s == 0.0
    table = SensorTable([SensorConfig(name="T1", kind="x")])
    for k in range(100):  # a 0.1 °C module in a stable room repeats for hours: that is no fault
        table.update("T1", Reading(21.8, t=60.0 * k), now=60.0 * k)
    assert table.state("T1", 60.0 * 99) == (State.OK, "")


def test_a_position_sensor_without_a_range_believes_the_workspace_with_a_margin() -> None:
    config = parse_config({"actuator": {"x_min_um": -100.0, "x_max_um": 500.0}, "sensors": []})
    sensor = ifm()
    assert valid_range(sensor, config.actuator.workspace_um) == (-160.0, 560.0)  # 10 % of the stroke each side
    assert valid_range(ifm(valid_max=600.0), config.actuator.workspace_um) == (-160.0, 600.0)  # a declared bound wins
    table = SensorTable([sensor], config.actuator.workspace_um)
    table.update("ifm", Reading(559.9, t=1.0), now=1.0)
    assert table.state("ifm", 1.0) == (State.OK, "")
    table.update("ifm", Reading(560.1, t=2.0), now=2.0)
    assert table.state("ifm", 2.0) == (
        State.FAULT, "reading 560.1 um outside the valid range [-160, 560] um (valid_min/valid_max)")


def test_a_reload_that_narrows_the_range_faults_a_value_it_no_longer_believes() -> None:
    old = SensorTable([ifm()], (0.0, 500.0))
    old.update("ifm", Reading(540.0, t=1.0), now=1.0)
    assert old.state("ifm", 1.0)[0] is State.OK
    new = SensorTable([ifm()], (0.0, 400.0))
    new.carry_over(old)
    assert new.state("ifm", 1.0)[0] is State.FAULT and "540" in new.state("ifm", 1.0)[1]


def test_a_lying_thermocouple_refuses_targets_naming_the_channel(tmp_path: Path) -> None:
    """The compensator's fast path sees the table's judgement (it is made at ingest, not per target)."""
    model = write_test_model(tmp_path / "m.json")
    config = parse_config({"sensors": []})
    table = SensorTable([SensorConfig(name=n, kind="x", max_age_s=5.0) for n in TEMPS])
    compensator = Compensator(model, {"x": config.actuator}, table)
    for name, value in TEMPS.items():
        table.update(name, Reading(value, t=10.0), now=10.0)
    compensator.observe(10.0, TEMPS)
    assert compensator.compensate(Target(1, {"x": 100.0}), 10.1, 0.0).positions_um == {"x": 100.0}  # believed: served
    table.update("T2", Reading(-3276.8, t=10.2), now=10.2)
    with pytest.raises(Refusal) as refused:
        compensator.compensate(Target(2, {"x": 100.0}), 10.3, 0.0)
    assert refused.value.kind == "fault" and "channel T2 is fault: reading -3276.8" in refused.value.message


# --- the property: whatever the device says, an ok channel's value is believable -------------------

WORKSPACE_UM = (0.0, 500.0)
LOW, HIGH = -50.0, 550.0  # the default range of that workspace


@settings(max_examples=examples(300), deadline=None)
@given(st.lists(st.tuples(st.floats(allow_nan=True, allow_infinity=True),
                          st.floats(min_value=-5.0, max_value=5.0)), min_size=1, max_size=30))
def test_an_ok_position_value_is_always_finite_and_inside_the_range(readings: list[tuple[float, float]]) -> None:
    table = SensorTable([ifm(frozen_after_s=1.0)], WORKSPACE_UM)
    now = 1000.0
    for k, (value, ahead_s) in enumerate(readings):
        now += 0.25
        table.update("ifm", Reading(value, t=now + ahead_s), now=now)
        state, _ = table.state("ifm", now)
        entry = table.entries["ifm"]
        if state is State.OK:
            assert entry.value is not None and math.isfinite(entry.value) and LOW <= entry.value <= HIGH, (k, value)
            assert entry.value == value and ahead_s <= FUTURE_TOLERANCE_S  # the ok value is the one just read
        elif not (math.isfinite(value) and LOW <= value <= HIGH) or ahead_s > FUTURE_TOLERANCE_S:
            assert state is State.FAULT, (k, value, ahead_s)
