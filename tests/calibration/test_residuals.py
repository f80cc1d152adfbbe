"""Settled residuals, health statistics and the bias tracker: the pure logic the daemon and validate share."""

from __future__ import annotations

import itertools
import math

import pytest
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.calibration.residuals import BiasTracker, HealthMonitor, RangeWatch, Settled, SettleTracker


def _hold(tracker: SettleTracker, t0: float, x: float, readings: list[tuple[float, float, bool]]) -> list[Settled]:
    tracker.commanded(t0, x, x)
    out = []
    for t, value, ok in readings:
        settled = tracker.position(t, value, ok)
        if settled is not None:
            out.append(settled)
    return out


def test_a_held_target_gives_the_mean_of_its_window_minus_the_target() -> None:
    tracker = SettleTracker(settle_s=3.0, window_s=2.0)
    readings = [(t / 10, 100.0 + (0.5 if 3.0 <= t / 10 <= 5.0 else 9.0), True) for t in range(0, 60)]
    (settled,) = _hold(tracker, 0.0, 100.0, readings)
    assert settled.residual_um == pytest.approx(0.5) and settled.samples == 21 and settled.t == 5.0


def test_a_newer_command_abandons_the_hold_and_a_bad_reading_voids_the_window() -> None:
    tracker = SettleTracker(settle_s=3.0, window_s=2.0)
    tracker.commanded(0.0, 100.0, 100.0)
    assert tracker.position(3.5, 100.1, True) is None
    tracker.commanded(4.0, 200.0, 200.0)  # superseded before its window closed
    assert tracker.position(5.5, 100.1, True) is None  # belongs to nothing: the new hold settles at 7 s
    stale = _hold(tracker, 10.0, 50.0, [(13.0, 50.2, True), (14.0, math.nan, False), (15.5, 50.2, True)])
    assert stale == []  # one faulted reading in the window: no residual at all


def test_health_states_unknown_ok_degraded_and_advice() -> None:
    monitor = HealthMonitor(history=10, alarm_rms_nm=100.0)
    assert monitor.state == "unknown"
    for k in range(5):
        monitor.add(Settled(float(k), 100.0, 100.0, 100.02, 10))
    assert monitor.state == "ok" and monitor.residual_rms_nm == pytest.approx(20.0)
    for k in range(10):
        monitor.add(Settled(float(k), 100.0, 100.0, 100.3, 10))
    doc = monitor.document(correction_um=None, extrapolating=[])
    assert doc["state"] == "degraded" and doc["residual_mean_nm"] == pytest.approx(300.0) and doc["n"] == 10
    assert "the cell changed" in doc["advice"] and "+300 nm" in doc["advice"]
    assert HealthMonitor(10, 100.0, has_position_sensor=False).state == "unknown"


def test_a_suspect_position_sensor_is_named_in_the_advice_instead_of_the_cell() -> None:
    monitor = HealthMonitor(history=10, alarm_rms_nm=100.0)
    for k in range(10):
        monitor.add(Settled(float(k), 100.0, 100.0, 100.3, 10))
    suspect = "position sensor 'ifm' is stale: value frozen at 300 um for 31 s (frozen_after_s 30)"
    doc = monitor.document(correction_um=None, extrapolating=[], sensor_problem=suspect)
    assert doc["state"] == "degraded"  # the residuals it has are the residuals it has
    assert doc["advice"] == (f"{suspect}; check the interferometer, not the cell: no residual is taken from it "
                             "until it reads believable values again")
    assert "the cell changed" in str(monitor.advice())  # once believed again, the cell is the suspect again


def test_range_watch_says_how_long_a_channel_has_been_outside() -> None:
    watch = RangeWatch({"T4": (20.0, 22.0)})
    watch.observe(0.0, {"T4": 21.0})
    watch.observe(600.0, {"T4": 22.6})
    watch.observe(3000.0, {"T4": 22.6})
    (outside,) = watch.outside()
    assert outside.describe().startswith("T4 has been 0.60 °C above the training range") and "for 40 min" in \
        outside.describe()
    watch.observe(3100.0, {"T4": 21.9})
    assert watch.outside() == []


def test_bias_tracker_converges_to_minus_a_constant_error_and_respects_the_clamp() -> None:
    tracker = BiasTracker(tau_s=600.0, max_um=1.0)
    error = 0.3  # the model lands 300 nm high
    for k in range(400):
        tracker.update(30.0 * k, error + tracker.correction_um)
    assert tracker.correction_um == pytest.approx(-0.3, abs=1e-3)
    clamped = BiasTracker(tau_s=60.0, max_um=0.5)
    for k in range(200):
        clamped.update(30.0 * k, 2.0 + clamped.correction_um)
    assert clamped.correction_um == -0.5


@settings(max_examples=examples(200), deadline=None)
@given(st.lists(st.tuples(st.floats(0.1, 120.0), st.floats(-50.0, 50.0)), min_size=1, max_size=50),
       st.floats(1.0, 3600.0), st.floats(0.0, 5.0))
def test_bias_tracker_never_jumps_or_leaves_its_clamp(steps, tau_s: float, max_um: float) -> None:
    tracker = BiasTracker(tau_s=tau_s, max_um=max_um)
    t = 0.0
    for dt, residual in steps:
        before = tracker.correction_um
        t += dt
        after = tracker.update(t, residual)
        assert abs(after) <= max_um + 1e-12
        allowed = max_um * (dt if tracker.updates > 1 else tracker.first_dt_s) / tau_s
        assert abs(after - before) <= allowed + 1e-12


def test_a_corrected_commands_sigma_goes_from_the_models_to_what_the_tracker_follows() -> None:
    """Issue 19: with ``[adapt] mode = "bias"`` q_sigma is what the tracker leaves, not the static model's."""
    tracker = BiasTracker(tau_s=600.0, max_um=1.0)
    static_um, wander_um = 1.0, 0.03  # out of range: the static model could be 1 µm off
    assert tracker.sigma_um(static_um, wander_um) == static_um  # nothing learnt yet: the model's own σ
    error_um, scatter_um = 0.4, 0.01
    sigmas = []
    for k in range(200):
        residual = error_um + tracker.correction_um + (scatter_um if k % 2 else -scatter_um)
        tracker.update(30.0 * k, residual)
        sigmas.append(tracker.sigma_um(static_um, wander_um))
    assert tracker.uncorrected == pytest.approx(math.exp(-(30.0 + 199 * 30.0) / 600.0))
    # learnt: the error is taken out; what is left is the wander it follows or the scatter it still sees
    assert tracker.residual_rms_um == pytest.approx(scatter_um, rel=0.1)  # and what is left of the first ones
    assert sigmas[-1] == pytest.approx(max(wander_um, scatter_um), rel=0.02)
    assert sigmas[0] < static_um and all(b <= a + 1e-12 for a, b in itertools.pairwise(sigmas[20:]))
    tracker.reset()  # a new model: its errors are not the old one's
    assert (tracker.uncorrected, tracker.residual_rms_um) == (1.0, 0.0)
    assert tracker.sigma_um(static_um, wander_um) == static_um


def test_a_tracker_held_at_its_clamp_keeps_a_wide_sigma() -> None:
    """A correction stuck at ``max_um`` leaves the rest of the error: its residuals say so, and σ keeps it."""
    tracker = BiasTracker(tau_s=60.0, max_um=0.5)
    for k in range(200):
        tracker.update(30.0 * k, 2.0 + tracker.correction_um)
    assert tracker.correction_um == -0.5
    assert tracker.sigma_um(0.1, 0.02) == pytest.approx(1.5, rel=0.01)  # 2 µm error, 0.5 µm corrected


@settings(max_examples=examples(200), deadline=None)
@given(st.lists(st.tuples(st.floats(0.1, 120.0), st.floats(-50.0, 50.0)), min_size=1, max_size=50),
       st.floats(1.0, 3600.0), st.floats(0.0, 10.0), st.floats(0.0, 1.0))
def test_the_trackers_sigma_is_finite_and_between_its_parts(steps, tau_s: float, static_um: float,
                                                             wander_um: float) -> None:
    tracker = BiasTracker(tau_s=tau_s, max_um=1.0)
    t = 0.0
    for dt, residual in steps:
        t += dt
        tracker.update(t, residual)
        sigma = tracker.sigma_um(static_um, wander_um)
        followed = max(wander_um, tracker.residual_rms_um)
        assert math.isfinite(sigma)
        assert min(static_um, followed) - 1e-9 <= sigma <= max(static_um, followed) + 1e-9
        assert tracker.residual_rms_um <= max(abs(r) for _, r in steps) + 1e-9


def test_a_residual_whose_square_overflows_is_counted_and_changes_nothing() -> None:
    """Issue 26.9: one residual of 1e200 µm made the tracker's RMS, and every later σ, infinite for good."""
    tracker = BiasTracker(tau_s=10.0, max_um=1.0)
    tracker.update(30.0, 0.2)
    before = (tracker.correction_um, tracker.residual_rms_um, tracker.sigma_um(0.05, 0.01))
    for lie in (1e200, -1e200, math.inf, math.nan):
        assert tracker.update(60.0, lie) == before[0]
    assert tracker.rejected == 4 and tracker.updates == 1
    assert (tracker.correction_um, tracker.residual_rms_um, tracker.sigma_um(0.05, 0.01)) == before
    tracker.update(90.0, 0.1)
    assert math.isfinite(tracker.sigma_um(0.05, 0.01)) and tracker.updates == 2
    monitor = HealthMonitor(history=10, alarm_rms_nm=100.0)
    monitor.add(Settled(1.0, 100.0, 100.0, 1e200, 3))
    monitor.add(Settled(2.0, 100.0, 100.0, 100.02, 3))
    assert monitor.rejected == 1 and monitor.n == 1 and monitor.residual_rms_nm == pytest.approx(20.0)
