"""The simulated cell over days and weeks (issue 19.6): bounded memory, the ``week`` scenario's shape,
the scaled clock's days, the truth log."""

from __future__ import annotations

import asyncio
import csv
from pathlib import Path

import numpy as np
import pytest

from nanodrift.drivers.base import DriverContext, MonotonicClock
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.clock import ScaledClock, VirtualClock
from nanodrift.drivers.simulated.config import SimulationConfig
from nanodrift.drivers.simulated.physics import CellPhysics, Exogenous
from nanodrift.drivers.simulated.plugin import PLUGIN, RESOURCE_KEY, default_sensor_configs
from nanodrift.drivers.simulated.scenarios import (
    WEEK_DAILY_AMPLITUDE_C,
    WEEK_DOOR_DIP_C,
    WEEK_DOOR_TIMES_H,
    WEEK_SETBACK_C,
    get_scenario,
)

MONTH_S = 30 * 86400.0


def unbounded(physics: CellPhysics) -> CellPhysics:
    """The same cell, keeping every knot it ever made (as before issue 19)."""
    physics.exogenous.KEEP_CHUNKS = 10**9
    return physics


def test_a_month_of_in_order_queries_holds_a_bounded_number_of_knots_and_the_same_numbers():
    bounded = CellPhysics.create("daily", "unmonitored_drift,thermal_lag", seed=4)
    reference = unbounded(CellPhysics.create("daily", "unmonitored_drift,thermal_lag", seed=4))
    times = np.arange(0.0, MONTH_S, 613.0)  # a daemon's polls, in order
    held = []
    for t in times:
        assert bounded.exogenous.at1(float(t)) == reference.exogenous.at1(float(t))
        held.append(bounded.exogenous.knots_held)
    limit = (Exogenous.KEEP_CHUNKS + 1) * Exogenous.CHUNK
    assert max(held) <= limit
    assert reference.exogenous.knots_held > 10 * limit  # what used to grow: a month of knots
    # vectorised queries in order (a day at a time) agree exactly too, and stay bounded
    for day in range(30):
        t = np.arange(day * 86400.0, (day + 1) * 86400.0, 7.0)
        assert np.array_equal(bounded.drift(t)["x"], reference.drift(t)["x"])
        assert np.array_equal(bounded.thermal(t)["bracket"], reference.thermal(t)["bracket"])
    assert bounded.exogenous.knots_held <= limit


def test_a_query_before_the_held_knots_is_recomputed_with_identical_numbers():
    physics = CellPhysics.create("week", seed=2)
    reference = unbounded(CellPhysics.create("week", seed=2))
    physics.exogenous.at1(MONTH_S)  # a month on: day 1 was dropped long ago
    assert physics.exogenous.first_knot > 0
    early = np.arange(3600.0, 2 * 86400.0, 11.0)
    assert np.array_equal(physics.drift(early)["x"], reference.drift(early)["x"])
    assert physics.exogenous.at1(MONTH_S) == reference.exogenous.at1(MONTH_S)


def test_a_simulated_cell_polled_for_a_month_keeps_bounded_memory():
    clock = VirtualClock(0.0)
    cell = SimulatedCell(CellPhysics.create("week", seed=1), clock)
    cell.epoch = 0.0
    for k in range(0, int(MONTH_S), 900):
        clock._now = float(k)  # the clock's own time: no scheduler needed for plain reads
        if k % 7200 == 0:
            cell.command("x", float(k % 480))
        cell.read(["T1", "T2", "T3", "T4", "interferometer"])
    assert cell.physics.exogenous.knots_held <= (Exogenous.KEEP_CHUNKS + 1) * Exogenous.CHUNK
    assert len(cell._last_ok) == 5


def weekday_and_weekend_days(t_step_s: float = 60.0) -> tuple[np.ndarray, np.ndarray]:
    scenario = get_scenario("week")
    tuesday = scenario.air(np.arange(1 * 86400.0, 2 * 86400.0, t_step_s))
    sunday = scenario.air(np.arange(6 * 86400.0, 7 * 86400.0, t_step_s))
    return tuesday, sunday


def test_the_week_has_a_daily_cycle_a_weekend_setback_and_door_openings():
    tuesday, sunday = weekday_and_weekend_days()
    # day/night: about ±1 °C (plus the HVAC's day mode and the doors on a weekday)
    assert 2 * WEEK_DAILY_AMPLITUDE_C - 0.1 <= np.ptp(sunday) <= 2 * WEEK_DAILY_AMPLITUDE_C + 0.05
    assert 2 * WEEK_DAILY_AMPLITUDE_C <= np.ptp(tuesday) <= 2 * WEEK_DAILY_AMPLITUDE_C + 0.5
    # the weekend setback: the whole of Sunday sits lower by the setback (the HVAC's step is off too)
    assert np.mean(sunday) - np.mean(tuesday) == pytest.approx(WEEK_SETBACK_C - 0.1, abs=0.05)
    # a door opening: a dip of ~0.3 °C that is gone 12 min later; none on Sunday at the same hour
    scenario = get_scenario("week")
    hour = WEEK_DOOR_TIMES_H[0]
    for day, dips in ((1, True), (6, False)):
        t = 86400.0 * day + 3600.0 * (hour + np.array([-0.1, 0.05, 0.3]))
        before, during, after = scenario.air(t)
        dip = during - (before + after) / 2  # the daily cycle's own curvature over 24 min: a few hundredths
        if dips:
            assert dip == pytest.approx(WEEK_DOOR_DIP_C, abs=0.05)
        else:
            assert abs(dip) < 0.05


def test_the_week_reaches_the_thermocouples_through_the_physics():
    physics = CellPhysics.create("week", seed=0)
    t = np.arange(0.0, 7 * 86400.0, 300.0)
    stage = physics.thermal(t)["stage"]
    per_day = stage.reshape(7, -1)
    assert np.all(np.ptp(per_day[1:5], axis=1) > 1.6)  # the stage (tau 15 min) follows the daily cycle
    assert per_day[6].mean() < per_day[2].mean() - 0.4  # ... and the setback


def test_a_scaled_clock_starts_at_a_utc_midnight_with_the_scenario_and_labels_records_with_its_days():
    section = SimulationConfig(scenario="week", speed=10_000.0)
    clock = PLUGIN.make_clock(section)
    assert isinstance(clock, ScaledClock)
    assert clock.start_unix_s % 86400.0 == 0.0
    label = PLUGIN.label_clock(clock)
    assert label() == pytest.approx(clock.now(), abs=600.0)  # the cell's clock, not the wall's
    context = DriverContext(clock=clock, sections={"simulation": section})
    PLUGIN.create(default_sensor_configs(speed=section.speed), context)
    cell = context.resources.get(RESOURCE_KEY, SimulatedCell)
    assert cell is not None and cell.epoch == clock.start_unix_s  # scenario day k is the clock's day k
    wall = PLUGIN.make_clock(SimulationConfig(speed=1.0))
    assert isinstance(wall, MonotonicClock)
    assert PLUGIN.label_clock(wall)() == pytest.approx(__import__("time").time(), abs=5.0)


def test_default_sensors_on_a_fast_clock_are_polled_and_aged_within_what_the_daemon_serves():
    paper = {s.name: s for s in default_sensor_configs()}
    fast = {s.name: s for s in default_sensor_configs(speed=10_000.0)}
    assert (paper["T1"].interval_s, paper["T1"].max_age_s) == (0.5, 5.0)  # unchanged at speed 1
    limits = SimulationConfig(speed=10_000.0)
    for sensor in fast.values():
        assert sensor.interval_s >= limits.min_interval_s
        assert sensor.max_age_s >= limits.min_max_age_s
    assert limits.timing_warnings(list(enumerate(fast.values()))) == []
    warnings = limits.timing_warnings(list(enumerate(paper.values())))
    assert any(w.startswith("sensors[0] (T1).max_age_s: 5 s of cell time is 0.5 ms of wall time") for w in warnings)
    assert any(w.startswith("sensors[4] (interferometer).interval_s:") for w in warnings)


@pytest.mark.parametrize(("axes", "channel", "true_column", "measured_column"), [
    ("x", "interferometer", "true_x_um", "measured_x_um"),  # the one-axis columns benchmarks/week.py reads
    ("xy", "interferometer_y", "true_um", "measured_um"),  # a stack's: one line per reading, with its axis
])
def test_the_truth_log_holds_each_interferometer_reading_beside_the_true_position(
        tmp_path: Path, axes: str, channel: str, true_column: str, measured_column: str) -> None:
    path = tmp_path / "truth.csv"
    clock = VirtualClock(0.0)
    cell = SimulatedCell(CellPhysics.create("week", seed=3, axes=axes), clock, truth_log=str(path))
    cell.epoch = 0.0
    axis = axes[-1]

    async def run() -> list[tuple[float, float, float]]:
        seen = []
        cell.command(axis, 240.0)
        for _ in range(50):
            await clock.sleep(60.0)
            reading = cell.read([channel, "T1"])[channel]
            seen.append((reading.t, cell.true_positions()[axis], reading.value))
        return seen

    seen = asyncio.run(run())
    with open(path, newline="") as handle:
        rows = list(csv.DictReader(handle))
    assert [(float(r["t_s"]), float(r[true_column]), float(r[measured_column])) for r in rows] == seen
    assert {float(r["q_um"]) for r in rows} == {240.0} and {r.get("axis", axis) for r in rows} == {axis}
    errors = np.array([m - x for _, x, m in seen])
    assert 0.0 < np.std(errors) < 0.1 and np.all(np.abs(errors) < 0.2)  # noise and wander, no drift


def test_the_realistic_cells_truth_log_holds_plain_numbers(tmp_path: Path) -> None:
    """Issue 27: the realistic cell's interferometer reading was numpy's float, logged as ``np.float64(0.88)``,
    which benchmarks/week.py (its default cell now) could not read."""
    path = tmp_path / "truth.csv"
    clock = VirtualClock(0.0)
    cell = SimulatedCell(CellPhysics.create("week", seed=3, cell="realistic"), clock, truth_log=str(path))
    cell.epoch = 0.0

    async def run() -> list[float]:
        cell.command("x", 240.0)
        values = []
        for _ in range(5):
            await clock.sleep(60.0)
            values.append(cell.read(["interferometer"])["interferometer"].value)
        return values

    values = asyncio.run(run())
    assert all(type(v) is float for v in values)
    logged = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    assert logged.shape == (5, 4) and list(logged[:, 3]) == values
