"""benchmarks/week.py's scoring: e_true = e_read - e_interf per command, and the tracker replays its bars rely on.

A synthetic static week (a row every 1200 s from Monday 00:00 UTC): the stage's error is a slow offset plus a
daily swing, the interferometer's own error a walk that grows steadily over the week. The daemon's bias
tracker, replayed on it, must zero what the interferometer reads and so take on the interferometer's walk
(the realistic cell's case); an off tracker must leave the static errors as they were and a reversed one run
to its clamp. Pure arithmetic on rows: no daemon, no clock.
"""

from __future__ import annotations

import datetime as dt
import math
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
from helpers.benchmark_module import load_benchmark

WEEK_START = dt.datetime(2026, 11, 30, tzinfo=dt.UTC).timestamp()  # a Monday 00:00 UTC
STEP_S = 1200.0
WALK_END_UM = 0.2  # the interferometer's own error at the end of the week


@pytest.fixture(scope="module")
def week() -> ModuleType:
    return load_benchmark("week")


def static_error_um(t_s: float) -> float:
    return -0.3 + 0.1 * math.sin(2 * math.pi * (t_s - WEEK_START) / 86400.0)


def interferometer_error_um(t_s: float) -> float:
    return WALK_END_UM * (t_s - WEEK_START) / (7 * 86400.0)


def static_week(week: ModuleType) -> object:
    run = week.Run("static", "off", Path("model.json"), 1, Path("."))
    run.week_start = WEEK_START
    points = [0.0, 80.0, 160.0, 240.0, 320.0, 400.0, 480.0]
    for k in range(int(7 * 86400 / STEP_S)):
        t_s = WEEK_START + (k + 1) * STEP_S - 1.0
        target = points[k % len(points)]
        true_x = target + static_error_um(t_s)
        run.rows.append({"t_s": t_s, "target_um": target, "true_x_um": true_x,
                         "x_um": true_x + interferometer_error_um(t_s)})
    return run


def test_the_split_holds_per_command(week: ModuleType) -> None:
    run = static_week(week)
    errors = week.CommandErrors.of(week.full_days(run.rows, run.week_start))
    assert errors.true.rms_nm == pytest.approx(1e3 * math.sqrt(0.3 ** 2 + 0.1 ** 2 / 2), rel=0.02)
    # days 1-6 see the walk from 1/7 of its end value to all of it
    walk = WALK_END_UM * np.linspace(1 / 7, 1.0, 1000)
    assert errors.interferometer.rms_nm == pytest.approx(1e3 * float(np.sqrt(np.mean(walk ** 2))), rel=0.02)
    full = [r for r in run.rows if WEEK_START + 86400.0 <= r["t_s"] < WEEK_START + 7 * 86400.0]
    read_nm = [1e3 * (r["x_um"] - r["target_um"]) for r in full]
    assert errors.read.max_nm == pytest.approx(max(abs(e) for e in read_nm), abs=1e-6)
    assert errors.read.rms_nm == pytest.approx(math.sqrt(sum(e * e for e in read_nm) / len(read_nm)), rel=1e-9)


def test_the_daemons_tracker_zeroes_the_reading_and_takes_on_the_interferometers_walk(week: ModuleType) -> None:
    run = static_week(week)
    working = next(r for r in week.tracker_replays() if r.name == week.WORKING_REPLAY).replay(run)
    static = week.CommandErrors.of(week.full_days(run.rows, run.week_start))
    assert working.read.rms_nm < 25.0  # the daily swing, one step late
    # its true error is minus the walk (to the same 25 nm), not the static model's
    assert abs(working.true.rms_nm - static.interferometer.rms_nm) < 25.0
    assert all(working.read.figure(f) <= bar for f, bar in week.BARS_NM["adaptive train"].items())


def test_a_broken_tracker_fails_the_adaptive_bars(week: ModuleType) -> None:
    run = static_week(week)
    replays = {r.name: r.replay(run) for r in week.tracker_replays()}
    static = week.CommandErrors.of(week.full_days(run.rows, run.week_start))
    off = replays["a tracker off (clamp 0)"]
    assert off == static  # clamp 0: every command as served
    reversed_sign = replays["a tracker with its sign reversed"]
    assert reversed_sign.read.max_nm > 1e3 * week.ADAPT_MAX_UM  # runs to its clamp, away from the target
    for broken in (off, reversed_sign):
        assert any(broken.read.figure(f) > bar for f, bar in week.BARS_NM["adaptive train"].items())


def test_a_full_day_without_a_row_fails_every_bar(week: ModuleType) -> None:
    run = static_week(week)
    run.rows = [r for r in run.rows if not WEEK_START + 3 * 86400.0 <= r["t_s"] < WEEK_START + 4 * 86400.0]
    assert week.full_days(run.rows, run.week_start) is None
    assert week.scores(run).commands.read.rms_nm == math.inf
