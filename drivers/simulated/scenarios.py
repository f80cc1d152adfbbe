"""Room-temperature histories (the air around the cell) for training and the paper's five tests.

A scenario is a list of waypoints (hours, °C) joined by half-cosine segments, held constant before
the first and after the last. Time 0 is the start of the run; waypoints before 0 are the room's
history, so the structures are not at equilibrium when the run starts. The cell's reference
temperature (the interferometer was zeroed there, paper III.A) is 22.0 °C: the start of ``train``.

Tests 1-4 stay inside the training range of T4 (about 21.55-22.0 °C); test 5's room rises 0.7 °C
during the test (paper Fig. 10) and ends ~1.5 °C above the training range, which makes its drift
about three times calibration's, as in the paper.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from nanodrift.drivers.simulated.effects import UnknownNameError

Trajectory = Literal["calibration", "bidirectional", "validation"]


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    waypoints_h: tuple[tuple[float, float], ...]
    trajectory: Trajectory = "calibration"

    @property
    def start_h(self) -> float:
        return self.waypoints_h[0][0]

    def air(self, t_s: np.ndarray) -> np.ndarray:
        """The scenario's air temperature (without the random fluctuation) at times ``t_s``."""
        times = np.array([w[0] * 3600.0 for w in self.waypoints_h])
        temps = np.array([w[1] for w in self.waypoints_h])
        t = np.asarray(t_s, dtype=np.float64)
        if times.size == 1:
            return np.full_like(t, temps[0])
        i = np.clip(np.searchsorted(times, t, side="right") - 1, 0, times.size - 2)
        span = times[i + 1] - times[i]
        frac = np.clip((t - times[i]) / span, 0.0, 1.0)
        shape = 0.5 - 0.5 * np.cos(np.pi * frac)
        result: np.ndarray = temps[i] + (temps[i + 1] - temps[i]) * shape
        return result


#: the ``week`` scenario's room (hours from Monday 00:00, °C): what a lab's air does over a week
WEEK_MEAN_C = 21.78  # the middle of the ``train`` range: the lab's set-point
WEEK_DAILY_AMPLITUDE_C = 1.0  # day/night: warmest at 15:00, coolest at 03:00
WEEK_HVAC_STEP_C = 0.2  # weekdays: the HVAC's day mode from 07:00 to 19:00 (30 min transitions)
WEEK_SETBACK_C = -0.5  # weekend: Friday 19:00-21:00 down, back on Monday 05:00-07:00
WEEK_DOOR_DIP_C = -0.3  # a door opened on a weekday: the air dips for ~12 min
WEEK_DOOR_TIMES_H = (8.5, 10.75, 12.25, 13.67, 16.0, 17.08)  # hour of the day of each opening (weekdays)


def _ramp(h: float, start_h: float, length_h: float) -> float:
    return min(1.0, max(0.0, (h - start_h) / length_h))


def week_air_c(h: float) -> float:
    """The ``week`` room's air without the door openings: daily cycle + HVAC day mode + weekend setback."""
    day, hour = divmod(h, 24.0)
    weekday = int(day) % 7  # 0: Monday
    daily = WEEK_DAILY_AMPLITUDE_C * float(np.sin(2 * np.pi * (hour - 9.0) / 24.0))
    hvac = WEEK_HVAC_STEP_C * (_ramp(hour, 7.0, 0.5) - _ramp(hour, 19.0, 0.5)) if weekday < 5 else 0.0
    if weekday == 4:
        setback = _ramp(hour, 19.0, 2.0)
    elif weekday in (5, 6):
        setback = 1.0
    elif weekday == 0:
        setback = 1.0 - _ramp(hour, 5.0, 2.0)
    else:
        setback = 0.0
    return WEEK_MEAN_C + daily + hvac + WEEK_SETBACK_C * setback


def _week_waypoints(days: int = 8) -> tuple[tuple[float, float], ...]:
    """Every 30 min of :func:`week_air_c`, with each door opening as three extra points (start, bottom
    3 min later, back 12 min after the start); from 2 h before Monday (the room's history)."""
    points = {float(h): week_air_c(float(h)) for h in np.arange(-2.0, 24.0 * days + 1e-9, 0.5)}
    for day in range(days):
        if day % 7 >= 5:
            continue
        for hour in WEEK_DOOR_TIMES_H:
            start = 24.0 * day + hour
            for offset_h, dip in ((0.0, 0.0), (0.05, WEEK_DOOR_DIP_C), (0.2, 0.0)):
                points[start + offset_h] = week_air_c(start + offset_h) + dip
    return tuple(sorted(points.items()))


SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("steady", "constant 22.0 °C room (only the small random fluctuation)", ((-2.0, 22.0),)),
        Scenario(
            "train",
            "calibration (paper III.B): the room cools 0.45 °C over 1.6 h, then warms back (~4 h)",
            ((-2.0, 22.0), (0.0, 22.0), (1.6, 21.55), (3.4, 21.98), (5.0, 22.0)),
        ),
        Scenario(
            "bidirectional",
            "the train room history with up-and-down sweeps (direction-dependent effects show)",
            ((-2.0, 22.0), (0.0, 22.0), (1.6, 21.55), (3.4, 21.98), (5.0, 22.0)),
            trajectory="bidirectional",
        ),
        Scenario(
            "test1",
            "validation without compensation, in the training range, slowly cooling",
            ((-2.0, 21.76), (0.0, 21.70), (0.9, 21.63), (1.8, 21.66)),
            trajectory="validation",
        ),
        Scenario(
            "test2",
            "validation with the model, in range, mild warming",
            ((-2.0, 21.66), (0.0, 21.67), (1.8, 21.76)),
            trajectory="validation",
        ),
        Scenario(
            "test3",
            "validation with the model, in range, cooling then warming",
            ((-2.0, 21.74), (0.0, 21.71), (0.9, 21.63), (1.8, 21.68)),
            trajectory="validation",
        ),
        Scenario(
            "test4",
            "validation with the model, in range, warming from the low end",
            ((-2.0, 21.64), (0.0, 21.64), (1.8, 21.75)),
            trajectory="validation",
        ),
        Scenario(
            "test5",
            "validation with the model, out of range: a heating room, 0.7 °C rise, ending ~1.5 °C above training",
            ((-3.0, 22.0), (-1.0, 22.8), (0.0, 22.8), (1.8, 23.5)),
            trajectory="validation",
        ),
        Scenario(
            "room",
            "a lab day inside the shipped model's training range: ±0.12 °C around 21.78 °C over 8 h "
            "(what `nanodrift run` serves when there is no config)",
            tuple((h, 21.78 + 0.12 * float(np.sin(2 * np.pi * h / 8.0))) for h in np.arange(-2.0, 240.0, 0.5)),
        ),
        Scenario(
            "daily",
            "a day/night room cycle (±0.4 °C over 24 h) for long daemon runs",
            tuple((h, 22.0 + 0.4 * float(np.sin(2 * np.pi * h / 24.0))) for h in np.arange(-2.0, 240.0, 1.0)),
        ),
        Scenario(
            "week",
            f"a lab's week from Monday 00:00: ±{WEEK_DAILY_AMPLITUDE_C:g} °C day/night around {WEEK_MEAN_C:g} °C, "
            f"HVAC day mode {WEEK_HVAC_STEP_C:+g} °C 07:00-19:00 on weekdays, weekend setback "
            f"{WEEK_SETBACK_C:+g} °C (Friday 19:00 to Monday 07:00), {len(WEEK_DOOR_TIMES_H)} door openings "
            f"a weekday ({WEEK_DOOR_DIP_C:+g} °C for ~12 min); 8 days, then held",
            _week_waypoints(),
            trajectory="validation",
        ),
    )
}


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise UnknownNameError(f"unknown scenario {name!r}; valid scenarios: {', '.join(SCENARIOS)}") from None
