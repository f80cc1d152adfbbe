"""The simulated cell stepped through time: what the simulated sensors read and the actuator moves.

One instance per daemon/procedure, shared by every simulated sensor group and the actuator (through
``DriverContext.resources``), so a command moves the stage the interferometer then sees. Time is the
clock's, relative to the cell's creation (scenario time 0). Faults can be injected per channel
for tests and demos: ``fault`` (burnout reading), ``stale`` (the device repeats an old sample),
``device_error`` (the link fails: :class:`~nanodrift.drivers.base.DeviceError`).

``truth_log``: a CSV the cell appends each interferometer reading to with the true attained position
(``t_s,q_um,true_x_um,measured_x_um``, one line each, line-buffered: nothing held in memory), so a
benchmark can score what the daemon served against the truth, not only the interferometer's view.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Literal, TextIO

import numpy as np

from nanodrift.drivers.base import Clock, DeviceError, MonotonicClock, Reading, State
from nanodrift.drivers.simulated.physics import POSITION_CHANNEL, THERMOCOUPLES, TRUTH_CHANNELS, CellPhysics, StageState

FaultMode = Literal["fault", "stale", "device_error"]
CHANNELS: tuple[str, ...] = (*THERMOCOUPLES, *TRUTH_CHANNELS, POSITION_CHANNEL)


@dataclass(frozen=True)
class FaultWindow:
    channel: str
    start_s: float
    end_s: float
    mode: FaultMode = "fault"


class SimulatedCell:
    TRUTH_HEADER = "t_s,q_um,true_x_um,measured_x_um\n"
    #: what a sensor may read (``[[sensors]] channel``)
    channels: tuple[str, ...] = CHANNELS

    def __init__(self, physics: CellPhysics, clock: Clock | None = None, truth_log: str | None = None) -> None:
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
        self.truth_log = truth_log
        self._truth_file: TextIO | None = None
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
        if channel not in self.channels:
            raise ValueError(f"unknown simulated channel {channel!r}; channels: {', '.join(self.channels)}")
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
        thermal = self.physics.thermal1(t) if any(not self.is_position(c) for c in names) else {}
        offsets = self._offsets
        for name in names:
            window = self._fault(name, t) if self.faults else None
            if window is not None and window.mode == "device_error":
                raise DeviceError(f"simulated {name}: link failure (injected)")
            unit = "um" if self.is_position(name) else "degC"
            if window is not None and window.mode == "fault":
                out[name] = Reading.fault(now, "open thermocouple (injected)" if unit == "degC" else
                                          "beam lost (injected)", unit=unit)
                continue
            if window is not None and window.mode == "stale" and name in self._last_ok:
                out[name] = self._last_ok[name]
                continue
            noise = float(self._noise_rng.standard_normal())
            if self.is_position(name):
                value = self._read_position(name, t, now, noise)
            else:
                node = THERMOCOUPLES.get(name) or TRUTH_CHANNELS[name]
                value = self.physics.measure_temperature1(thermal[node] + offsets.get(name, 0.0), noise)
            reading = Reading(value=value, t=now, state=State.OK, unit=unit)
            if math.isfinite(value):
                self._last_ok[name] = reading
            out[name] = reading
        return out

    def is_position(self, channel: str) -> bool:
        """Whether ``channel`` is an interferometer (µm), not a temperature."""
        return channel == POSITION_CHANNEL

    def true_reading(self, channel: str) -> float | None:
        """The true attained position behind ``channel``'s last reading (None: a temperature channel)."""
        return self.last_true_position_um if channel == POSITION_CHANNEL else None

    def _read_position(self, channel: str, t: float, now: float, noise: float) -> float:
        self.last_true_position_um = true_x = self.physics.attained_now(t, self.state)
        value = self.physics.measure_position1(t, true_x, noise)
        if self.truth_log is not None:
            self._log_truth(now, true_x, value)
        return value

    def _log_truth(self, t: float, true_x_um: float, measured_x_um: float) -> None:
        self._log_line(f"{t!r},{self.state.q!r},{true_x_um!r},{measured_x_um!r}\n")

    def _log_line(self, line: str) -> None:
        if self._truth_file is None:
            assert self.truth_log is not None
            path = Path(self.truth_log)
            fresh = not path.exists() or path.stat().st_size == 0
            self._truth_file = open(path, "a", buffering=1, encoding="utf-8")  # held open: a line a poll
            if fresh:
                self._truth_file.write(self.TRUTH_HEADER)
        self._truth_file.write(line)
