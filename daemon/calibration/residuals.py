"""Is the model still right? Settled residuals from the interferometer, their statistics, a bias tracker.

Pure: the daemon's health unit (:mod:`nanodrift.service.health_unit`) feeds it commands and position
readings, ``validate --adapt`` feeds it step averages (``nanodrift.procedure``); both get the same numbers
from the same samples.

- :class:`SettleTracker`: a served target the stage then holds (no newer command for ``settle_s``)
  yields one *settled residual*: the mean of the ``ok`` position readings over ``window_s`` minus
  the target. A newer command abandons the hold; a reading that is not ``ok`` inside the window
  voids it (a stale interferometer never feeds the monitor or the tracker); a window with no reading
  in it at all (a sensor that polls slower than ``window_s``) is counted in ``unfilled_windows``.
- :class:`HealthMonitor`: rolling RMS and mean over the last ``history`` residuals; state
  ``unknown`` (no position sensor, or fewer than ``MIN_RESIDUALS``), ``ok``, or ``degraded`` (RMS
  above ``alarm_rms_nm``), with advice in words.
- :class:`BiasTracker`: ``[adapt] mode = "bias"``: a first-order tracker (time constant ``tau_s``)
  of the settled residual, slew-limited and clamped to ``max_um``, applied as a correction
  ``correction_um`` added to every command.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

#: below this many residuals the state is "unknown": a handful of targets says little
MIN_RESIDUALS = 5
#: the bias tracker's correction moves at most max_um per tau_s (no step larger than a lag allows)
SLEW_TAUS = 1.0


def believable_residual(residual_um: float) -> bool:
    """A residual the statistics can take: finite, and so is its square (1e200 µm would make every later
    RMS and σ infinite for good). Anything else is a broken reading, never a stage."""
    return math.isfinite(residual_um * residual_um)


@dataclass(frozen=True)
class Settled:
    """One held target: where the stage was told to go and where the interferometer saw it."""

    t: float  # end of the averaging window (cell clock, s)
    x_um: float  # the target
    q_um: float  # the command sent (model + correction)
    position_um: float  # mean of the ok readings in the window
    samples: int
    temperatures: Mapping[str, float] = field(default_factory=dict)
    #: the daemon's own number of the command held (every axis of one command has the same): a cell's
    #: record row pairs its axes by it, never by the client's id (ids repeat, or are absent)
    sequence: int | None = None

    @property
    def residual_um(self) -> float:
        return self.position_um - self.x_um


@dataclass
class _Hold:
    t_command: float
    x_um: float
    q_um: float
    temperatures: Mapping[str, float]
    sequence: int | None
    total_um: float = 0.0
    samples: int = 0
    void: bool = False
    reached: bool = True  # the stage holds the command (False: a ramp towards it is still under way)


class SettleTracker:
    """Commands and position readings in, settled residuals out (see the module docstring)."""

    def __init__(self, settle_s: float, window_s: float) -> None:
        if settle_s < 0 or window_s <= 0:
            raise ValueError(f"settle_s must be >= 0 and window_s > 0, got {settle_s}, {window_s}")
        self.settle_s = settle_s
        self.window_s = window_s
        self._hold: _Hold | None = None
        #: holds whose window closed with no reading inside it: the sensor polls slower than ``window_s``
        self.unfilled_windows = 0

    def commanded(self, t: float, x_um: float, q_um: float, temperatures: Mapping[str, float] | None = None,
                  sequence: int | None = None, *, reached: bool = True) -> None:
        """A command went out at cell time ``t``: any hold in progress is superseded. ``reached`` False:
        the output is still ramping towards it; the settle time starts at :meth:`reached`, not now."""
        self._hold = _Hold(t, x_um, q_um, dict(temperatures or {}), sequence, reached=reached)

    def reached(self, t: float, q_um: float) -> None:
        """The output reached command ``q_um`` at cell time ``t``: the hold of that command settles from then."""
        hold = self._hold
        if hold is not None and not hold.reached and hold.q_um == q_um:
            hold.t_command = max(hold.t_command, t)
            hold.reached = True

    def position(self, t: float, value_um: float, ok: bool) -> Settled | None:
        """A position reading taken at ``t``; the settled residual when this reading closes a window."""
        hold = self._hold
        if hold is None or not hold.reached:
            return None  # mid-ramp: the stage is not where it was told yet
        start = hold.t_command + self.settle_s
        end = start + self.window_s
        if t < start:
            return None
        if t <= end:
            if ok and math.isfinite(value_um):
                hold.total_um += value_um
                hold.samples += 1
            else:
                hold.void = True
            return None
        self._hold = None  # the window is over: one residual per hold at most
        if hold.samples == 0 and not hold.void:
            self.unfilled_windows += 1
        if hold.void or hold.samples == 0:
            return None
        return Settled(end, hold.x_um, hold.q_um, hold.total_um / hold.samples, hold.samples, hold.temperatures,
                       hold.sequence)


class HealthMonitor:
    """Rolling statistics of settled residuals and what they mean for the operator."""

    def __init__(self, history: int, alarm_rms_nm: float, *, has_position_sensor: bool = True) -> None:
        if history < 1 or not alarm_rms_nm > 0:
            raise ValueError(f"history must be >= 1 and alarm_rms_nm > 0, got {history}, {alarm_rms_nm}")
        self.alarm_rms_nm = alarm_rms_nm
        self.has_position_sensor = has_position_sensor
        self._residuals_nm: deque[float] = deque(maxlen=history)
        self.total = 0
        #: residuals refused as broken readings (:func:`believable_residual`)
        self.rejected = 0

    def add(self, settled: Settled) -> None:
        """One settled residual; an unbelievable one (:func:`believable_residual`) is counted in ``rejected``."""
        if not believable_residual(settled.residual_um * 1e3):
            self.rejected += 1
            return
        self._residuals_nm.append(settled.residual_um * 1e3)
        self.total += 1

    def reset(self) -> None:
        """A new model: the old residuals say nothing about it."""
        self._residuals_nm.clear()

    @property
    def n(self) -> int:
        return len(self._residuals_nm)

    @property
    def residual_rms_nm(self) -> float | None:
        if not self._residuals_nm:
            return None
        return math.sqrt(sum(r * r for r in self._residuals_nm) / len(self._residuals_nm))

    @property
    def residual_mean_nm(self) -> float | None:
        if not self._residuals_nm:
            return None
        return sum(self._residuals_nm) / len(self._residuals_nm)

    @property
    def state(self) -> str:
        if not self.has_position_sensor or self.n < MIN_RESIDUALS:
            return "unknown"
        rms = self.residual_rms_nm
        return "degraded" if rms is not None and rms > self.alarm_rms_nm else "ok"

    def advice(self, outside: Sequence[OutsideRange] = (), sensor_problem: str | None = None) -> str | None:
        """What to do, in words (None when there is nothing to do).

        ``sensor_problem`` (``position sensor 'ifm' is stale: value frozen at ...``): the interferometer is
        the suspect, not the cell; that comes first, since no residual is taken from it meanwhile.
        """
        if not self.has_position_sensor:
            return "no position sensor: add the interferometer ([[sensors]] role = \"position\") to monitor the model"
        if sensor_problem:
            return (f"{sensor_problem}; check the interferometer, not the cell: no residual is taken from it until it "
                    "reads believable values again")
        if self.state != "degraded":
            if outside:
                return "; ".join(o.describe() for o in outside) + " (accuracy degrades outside the training range)"
            return None
        rms, mean = self.residual_rms_nm or 0.0, self.residual_mean_nm or 0.0
        if outside:
            return "recalibrate: " + "; ".join(o.describe() for o in outside)
        if abs(mean) > 0.5 * rms:
            return (f"residual mean {mean:+.0f} nm while in range: the cell changed (bracket, mounting, amplifier); "
                    "recalibrate")
        return (f"residual RMS {rms:.0f} nm above {self.alarm_rms_nm:.0f} nm with no steady offset: look for an "
                "effect the model lacks (nanodrift discover on recorded operation)")

    def document(self, *, correction_um: float | None, extrapolating: Sequence[str],
                 outside: Sequence[OutsideRange] = (), sensor_problem: str | None = None) -> dict[str, object]:
        """The ``health`` payload of the Zenoh contract."""
        rms, mean = self.residual_rms_nm, self.residual_mean_nm
        return {
            "state": self.state,
            "residual_rms_nm": None if rms is None else round(rms, 3),
            "residual_mean_nm": None if mean is None else round(mean, 3),
            "n": self.n,
            "correction_um": correction_um,
            "extrapolating": list(extrapolating),
            "advice": self.advice(outside, sensor_problem),
        }


@dataclass(frozen=True)
class OutsideRange:
    """A channel outside the model's training range, and since when (cell clock)."""

    channel: str
    value: float
    low: float
    high: float
    since_t: float
    now_t: float

    def describe(self) -> str:
        above = self.value > self.high
        by = self.value - self.high if above else self.low - self.value
        minutes = max(0.0, self.now_t - self.since_t) / 60.0
        unit = "um" if self.channel == "x" else "°C"
        return (f"{self.channel} has been {by:.2f} {unit} {'above' if above else 'below'} the training range "
                f"[{self.low:.2f}, {self.high:.2f}] for {minutes:.0f} min")


class RangeWatch:
    """Remembers since when each channel has been outside its training range."""

    def __init__(self, ranges: Mapping[str, tuple[float, float]]) -> None:
        self.ranges = dict(ranges)
        self._since: dict[str, float] = {}
        self._latest: dict[str, tuple[float, float]] = {}

    def observe(self, t: float, values: Mapping[str, float]) -> None:
        for channel, value in values.items():
            bounds = self.ranges.get(channel)
            if bounds is None:
                continue
            self._latest[channel] = (t, value)
            if bounds[0] <= value <= bounds[1]:
                self._since.pop(channel, None)
            else:
                self._since.setdefault(channel, t)

    def outside(self) -> list[OutsideRange]:
        return [OutsideRange(channel, self._latest[channel][1], *self.ranges[channel], since, self._latest[channel][0])
                for channel, since in self._since.items()]


class BiasTracker:
    """``[adapt] mode = "bias"``: the correction that cancels the settled residual's slow part.

    Each settled residual r (position - target, with the current correction already applied)
    moves the correction c towards -r with weight 1 - exp(-dt / tau_s), dt the time since the
    previous residual (the first residual counts as ``first_dt_s``, one typical step). The change is
    limited to ``max_um * dt / tau_s`` (slew) and c to [-max_um, max_um] (clamp).
    """

    def __init__(self, tau_s: float, max_um: float, *, first_dt_s: float = 30.0) -> None:
        if not tau_s > 0 or not max_um >= 0:
            raise ValueError(f"tau_s must be > 0 and max_um >= 0, got {tau_s}, {max_um}")
        self.tau_s = tau_s
        self.max_um = max_um
        self.first_dt_s = first_dt_s
        self.reset()

    def reset(self) -> None:
        """A new model is loaded: its errors are not the old one's."""
        self.correction_um = 0.0
        self._last_t: float | None = None
        self.updates = 0
        self.rejected = 0
        #: the share of the model's own error the correction has not taken out yet: the product of
        #: the updates' exp(-dt / tau_s) (1 before the first residual)
        self.uncorrected = 1.0
        #: the residuals' mean square, weighted as the correction weighs them (µm²)
        self._residual_ms_um2 = 0.0

    @property
    def residual_rms_um(self) -> float:
        """RMS of the recent settled residuals (after correction), on the correction's own time scale."""
        filled = 1.0 - self.uncorrected  # the EWMA started from 0: divide by the weight it has gathered
        return math.sqrt(self._residual_ms_um2 / filled) if filled > 0 else 0.0

    def sigma_um(self, static_sigma_um: float, wander_um: float) -> float:
        """``q_sigma`` of a corrected command: what the tracker leaves of the true error.

        The correction takes out the model's error (``static_sigma_um``, the model's own q_sigma)
        at the rate it learns, and leaves what its residuals still show (their recent RMS, as the
        sensor sees them: lag, scatter) or the calibration's wander (``wander_um``), whichever is
        larger. The wander is either the sensor's own (the tracker follows it into the true error,
        and its residuals cannot show it) or a slow misfit of the stage (the tracker takes it out,
        and its residuals show what is left); one instrument cannot tell which, so the larger is
        taken, not the sum, which counted the stage's misfit twice (on the realistic cell ±2σ held
        99.6 % in range with RMS(e/σ) 0.78: ``benchmarks/coverage.py``). Before the first residual
        it is the static σ; then

            σ² = u²·static² + (1 - u²)·max(wander², residual RMS²),   u = :attr:`uncorrected`.
        """
        u2 = self.uncorrected * self.uncorrected
        followed = max(wander_um * wander_um, self.residual_rms_um ** 2)
        return math.sqrt(u2 * static_sigma_um * static_sigma_um + (1.0 - u2) * followed)

    def update(self, t: float, residual_um: float) -> float:
        """Feed one settled residual (ok readings only) ending at ``t``; the new correction. An unbelievable
        residual (:func:`believable_residual`) changes nothing: it is counted in ``rejected``."""
        if not believable_residual(residual_um):
            self.rejected += 1
            return self.correction_um
        dt = self.first_dt_s if self._last_t is None else max(0.0, t - self._last_t)
        self._last_t = t
        weight = 1.0 - math.exp(-dt / self.tau_s)
        self.uncorrected *= 1.0 - weight
        self._residual_ms_um2 += weight * (residual_um * residual_um - self._residual_ms_um2)
        step = -weight * residual_um
        limit = self.max_um * SLEW_TAUS * dt / self.tau_s
        step = max(-limit, min(limit, step))
        self.correction_um = max(-self.max_um, min(self.max_um, self.correction_um + step))
        self.updates += 1
        return self.correction_um
