"""The simulated cell stepped through time: what the simulated sensors read and the actuator moves.

One instance per daemon/procedure, shared by every simulated sensor group and the actuator (through
``DriverContext.resources``), so a command moves the stage the interferometer then sees. Time is the
clock's, relative to the cell's creation (scenario time 0). Faults can be injected per channel
for tests and demos: ``fault`` (burnout reading), ``stale`` (the device repeats an old sample),
``device_error`` (the link fails: :class:`~drivers.base.DeviceError`).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

import numpy as np

from drivers.base import Clock, DeviceError, MonotonicClock, Reading, State
from drivers.simulated.physics import POSITION_CHANNEL, THERMOCOUPLES, TRUTH_CHANNELS, CellPhysics, StageState

FaultMode = Literal["fault", "stale", "device_error"]
CHANNELS: tuple[str, ...] = (*THERMOCOUPLES, *TRUTH_CHANNELS, POSITION_CHANNEL)


@dataclass(frozen=True)
class FaultWindow:
    channel: str
    start_s: float
    end_s: float
    mode: FaultMode = "fault"


class SimulatedCell:
    def __init__(self, physics: CellPhysics, clock: Clock | None = None) -> None:
        self.physics = physics
        self.clock = clock or MonotonicClock()
        self.epoch = self.clock.now()
        self.state = StageState()
        self.faults: list[FaultWindow] = []
        self.commands = 0
        self._landing_rng = np.random.default_rng([physics.seed, 2])
        self._noise_rng = np.random.default_rng([physics.seed, 3])
        self._last_ok: dict[str, Reading] = {}
        self._offsets = dict(physics.params.offsets_c)
        #: the true attained position behind the last interferometer reading (nan before one):
        #: what a validation on the simulated cell is scored against besides the interferometer
        self.last_true_position_um = math.nan

    def sim_time(self) -> float:
        return self.clock.now() - self.epoch

    # ----- actuator side -------------------------------------------------------------------------
    def command(self, q_um: float) -> None:
        """The stage's closed loop takes setpoint ``q_um`` now."""
        landing = float(self._landing_rng.normal(0.0, self.physics.params.landing_sigma_um))
        self.state = self.physics.after_command(self.state, self.sim_time(), float(q_um), landing)
        self.commands += 1

    def true_position(self, t: float | None = None) -> float:
        return self.physics.attained_now(self.sim_time() if t is None else t, self.state)

    # ----- sensor side ---------------------------------------------------------------------------
    def inject_fault(self, channel: str, start_s: float, end_s: float, mode: FaultMode = "fault") -> None:
        """Make ``channel`` misbehave during [start_s, end_s) of scenario time."""
        if channel not in CHANNELS:
            raise ValueError(f"unknown simulated channel {channel!r}; channels: {', '.join(CHANNELS)}")
        self.faults.append(FaultWindow(channel, start_s, end_s, mode))

    def _fault(self, channel: str, t: float) -> FaultWindow | None:
        for window in self.faults:
            if window.channel == channel and window.start_s <= t < window.end_s:
                return window
        return None

    def read(self, channels: Iterable[str]) -> dict[str, Reading]:
        """One poll of ``channels`` now, with noise; honours injected faults."""
        t = self.sim_time()
        now = self.clock.now()
        names = list(channels)
        out: dict[str, Reading] = {}
        thermal = self.physics.thermal1(t) if any(c != POSITION_CHANNEL for c in names) else {}
        offsets = self._offsets
        for name in names:
            window = self._fault(name, t) if self.faults else None
            if window is not None and window.mode == "device_error":
                raise DeviceError(f"simulated {name}: link failure (injected)")
            unit = "um" if name == POSITION_CHANNEL else "degC"
            if window is not None and window.mode == "fault":
                out[name] = Reading.fault(now, "open thermocouple (injected)" if unit == "degC" else
                                          "beam lost (injected)", unit=unit)
                continue
            if window is not None and window.mode == "stale" and name in self._last_ok:
                out[name] = self._last_ok[name]
                continue
            noise = float(self._noise_rng.standard_normal())
            if name == POSITION_CHANNEL:
                self.last_true_position_um = self.physics.attained_now(t, self.state)
                value = self.physics.measure_position1(t, self.last_true_position_um, noise)
            else:
                node = THERMOCOUPLES.get(name) or TRUTH_CHANNELS[name]
                value = self.physics.measure_temperature1(thermal[node] + offsets.get(name, 0.0), noise)
            reading = Reading(value=value, t=now, state=State.OK, unit=unit)
            if math.isfinite(value):
                self._last_ok[name] = reading
            out[name] = reading
        return out
