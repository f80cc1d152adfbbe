"""The one owner of motion: where a move starts, how fast it goes, what may be sent. Pure computation.

The daemon's actuation (``nanodrift.service.actuation``) and the procedures (``nanodrift.procedure.steps``)
both move the stage through these rules, so a calibration run and the service can never disagree on
what is safe:

- **Limits**: nothing outside ``[v_min, v_max]`` is ever sent, and what is checked is the value the
  device actually receives (a DAC's counts, a controller's formatted digits: ``Actuator.sent_voltage``),
  not the float that was asked for.
- **Where a move starts** (:func:`trusted_start`): a device's read-back is a claim, checked before it is
  believed: inside the limits and agreeing with what was last written to that device (by this process,
  or, across a restart, as the durable record of ``nanodrift.output_record`` says), or on a first start
  with the output's power-up value. A claim this process can contradict starts the move from what it
  wrote; one nothing confirms is *unproven*: the stage is never ramped from (or towards) a lie, unless
  the axis' position sensor measures where that voltage puts the stage (:func:`position_disagreement`).
- **Slew** (:class:`Slew`): ``max_slew_um_per_s`` is a rate in µm per second of elapsed time. Each
  sub-command of a ramp covers the time since the previous write returned (the device had that value by
  then), so between any two values a device receives it never moves faster than the rate. A ramp waits
  :meth:`Slew.pause_s` between sub-commands, at least :data:`LATENCY_PAUSES` times the device's write
  time, so a slow device still ramps at >= 90 % of the rate; a loop that stalls never turns into a jump
  (the time one step may cover is capped).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

#: a ramp's sub-commands are this far apart (at least): an output needs no more than 50 updates a second
RAMP_PERIOD_S = 0.02
#: the most time one sub-command may cover on a fast device: a loop stalled for longer resumes at the rate,
#: not with a jump (a slow device's steps may cover more: :meth:`Slew.pause_s`)
MAX_STEP_INTERVAL_S = 5 * RAMP_PERIOD_S
#: a ramp waits at least this many times the device's last write between two sub-commands, so a step (which
#: covers only the time since the previous write returned) keeps a slow device at >= 90 % of the rate:
#: a module answering in 60 ms ramped at 25 % when every step waited one ramp period
LATENCY_PAUSES = 9.0
#: the share of the rate a ramp keeps whatever the device's latency (what check-config bounds a safe stop with)
SAFE_RATE_SHARE = LATENCY_PAUSES / (LATENCY_PAUSES + 1.0)
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
    """Where the stage is before a move (``voltage_v`` None: unknown or unproven), how that is known, and why a
    read-back was not believed (``distrust``, None when it was or there was none).

    ``known_from`` "unproven": the device claims a value nothing the daemon knows confirms (neither what it
    wrote, nor the power-up value on a first start): the output must not be moved until an operator confirms
    where it is."""

    voltage_v: float | None
    known_from: str  # "read back" | "power-up value" | "last written" | "safe_voltage_v" | "unknown" | "unproven"
    distrust: str | None = None
    #: an unproven claim inside the limits, which another witness (a position sensor) may still prove
    claimed_v: float | None = None


def trusted_start(limits: MotionLimits, read_back_v: float | None, sent_v: tuple[float, ...],
                  safe_voltage_v: float, *, tolerance_v: float = READ_BACK_TOLERANCE_V,
                  sent_here: bool = True, power_up_v: float | None = None) -> StartPoint:
    """Where a move may start from, believing nothing a device cannot prove.

    ``read_back_v``: what the device says its output holds (None: it cannot say). ``sent_v``: the
    voltages last written to this device that it may hold (the last one confirmed and the last one tried;
    empty when nothing is known to have been written). ``sent_here``: they were written by this process,
    which has been the device's only writer since; else they come from the durable record of an earlier
    run (someone may have written since). ``power_up_v``: the prover's rule for a first start with nothing
    written (what the output holds after power-up; nan: nothing is believed); None: the procedures' rule,
    which believes a read-back inside the limits.

    A read-back is believed when it is finite, inside the limits and agrees (within ``tolerance_v``) with
    one of ``sent_v``, or, with nothing written, with ``power_up_v``. One that is not: in this process the
    move starts from the last value written (the device received nothing else since, so ramping from it
    keeps the slew on the device, whatever it claims); from a record or on a first start it is
    ``unproven``. With no read-back: the last voltage written, else a finite ``safe_voltage_v`` (where a
    clean stop leaves the stage), else unknown.
    """
    if read_back_v is None:
        if sent_v and math.isfinite(sent_v[-1]):
            return StartPoint(sent_v[-1], "last written")
        if math.isfinite(safe_voltage_v):
            return StartPoint(safe_voltage_v, "safe_voltage_v")
        return StartPoint(None, "unknown")
    if not math.isfinite(read_back_v):
        problem = f"read back {read_back_v} V, not a number"
    elif not within_limits(limits, read_back_v):
        problem = f"read back {read_back_v:.4f} V, outside [{limits.v_min:g}, {limits.v_max:g}] V"
    elif sent_v:
        if any(abs(read_back_v - v) <= tolerance_v for v in sent_v):
            return StartPoint(read_back_v, "read back")
        problem = (f"read back {read_back_v:.4f} V, but {sent_v[-1]:.4f} V was "
                   + ("sent last" if sent_here else "the last value written (state file)"))
    elif power_up_v is None:
        return StartPoint(read_back_v, "read back")
    elif abs(read_back_v - power_up_v) <= tolerance_v:
        return StartPoint(read_back_v, "power-up value")
    else:
        problem = (f"read back {read_back_v:.4f} V on a first start (no value written is on record), not the "
                   f"power-up value {power_up_v:g} V")
    if sent_v and sent_here and math.isfinite(sent_v[-1]):
        return StartPoint(sent_v[-1], "last written", problem)
    if power_up_v is not None:
        claimed = read_back_v if math.isfinite(read_back_v) and within_limits(limits, read_back_v) else None
        return StartPoint(None, "unproven", problem, claimed)
    return StartPoint(None, "unknown", problem)


def position_disagreement(limits: MotionLimits, read_back_v: float, measured_um: float,
                          tolerance_um: float) -> str | None:
    """Why a position sensor's reading does not prove ``read_back_v`` (None: it does).

    The voltage implies the command ``q = (V - offset_v) / volts_per_um``; the stage holding it sits where the
    model's correction (thermal terms, nonlinearity, bias: ``q - x``) and the sensor's own uncertainty allow,
    which the operator states as ``tolerance_um``. Nothing is believed with no finite, positive tolerance."""
    implied_um = q_um_for(limits, read_back_v)
    gap_um = abs(measured_um - implied_um)
    if math.isfinite(gap_um) and gap_um <= tolerance_um:
        return None
    return (f"read back {read_back_v:.4f} V means q {implied_um:.3f} µm, but the position sensor measures "
            f"{measured_um:.3f} µm ({gap_um:.3f} µm apart; position_proof_tolerance_um = {tolerance_um:g} µm)")


class Slew:
    """The next voltage of a move under ``max_slew_um_per_s``, stepping on elapsed time.

    ``next_voltage`` is asked just before each write with the time it is asked at (any monotonic
    seconds); ``wrote`` is told once that write returned, with the time it returned. A step covers the
    time since the previous write returned, not since it began: the device had the previous value by
    then and gets the next one after this step is asked for, so however late the loop or the device,
    between any two values a device receives it never moves faster than the rate (a stamp taken before
    the write let a loop late by 4 ms put 56 um in 24 ms on a 2000 um/s device). A move from rest covers
    one :meth:`pause_s` in its first step (:data:`RAMP_PERIOD_S` on a device never written), or less when
    the device's last write (of any move: one a stop or a reload cut short) returned less than that ago.
    """

    def __init__(self) -> None:
        self._last_step_s: float | None = None  # when the previous sub-command of a ramp returned
        self._last_write_s: float | None = None  # when the last sub-command of any move returned
        self._write_took_s = 0.0  # how long the device took to take the last sub-command
        self._cut_short = False  # the last sub-command did not return: it may reach the device later still

    def pause_s(self) -> float:
        """How long a ramp waits between two sub-commands: :data:`RAMP_PERIOD_S`, or :data:`LATENCY_PAUSES`
        times the device's last write when that is longer, so the time a step may cover (the pause) is most of
        each cycle (pause + write) on a slow device too: >= 90 % of the rate, in fewer, larger steps."""
        return max(RAMP_PERIOD_S, LATENCY_PAUSES * self._write_took_s)

    def wait_s(self, limits: MotionLimits, at_v: float | None, goal_v: float) -> float:
        """How long a ramp at ``at_v`` waits before its next step: one :meth:`pause_s`, or only the time the rest
        of the way takes at the rate (the last step of a slow device's ramp does not wait a whole pause), and
        never less than :data:`RAMP_PERIOD_S`."""
        left_s = math.inf if at_v is None else ramp_seconds(limits, at_v, goal_v)
        return max(RAMP_PERIOD_S, min(self.pause_s(), left_s))

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
        if since is None:  # from rest: one pause (a ramp period, longer on a slow device), never more time than
            last = self._last_write_s  # passed since this device's last write
            interval_s = RAMP_PERIOD_S if last is None else min(max(now_s - last, 0.0), self.pause_s())
        else:  # a stalled loop resumes at the rate: no step covers more than a few of this device's pauses
            interval_s = min(max(now_s - since, 0.0), max(MAX_STEP_INTERVAL_S, 2.0 * self.pause_s()))
        max_step_v = slew * abs(limits.volts_per_um) * interval_s
        delta = goal_v - at_v
        if abs(delta) <= max_step_v:
            return goal_v
        return at_v + math.copysign(max_step_v, delta)

    def cut_short(self, at_s: float) -> None:
        """A write that did not return (cancelled by a reload or a stop, or failed) may still have reached the
        device: the next step counts from ``at_s`` as if it had returned then (its duration says nothing)."""
        if self._last_step_s is not None:
            self._last_step_s = at_s
        self._last_write_s = at_s
        self._cut_short = True

    def reopened(self, at_s: float) -> None:
        """The device was opened again (a reload, a reopen after a fault) and read back at ``at_s``: a write cut
        short on the old connection may have reached the device as late as that (its bytes were on their way when
        it was cut: a reload's first step 0.3 ms later than the cut crossed 15 V/s), so it counts from ``at_s``."""
        if self._cut_short:
            self._last_write_s = at_s

    def wrote(self, returned_s: float, reached_goal: bool, took_s: float = 0.0) -> None:
        """A sub-command's write returned at ``returned_s`` after ``took_s``; ``reached_goal``: it was the goal."""
        self._last_step_s = None if reached_goal else returned_s
        self._last_write_s = returned_s
        self._write_took_s = max(took_s, 0.0)
        self._cut_short = False


def ramp_seconds(limits: MotionLimits, from_v: float, to_v: float) -> float:
    """How long a ramp takes at the slew limit (0 when it is off)."""
    slew = limits.max_slew_um_per_s
    if slew <= 0:
        return 0.0
    return abs(to_v - from_v) / (slew * abs(limits.volts_per_um))
