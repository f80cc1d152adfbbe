"""nanodrift.motion: the one owner of motion (start point, slew on elapsed time, limits), as pure functions."""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import pytest
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.motion import (
    MAX_STEP_INTERVAL_S,
    RAMP_PERIOD_S,
    SAFE_RATE_SHARE,
    Slew,
    VoltageLimitError,
    checked_voltage,
    position_disagreement,
    q_um_for,
    ramp_seconds,
    trusted_start,
    voltage_for,
    within_limits,
)


@dataclass
class Limits:
    volts_per_um: float = 0.02
    offset_v: float = 0.0
    v_min: float = -2.0
    v_max: float = 12.0
    max_slew_um_per_s: float = 100.0


voltages = st.floats(min_value=-2.0, max_value=12.0, allow_nan=False)
rates = st.floats(min_value=0.5, max_value=5000.0, allow_nan=False)
latencies = st.lists(st.floats(min_value=0.0, max_value=0.05), min_size=1, max_size=20)


@settings(max_examples=examples(300), deadline=None)
@given(start_v=voltages, goal_v=voltages, rate=rates, latencies_s=latencies)
def test_a_ramp_moves_at_the_rate_on_elapsed_time_whatever_the_device_latency(
        start_v: float, goal_v: float, rate: float, latencies_s: list[float]) -> None:
    """Each step covers the time since the previous one began (the first: one ramp period), never more
    than the cap; the ramp is monotone, ends at the goal, and lasts distance / rate (less a period)."""
    limits = Limits(max_slew_um_per_s=rate)
    slew = Slew()
    now_s, at_v, began = 0.0, start_v, []
    for i in range(200_000):
        voltage = slew.next_voltage(limits, at_v, goal_v, now_s)
        covered_s = RAMP_PERIOD_S if not began else min(now_s - began[-1], MAX_STEP_INTERVAL_S)
        assert abs(voltage - at_v) <= rate * limits.volts_per_um * covered_s * (1 + 1e-9) + 1e-12
        assert (voltage - at_v) * (goal_v - start_v) >= 0, "moved away from the goal"
        began.append(now_s)
        slew.wrote(now_s, voltage == goal_v)
        at_v = voltage
        if voltage == goal_v:
            break
        now_s += latencies_s[i % len(latencies_s)] + RAMP_PERIOD_S  # the write, then the pause
    assert at_v == goal_v
    expected_s = ramp_seconds(limits, start_v, goal_v)
    # never slower than the rate, whatever the latency (the last step waits at most one write longer
    # than the distance needs) ...
    assert now_s <= expected_s + max(latencies_s) + 1e-6
    assert now_s >= expected_s - RAMP_PERIOD_S - 1e-6  # ... and never faster


def test_a_device_answering_in_10_ms_does_not_slow_the_ramp() -> None:
    """Issue 16.6: ramps ran at ~38 % of the rate when the module answered in 10 ms (step count drove them)."""
    limits = Limits(max_slew_um_per_s=100.0)
    slew, now_s, at_v, goal_v = Slew(), 0.0, 0.0, 9.6  # 480 um at 100 um/s: 4.8 s
    while at_v != goal_v:
        at_v = slew.next_voltage(limits, at_v, goal_v, now_s)
        slew.wrote(now_s, at_v == goal_v)
        now_s += 0.010 + RAMP_PERIOD_S
    assert 4.75 <= now_s <= 4.85


def test_a_stalled_loop_resumes_at_the_rate_not_with_a_jump() -> None:
    limits = Limits(max_slew_um_per_s=100.0)
    slew = Slew()
    first = slew.next_voltage(limits, 0.0, 9.6, 0.0)
    slew.wrote(0.0, False)
    after_stall = slew.next_voltage(limits, first, 9.6, 30.0)  # the loop was away for 30 s
    assert math.isclose(after_stall - first, 100.0 * 0.02 * MAX_STEP_INTERVAL_S, rel_tol=1e-12)


def test_off_or_unknown_start_is_the_goal_at_once() -> None:
    assert Slew().next_voltage(Limits(max_slew_um_per_s=0.0), 0.0, 9.6, 0.0) == 9.6
    assert Slew().next_voltage(Limits(), None, 9.6, 0.0) == 9.6


@given(latency_s=st.floats(min_value=0.0, max_value=0.5), rate=st.floats(min_value=10.0, max_value=2000.0))
def test_a_slow_device_ramps_at_its_share_of_the_rate_and_never_faster_between_two_values_it_received(
        latency_s: float, rate: float) -> None:
    """Issue 26.9: a module answering in 60 ms ramped at a quarter of the rate when every step waited one ramp
    period; a ramp now pauses 9x the write time, so each step (the time since the previous write returned)
    is most of each cycle. On a simulated clock: the device takes ``latency_s`` to take each value."""
    limits = Limits(max_slew_um_per_s=rate)
    goal_v = 12.0
    distance_um = (goal_v - -2.0) / limits.volts_per_um
    slew, now_s, at_v, received = Slew(), 0.0, -2.0, [(0.0, -2.0)]  # (when the device had it, V)
    slew.wrote(0.0, reached_goal=True, took_s=latency_s)  # the stage at rest, its device as slow as ever
    now_s += slew.pause_s()
    while at_v != goal_v:
        at_v = slew.next_voltage(limits, at_v, goal_v, now_s)
        now_s += latency_s  # the device has it no later than when the write returns
        received.append((now_s, at_v))
        slew.wrote(now_s, at_v == goal_v, took_s=latency_s)
        now_s += slew.pause_s()
    for (t0, v0), (t1, v1) in itertools.pairwise(received):
        assert v1 - v0 <= rate * limits.volts_per_um * (t1 - t0) * (1 + 1e-9), (t0, t1, v0, v1)
    took_s = received[-1][0]
    # the share holds over the ramp, less at most one cycle for the last, partial step
    assert took_s <= distance_um / rate / SAFE_RATE_SHARE + slew.pause_s() + latency_s + 1e-9


# --- where a move starts ------------------------------------------------------------------------


def test_a_read_back_outside_the_limits_is_unknown_never_a_start_point() -> None:
    """Issue 16.3: a GCS controller answering 50 V at start made the first write v_max."""
    start = trusted_start(Limits(), 50.0, (), math.nan)
    assert start.voltage_v is None and start.known_from == "unknown" and "outside [-2, 12] V" in start.distrust


def test_a_read_back_that_contradicts_what_this_process_sent_starts_from_what_was_sent() -> None:
    """Issue 16.3: an output holding 0 V but reading back 10 V was ramped from 10 V at each reopen; issue 26.4:
    believing nothing then wrote the goal unramped. The device received nothing but what was sent: ramp from it."""
    start = trusted_start(Limits(), 10.0, (-0.45,), math.nan)
    assert start.voltage_v == -0.45 and start.known_from == "last written"
    assert "but -0.4500 V was sent last" in start.distrust
    agrees = trusted_start(Limits(), -0.45, (-0.45,), math.nan)
    assert agrees.voltage_v == -0.45 and agrees.known_from == "read back" and agrees.distrust is None


def test_a_read_back_that_contradicts_the_state_file_is_unproven() -> None:
    """Issue 26.5: across a restart someone may have written the output: a claim the record does not confirm
    moves nothing."""
    start = trusted_start(Limits(), 10.0, (0.0, 0.0), math.nan, sent_here=False, power_up_v=0.0)
    assert start.voltage_v is None and start.known_from == "unproven"
    assert "but 0.0000 V was the last value written (state file)" in start.distrust
    resumed = trusted_start(Limits(), 8.0, (7.98, 8.0), math.nan, sent_here=False, power_up_v=0.0)
    assert resumed.voltage_v == 8.0 and resumed.known_from == "read back"


def test_a_first_start_believes_only_the_power_up_value() -> None:
    assert trusted_start(Limits(), 0.0005, (), math.nan, power_up_v=0.0).known_from == "power-up value"
    lying = trusted_start(Limits(), 10.0, (), 0.0, power_up_v=0.0)
    assert lying.voltage_v is None and lying.known_from == "unproven" and "power-up value 0 V" in lying.distrust
    assert trusted_start(Limits(), 0.0, (), math.nan, power_up_v=math.nan).known_from == "unproven"


def test_a_read_back_may_agree_with_the_last_confirmed_or_the_last_tried_voltage() -> None:
    """A write that failed on the way may or may not have reached the output: either is believed."""
    assert trusted_start(Limits(), 3.0, (3.0, 5.0), math.nan).voltage_v == 3.0
    assert trusted_start(Limits(), 5.0, (3.0, 5.0), math.nan).voltage_v == 5.0


@given(read=st.one_of(st.none(), st.floats(allow_nan=True, allow_infinity=True)),
       sent=st.lists(voltages, max_size=2).map(tuple),
       safe=st.one_of(st.just(math.nan), voltages),
       sent_here=st.booleans(),
       power_up=st.one_of(st.none(), st.just(math.nan), voltages))
def test_a_start_point_is_always_inside_the_limits_and_never_an_unconfirmed_claim(
        read: float | None, sent: tuple[float, ...], safe: float, sent_here: bool, power_up: float | None) -> None:
    start = trusted_start(Limits(), read, sent, safe, sent_here=sent_here, power_up_v=power_up)
    assert start.voltage_v is None or within_limits(Limits(), start.voltage_v)
    if read is not None and start.known_from == "read back":
        assert (not sent and power_up is None) or min(abs(read - v) for v in sent) <= 0.001
    if read is not None and start.known_from == "last written":  # a claim not believed: what this process sent
        assert sent_here and start.voltage_v == sent[-1]
    if start.known_from == "power-up value":
        assert not sent and power_up is not None and read is not None and abs(read - power_up) <= 0.001
    if start.known_from == "unproven":
        assert power_up is not None and not (sent and sent_here)


def test_an_unproven_claim_inside_the_limits_is_kept_for_a_position_sensor_and_one_outside_never() -> None:
    claimed = trusted_start(Limits(), 8.0, (), math.nan, sent_here=False, power_up_v=0.0)
    assert claimed.known_from == "unproven" and claimed.voltage_v is None and claimed.claimed_v == 8.0
    outside = trusted_start(Limits(), 40.0, (), math.nan, sent_here=False, power_up_v=0.0)
    assert outside.known_from == "unproven" and outside.claimed_v is None
    assert trusted_start(Limits(), math.nan, (), math.nan, power_up_v=0.0).claimed_v is None


@settings(max_examples=examples(300))
@given(read=voltages, measured=st.floats(allow_nan=True, allow_infinity=True),
       tolerance=st.floats(min_value=1e-3, max_value=1e3, allow_nan=False),
       offset=st.floats(min_value=-1.0, max_value=1.0), gain=st.sampled_from([0.02, -0.02, 0.0105]))
def test_a_position_reading_proves_a_read_back_exactly_within_the_stated_tolerance(
        read: float, measured: float, tolerance: float, offset: float, gain: float) -> None:
    """The reading comes from a device: any float, NaN and infinities too; only a finite one within the tolerance
    of the command the voltage means proves it."""
    limits = Limits(volts_per_um=gain, offset_v=offset)
    problem = position_disagreement(limits, read, measured, tolerance)
    gap_um = abs(measured - q_um_for(limits, read))
    assert (problem is None) == (math.isfinite(gap_um) and gap_um <= tolerance)
    if problem is not None:
        assert f"read back {read:.4f} V" in problem and f"position_proof_tolerance_um = {tolerance:g}" in problem


def test_a_position_reading_names_what_the_voltage_means_and_how_far_it_is() -> None:
    assert position_disagreement(Limits(), 8.0, 401.5, 5.0) is None
    assert position_disagreement(Limits(), 8.0, 100.0, 5.0) == (
        "read back 8.0000 V means q 400.000 µm, but the position sensor measures 100.000 µm (300.000 µm apart; "
        "position_proof_tolerance_um = 5 µm)")
    assert position_disagreement(Limits(), 8.0, 400.0, math.nan) is not None  # no tolerance stated: nothing proved


@given(q=st.floats(min_value=-1e4, max_value=1e4, allow_nan=False))
def test_the_voltage_rule_and_its_inverse(q: float) -> None:
    limits = Limits(volts_per_um=0.021, offset_v=-0.3)
    assert math.isclose(q_um_for(limits, voltage_for(limits, q)), q, rel_tol=1e-12, abs_tol=1e-9)


def test_the_one_voltage_limit_check_names_the_command_and_the_limits() -> None:
    """The daemon's ``voltage_limit`` refusal and the procedures' steps both go through checked_voltage."""
    assert checked_voltage(Limits(), 500.0) == pytest.approx(10.0)
    for q in (700.0, -150.0, math.nan):
        with pytest.raises(VoltageLimitError) as refused:
            checked_voltage(Limits(), q)
        message = str(refused.value)
        assert message.startswith(f"command q {q:.4f} µm needs ") and message.endswith("outside [-2, 12] V")


def test_a_move_from_rest_soon_after_the_last_write_covers_only_the_time_since_it() -> None:
    """A stop (or a reload) ends a ramp and the next move starts 5 ms after the last write: its first step
    covers those 5 ms, not a whole ramp period (between two values the device receives, never faster)."""
    limits = Limits(max_slew_um_per_s=100.0)  # 2 V/s at 0.02 V/um
    slew = Slew()
    slew.next_voltage(limits, 0.0, 9.6, 0.0)
    slew.wrote(0.0, False)
    slew.next_voltage(limits, 0.04, 9.6, 0.02)
    slew.wrote(0.02, False)
    slew.rest()  # a stop
    step = slew.next_voltage(limits, 0.08, 0.0, 0.025) - 0.08  # back down, 5 ms after the last write
    assert math.isclose(step, -2.0 * 0.005, rel_tol=1e-9)
    slew.wrote(0.025, False)
    slew.rest()
    assert math.isclose(slew.next_voltage(limits, 0.0, 9.6, 10.0), 2.0 * RAMP_PERIOD_S, rel_tol=1e-12)  # long rest


def test_a_write_cut_short_bounds_the_next_step_from_when_it_was_cut() -> None:
    """A write a reload cancelled may have reached the device: the next move's first step covers only the time
    since it was cut, not a whole ramp period (before: 0.3 V in 5 ms at 15 V/s on an XY module)."""
    limits = Limits(volts_per_um=0.01, v_min=-10.0, v_max=10.0, max_slew_um_per_s=1500.0)
    slew = Slew()
    slew.cut_short(100.0)
    slew.rest()
    assert slew.next_voltage(limits, 0.3, 5.0, 100.005) == pytest.approx(0.3 + 15.0 * 0.005, abs=1e-12)


def test_a_write_cut_short_counts_from_the_reopen_that_follows_it_and_a_returned_write_does_not() -> None:
    """A cut-short write's bytes may reach the device after the cut (a release run: 0.047 V 2.8 ms after it took
    the cut value, at 15 V/s): once the device is opened again and read back, the next step counts from then. A
    write that returned is not moved by a reopen: the device held it by its return."""
    limits = Limits(volts_per_um=0.01, v_min=-10.0, v_max=10.0, max_slew_um_per_s=1500.0)
    slew = Slew()
    slew.cut_short(100.0)
    slew.reopened(100.004)
    slew.rest()
    assert slew.next_voltage(limits, 0.319, 0.0, 100.005) == pytest.approx(0.319 - 15.0 * 0.001, abs=1e-12)
    returned = Slew()
    returned.wrote(100.0, False)
    returned.reopened(100.004)
    returned.rest()
    assert returned.next_voltage(limits, 0.319, 0.0, 100.005) == pytest.approx(0.319 - 15.0 * 0.005, abs=1e-12)
