"""The one owner of motion: where a move starts, how fast it goes, what may be sent. Pure computation.

The daemon's actuation (``nanodrift.service.actuation``) and the procedures (``nanodrift.procedure.steps``)
both move the stage through these rules, so a calibration run and the service can never disagree on
what is safe:

- **Limits**: nothing outside ``[v_min, v_max]`` is ever sent, and what is checked is the value the
  device actually receives (a DAC's counts, a controller's formatted digits: ``Actuator.sent_voltage``),
  not the float that was asked for.
- **Where a move starts** (:func:`trusted_start`): a device's read-back is a claim, checked before it is
  believed. A read-back outside the limits, or one that disagrees with the last voltage written to that
  device, is *unknown*, never a start point: the stage is never ramped from (or towards) a lie.
- **Slew** (:class:`Slew`): ``max_slew_um_per_s`` is a rate in µm per second of elapsed time. Each
  sub-command of a ramp covers the time since the previous one began, so a device that takes 10 ms to
  answer slows nothing down (the ramp's duration is distance / rate), and a loop that stalls never
  turns into a jump (the time one step may cover is capped).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

#: a ramp's sub-commands are this far apart (at least): an output needs no more than 50 updates a second
RAMP_PERIOD_S = 0.02
#: the most time one sub-command may cover: a loop stalled for longer resumes at the rate, not with a jump
MAX_STEP_INTERVAL_S = 5 * RAMP_PERIOD_S
#: a read-back within this of a voltage sent agrees with it (what is compared was quantized the same way)
READ_BACK_TOLERANCE_V = 0.001


class MotionLimits(Protocol):
    """What motion needs of ``[actuator]`` (``nanodrift.config.ActuatorConfig`` has it): gain and limits."""

    volts_per_um: float
    offset_v: float
    v_min: float
    v_max: float
    max_slew_um_per_s: float


def voltage_for(limits: MotionLimits, q_um: float) -> float:
    """The one voltage rule: what the amplifier gets for command ``q_um``."""
    return limits.offset_v + limits.volts_per_um * q_um


def q_um_for(limits: MotionLimits, voltage_v: float) -> float:
    """The command whose voltage is ``voltage_v``: the inverse of :func:`voltage_for`."""
    return (voltage_v - limits.offset_v) / limits.volts_per_um


def within_limits(limits: MotionLimits, voltage_v: float) -> bool:
    """Nothing outside ``[v_min, v_max]`` is ever published or sent (NaN is outside)."""
    return limits.v_min <= voltage_v <= limits.v_max


class VoltageLimitError(ValueError):
    """A command whose voltage would leave ``[v_min, v_max]``: never sent."""


def checked_voltage(limits: MotionLimits, q_um: float) -> float:
    """:func:`voltage_for`, or a :class:`VoltageLimitError` naming the command and the limits: the one
    check of a command against the limits, for the daemon's targets and the procedures' steps alike."""
    voltage = voltage_for(limits, q_um)
    if not within_limits(limits, voltage):  # NaN fails it too
        raise VoltageLimitError(f"command q {q_um:.4f} µm needs {voltage:.4f} V, outside "
                                f"[{limits.v_min:g}, {limits.v_max:g}] V")
    return voltage


@dataclass(frozen=True, slots=True)
class StartPoint:
    """Where the stage is before a move (``voltage_v`` None: unknown), how that is known, and why a
    read-back was not believed (``distrust``, None when it was or there was none)."""

    voltage_v: float | None
    known_from: str  # "read back" | "last written" | "safe_voltage_v" | "unknown"
    distrust: str | None = None


def trusted_start(limits: MotionLimits, read_back_v: float | None, sent_v: tuple[float, ...],
                  safe_voltage_v: float, *, tolerance_v: float = READ_BACK_TOLERANCE_V) -> StartPoint:
    """Where a move may start from, believing nothing a device cannot prove.

    ``read_back_v``: what the device says its output holds (None: it cannot say). ``sent_v``: the
    voltages last sent to this device that it may hold (the last one confirmed and the last one tried;
    empty when nothing was sent yet). A read-back is believed only when it is finite, inside the limits
    and, once something was sent, agrees with one of those; otherwise the start is unknown, since the
    device contradicts what we know. With no read-back: the last voltage sent, else a finite
    ``safe_voltage_v`` (where a clean stop leaves the stage), else unknown.
    """
    if read_back_v is not None:
        if not math.isfinite(read_back_v):
            return StartPoint(None, "unknown", f"read back {read_back_v} V, not a number")
        if not within_limits(limits, read_back_v):
            return StartPoint(None, "unknown", f"read back {read_back_v:.4f} V, outside "
                              f"[{limits.v_min:g}, {limits.v_max:g}] V")
        if sent_v and all(abs(read_back_v - v) > tolerance_v for v in sent_v):
            return StartPoint(None, "unknown", f"read back {read_back_v:.4f} V, but {sent_v[-1]:.4f} V "
                              "was sent last")
        return StartPoint(read_back_v, "read back")
    if sent_v and math.isfinite(sent_v[-1]):
        return StartPoint(sent_v[-1], "last written")
    if math.isfinite(safe_voltage_v):
        return StartPoint(safe_voltage_v, "safe_voltage_v")
    return StartPoint(None, "unknown")


class Slew:
    """The next voltage of a move under ``max_slew_um_per_s``, stepping on elapsed time.

    ``next_voltage`` is asked just before each write with the time it is asked at (any monotonic
    seconds); ``wrote`` is told once that write returned, with the time it returned. A step covers the
    time since the previous write returned, not since it began: the device had the previous value by
    then and gets the next one after this step is asked for, so however late the loop or the device,
    between any two values a device receives it never moves faster than the rate (a stamp taken before
    the write let a loop late by 4 ms put 56 um in 24 ms on a 2000 um/s device). A move from rest covers
    one :data:`RAMP_PERIOD_S` in its first step, or less when the device's last write (of any move: one
    a stop or a reload cut short) returned less than that ago.
    """

    def __init__(self) -> None:
        self._last_step_s: float | None = None  # when the previous sub-command of a ramp returned
        self._last_write_s: float | None = None  # when the last sub-command of any move returned

    def rest(self) -> None:
        """The stage is at rest (a move ended, or nothing is known): the next move starts afresh."""
        self._last_step_s = None

    def next_voltage(self, limits: MotionLimits, at_v: float | None, goal_v: float, now_s: float) -> float:
        """The voltage to send now on the way from ``at_v`` to ``goal_v`` (the goal itself when it is within
        reach, when the slew limit is off, or when ``at_v`` is unknown)."""
        slew = limits.max_slew_um_per_s
        if slew <= 0 or at_v is None:
            return goal_v
        since = self._last_step_s
        if since is None:  # from rest: one ramp period, never more time than passed since the last write
            last = self._last_write_s
            interval_s = RAMP_PERIOD_S if last is None else min(max(now_s - last, 0.0), RAMP_PERIOD_S)
        else:
            interval_s = min(max(now_s - since, 0.0), MAX_STEP_INTERVAL_S)
        max_step_v = slew * abs(limits.volts_per_um) * interval_s
        delta = goal_v - at_v
        if abs(delta) <= max_step_v:
            return goal_v
        return at_v + math.copysign(max_step_v, delta)

    def wrote(self, returned_s: float, reached_goal: bool) -> None:
        """A sub-command's write returned at ``returned_s``; ``reached_goal``: it was the goal itself."""
        self._last_step_s = None if reached_goal else returned_s
        self._last_write_s = returned_s


def ramp_seconds(limits: MotionLimits, from_v: float, to_v: float) -> float:
    """How long a ramp takes at the slew limit (0 when it is off)."""
    slew = limits.max_slew_um_per_s
    if slew <= 0:
        return 0.0
    return abs(to_v - from_v) / (slew * abs(limits.volts_per_um))
