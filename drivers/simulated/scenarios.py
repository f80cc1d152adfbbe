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

from drivers.simulated.effects import UnknownNameError

Trajectory = Literal["calibration", "bidirectional", "validation"]


@dataclass(frozen=True)
class Scenario:
    name: str
    description: str
    waypoints_h: tuple[tuple[float, float], ...]
    trajectory: Trajectory = "calibration"
    compensated: bool = True  # for validation scenarios: whether the paper ran the model (test 1: no)

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
        return temps[i] + (temps[i + 1] - temps[i]) * shape


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
            compensated=False,
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
    )
}


def get_scenario(name: str) -> Scenario:
    try:
        return SCENARIOS[name]
    except KeyError:
        raise UnknownNameError(f"unknown scenario {name!r}; valid scenarios: {', '.join(SCENARIOS)}") from None
