"""The stage gets the latest command: coalesced, ramped when the jump is large, never on the answer's path.

Answers hand their command over with :meth:`Actuation.offer` from Zenoh's threads; the writes run
on the asyncio loop. A target asks for a wake of the loop only when the loop is idle: while a write
is under way, newer commands just replace the pending one, and the loop takes the newest as soon as
the write returns. Motion itself (where a move starts, the slew, the limits of what is sent) is
:mod:`nanodrift.motion`'s, the one owner the procedures use too; this module owns the device's lifecycle.

- **The goal** is the latest served command. It survives a reload that touches ``[actuator]``, a
  device reopened after a fault, and a target answered while the drivers were being swapped: once
  the (new) output is open, the goal is written to it (ramped from where the stage is). A goal the
  new limits forbid is dropped (``actuator_goal_dropped``) and the stage holds where it is.
- **Where the stage is** (:func:`nanodrift.motion.trusted_start`): a read-back is believed only inside
  ``[v_min, v_max]`` and, once something was sent to this device, when it agrees with what was sent;
  else it is unknown (``actuator_readback_untrusted``), never a start point. Unknown: the next
  command is written as it is (``actuator_unramped`` says so, once).
- **Slew** (``max_slew_um_per_s > 0``): sub-commands every ``RAMP_PERIOD_S``, each covering the time
  since the previous one began, so a ramp takes distance / rate whatever the device's latency.
- **What is sent** is checked: the voltage the device will receive (``Actuator.sent_voltage``: a DAC's
  count, a controller's digits) must be inside the limits in force, or nothing is written.
- **Faults**: a failed open, read back or write (``DeviceError``, any error, a timeout) or readback
  mismatch puts the actuator in ``fault`` with the reason; it is closed and reopened with backoff and
  the goal written again. Meanwhile targets are refused (``actuator_fault``). One ``actuator_failed``
  line per episode, ``actuator_recovered`` when the device works again (a write, a reopen with nothing
  to write, or a reload onto a device that opens).
- **Shutdown**: :meth:`Actuation.stop` with ``final=True`` ramps to a finite ``safe_voltage_v`` within
  ``SAFE_RAMP_BUDGET_S`` (the unit's stop timeout less a margin), retrying a transient failure, and
  runs in a ``finally``: an exception on the way out never skips it.

One module of ~410 lines on purpose: it is one object, :class:`Actuation`, whose goal, fault and
reopen cycle and shutdown ramp share one state (the goal, what was sent, the device open now) driven
by one task on the loop; split, each part would reach into the others' state. The motion rules it
applies are already :mod:`nanodrift.motion`'s.
"""

from __future__ import annotations

import asyncio
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from nanodrift.config import SAFE_RAMP_BUDGET_S, ActuatorConfig
from nanodrift.drivers.base import Actuator, DeviceError
from nanodrift.logs import RateLimitedLog
from nanodrift.motion import RAMP_PERIOD_S, Slew, StartPoint, trusted_start

WRITE_PERIOD_S = RAMP_PERIOD_S  # any two writes are this far apart: a stream is coalesced to 50 writes a second
WRITE_TIMEOUT_S = 3.0  # a write that takes longer is a fault
INITIAL_BACKOFF_S = 0.2
MAX_BACKOFF_S = 5.0
#: tolerance on a sent voltage against the limits: float rounding of a count times a scale, not a volt more
SENT_SLACK_V = 1e-9


async def locate_stage(actuator: Actuator, config: ActuatorConfig, sent_v: tuple[float, ...] = ()) -> StartPoint:
    """Where the stage is after ``actuator.open()`` (:func:`nanodrift.motion.trusted_start` on its read-back);
    a failed read back raises, like a failed write. The procedures use it too."""
    read = await actuator.read_back()
    read_v = None
    if read is not None:
        field, value = read
        read_v = value if field == "voltage_v" else config.voltage(value)
    return trusted_start(config, read_v, sent_v, config.safe_voltage_v)


def checked_sent_voltage(actuator: Actuator, config: ActuatorConfig, voltage_v: float) -> float:
    """The voltage the device will receive for ``voltage_v``; ValueError (write nothing) when that is
    outside the limits in force."""
    sent = actuator.sent_voltage(voltage_v)
    if not config.v_min - SENT_SLACK_V <= sent <= config.v_max + SENT_SLACK_V:
        raise ValueError(f"{actuator.description}: {voltage_v:.6f} V would be sent as {sent:.6f} V, outside "
                         f"[{config.v_min:g}, {config.v_max:g}] V: nothing written")
    return sent


@dataclass(frozen=True, slots=True)
class Goal:
    """A served command the stage should hold."""

    q_um: float
    voltage_v: float
    x_um: float | None = None


#: told (on the loop) when the stage reached a goal: the goal and the monotonic time it was sent
OnReached = Callable[[Goal, float], None]


class Actuation:
    """The goal (latest wins), the task that gives it to the drivers' actuator, and its state."""

    def __init__(self, log: Any, *, safe_budget_s: float = SAFE_RAMP_BUDGET_S) -> None:
        self.log = log
        self.failures = RateLimitedLog(log, "actuator_failed", level="error")
        self.safe_budget_s = safe_budget_s
        self._lock = threading.Lock()  # guards the three below; never held across an await or a publish
        self._active = False
        self._pending: Goal | None = None  # served, not yet taken by the loop (kept while drivers are swapped)
        self._wake_pending = False
        self._event = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._actuator: Actuator | None = None
        self._config: ActuatorConfig | None = None
        self._goal: Goal | None = None  # the latest command taken: survives reloads and reopens
        self._goal_on_device = True  # the goal was written in full to the device that is open now
        self.reached_listeners: list[OnReached] = []
        #: set while in fault (read without a lock on Zenoh's threads: one attribute, atomic)
        self.fault_reason: str | None = None
        self._fault_since = 0.0
        self._episode_failures = 0
        self._stashed_episode: tuple[float, int] | None = None  # a fault a reload stopped, until a device opens
        # what status shows (kept across a restart on the same device: the stage keeps its voltage)
        self.last_voltage_v: float | None = None
        self.last_write_t: float | None = None  # unix time: a label for people
        self.writes = 0
        self.write_failures = 0
        self._device: str | None = None  # the description of the device the voltages below were sent to
        self._tried_v: float | None = None  # the last voltage sent to it, confirmed or not
        self._at_v: float | None = None  # where the stage is (the ramps start there); None: unknown
        self._slew = Slew()
        self._unramped_told = False  # actuator_unramped is said once per start

    # --- the target path (any thread) -----------------------------------------------------------

    def offer(self, q_um: float, voltage_v: float, x_um: float | None = None) -> bool:
        """Make this the command the stage gets next (any thread). True: the caller must wake the loop
        (``loop.call_soon_threadsafe(actuation.wake)``); it is asked at most once per burst. While the
        drivers are being swapped (a reload) the command waits for the new output."""
        with self._lock:
            self._pending = Goal(q_um, voltage_v, x_um)
            if not self._active:
                return False
            wake = not self._wake_pending
            self._wake_pending = True
            return wake

    def wake(self) -> None:
        self._event.set()

    def doc(self) -> dict[str, Any]:
        """The actuator's state for ``status`` (a device is driven: ``started`` was called)."""
        actuator = self._actuator
        return {
            "state": "fault" if self.fault_reason is not None else ("ok" if actuator is not None else "closed"),
            "reason": self.fault_reason,
            "device": actuator.description if actuator is not None else None,
            "last_voltage_v": self.last_voltage_v,
            "last_write_t": self.last_write_t,
            "writes": self.writes,
            "failures": self.write_failures,
        }

    # --- lifecycle (the loop) -------------------------------------------------------------------

    async def start(self, actuator: Actuator, config: ActuatorConfig) -> None:
        """Open ``actuator``, find where the stage is, and start writing the goal and what follows; a
        failure to open (or to read the output back) is a fault (reopened with backoff)."""
        self._actuator, self._config = actuator, config
        self.fault_reason = None
        if actuator.description != self._device:  # another device: what the old one was sent says nothing
            self._device = actuator.description
            self.last_voltage_v = self.last_write_t = self._tried_v = None
        self._at_v, self._unramped_told = None, False
        self._slew.rest()
        self._goal_on_device = self._goal is None
        actuator.limits_v = (config.v_min, config.v_max)
        try:
            start = await self._open(actuator, config)
            self.log.info("actuator_open", device=actuator.description, voltage_v=start.voltage_v,
                          known_from=start.known_from)
            if self._stashed_episode is not None:
                since, failures = self._stashed_episode
                self.log.info("actuator_recovered", device=actuator.description, via="reload",
                              after_s=round(time.monotonic() - since, 3), failures=failures)
        except Exception as error:
            if self._stashed_episode is not None:
                self._fault_since, self._episode_failures = self._stashed_episode
                self._still_failing(actuator, f"open failed: {_reason(error)}")
            else:
                self._enter_fault(actuator, f"open failed: {_reason(error)}")
        self._stashed_episode = None
        with self._lock:
            self._active, self._wake_pending = True, False
        self._task = asyncio.create_task(self._drive(actuator), name="actuator")

    async def stop(self, *, final: bool = False) -> None:
        """Stop writing and close the actuator (a failure to close is logged). ``final`` (the daemon
        stops): first ramp to a finite ``safe_voltage_v``, whatever happened before."""
        with self._lock:
            self._active = False
        actuator, self._actuator = self._actuator, None
        fault, self.fault_reason = self.fault_reason, None  # a stopped actuator refuses nothing (reload to zenoh)
        try:
            task, self._task = self._task, None
            while task is not None and not task.done():
                # cancelled again until it ends: a driver that swallows one cancellation (3.11's wait_for can)
                # must not hang a reload or the stop, and with it the safe ramp
                task.cancel()
                await asyncio.wait({task}, timeout=1.0)
            error = task.exception() if task is not None and not task.cancelled() else None
            if error is not None:  # the drive loop catches its own; this is a bug, not a reason to skip the safe ramp
                self.log.error("actuator_task_failed", error=_reason(error))
        finally:
            if actuator is not None:
                if fault is not None and not final:
                    self._stashed_episode = (self._fault_since, self._episode_failures)
                try:
                    if final and self._config is not None:
                        await self._write_safe(actuator, self._config, reopen=fault is not None or self._at_v is None)
                finally:
                    try:
                        await actuator.close()
                    except Exception as error:
                        self.log.warning("actuator_close_failed", error=str(error))

    async def _write_safe(self, actuator: Actuator, config: ActuatorConfig, *, reopen: bool) -> None:
        """Ramp to ``safe_voltage_v`` within the budget, reopening and retrying after a transient failure."""
        safe_v, safe_q = config.safe_voltage_v, config.safe_q_um
        if safe_q is None:
            return  # nan: leave the stage where it is
        if not config.within_limits(safe_v):  # the config refuses this; never write it anyway
            self.log.error("actuator_safe_refused", voltage_v=safe_v, v_min=config.v_min, v_max=config.v_max)
            return
        goal = Goal(safe_q, safe_v)
        deadline = time.monotonic() + self.safe_budget_s
        attempts, error_text = 0, ""
        while True:
            attempts += 1
            try:
                async with asyncio.timeout(max(0.0, deadline - time.monotonic())):
                    if reopen:
                        await self._close_quietly(actuator)
                        await self._open(actuator, config)
                    await self._move_to(actuator, config, goal, follow_pending=False)
                self.log.info("actuator_safe", voltage_v=safe_v, device=actuator.description, attempts=attempts)
                return
            except TimeoutError:
                error_text = f"not reached within {self.safe_budget_s:g} s" + (f" ({error_text})" if error_text else "")
                break
            except Exception as error:
                error_text = _reason(error)
                reopen = True
                remaining = deadline - time.monotonic()
                if remaining <= INITIAL_BACKOFF_S:
                    break
                await asyncio.sleep(min(INITIAL_BACKOFF_S * attempts, remaining / 2))
        self.log.error("actuator_safe_failed", voltage_v=safe_v, error=error_text, attempts=attempts,
                       last_voltage_v=self.last_voltage_v)

    # --- writing --------------------------------------------------------------------------------

    def _take_pending(self) -> Goal | None:
        with self._lock:
            pending, self._pending = self._pending, None
            if pending is None:
                self._wake_pending = False
            return pending

    def _next_goal(self) -> Goal | None:
        """A newer served command, else the goal when this device does not hold it yet."""
        pending = self._take_pending()
        if pending is not None:
            return pending
        return self._goal if not self._goal_on_device else None

    async def _drive(self, actuator: Actuator) -> None:
        assert self._config is not None
        config = self._config
        backoff = INITIAL_BACKOFF_S
        while True:
            if self.fault_reason is not None:
                await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
                backoff = min(backoff * 2.0, MAX_BACKOFF_S)
                try:
                    await self._open(actuator, config)
                except asyncio.CancelledError:
                    raise
                except Exception as error:
                    self._still_failing(actuator, f"reopen failed: {_reason(error)}")
                    await self._close_quietly(actuator)
                    continue
                goal = self._next_goal()
                if goal is None:  # nothing to write: the device opens (and reads back) again
                    self._recovered(actuator)
                    continue
            else:
                goal = self._next_goal()
                if goal is None:
                    await self._event.wait()
                    self._event.clear()
                    continue
            # not on the device until a write of it is confirmed: a write that fails leaves it to be
            # written again once the device works again (the chaos suite found it lost otherwise)
            self._goal, self._goal_on_device = goal, False
            try:
                await self._move_to(actuator, config, goal, follow_pending=True)
            except asyncio.CancelledError:
                raise
            except Exception as error:
                reason = _reason(error)
                if self.fault_reason is None:
                    self._enter_fault(actuator, reason)
                else:
                    self._still_failing(actuator, reason)
                await self._close_quietly(actuator)
                continue
            if self.fault_reason is not None:
                self._recovered(actuator)
            backoff = INITIAL_BACKOFF_S
            # Writes are paced at the ramp period: an isolated target is written at once, a stream is
            # coalesced to 50 writes/s (newest wins). Waking the loop for every target of a 1 kHz stream
            # halved the daemon's burst throughput and raised its answer latency (benchmarks/daemon_latency.py).
            await asyncio.sleep(WRITE_PERIOD_S)

    async def _move_to(self, actuator: Actuator, config: ActuatorConfig, goal: Goal, *,
                       follow_pending: bool) -> None:
        """Write ``goal`` (ramped under the slew limit); with ``follow_pending`` a newer command taken
        during the ramp becomes the goal (re-planned from where the stage is)."""
        while True:
            if follow_pending:
                newer = self._take_pending()
                if newer is not None:
                    goal = self._goal = newer
            if not config.within_limits(goal.voltage_v):  # a reload narrowed the limits under it
                self.log.warning("actuator_goal_dropped", device=actuator.description, voltage_v=goal.voltage_v,
                                 v_min=config.v_min, v_max=config.v_max, held_v=self._at_v,
                                 reason="the served command is outside the limits now in force: the stage holds")
                self._goal, self._goal_on_device = None, True
                return
            if self._at_v is None and config.max_slew_um_per_s > 0 and not self._unramped_told:
                self._unramped_told = True
                self.log.warning("actuator_unramped", device=actuator.description, voltage_v=goal.voltage_v,
                                 reason="where the stage is is unknown (no trusted read-back, nothing sent to it "
                                 "yet, safe_voltage_v = nan): this move is not ramped")
            began_s = time.monotonic()
            voltage = self._slew.next_voltage(config, self._at_v, goal.voltage_v, began_s)
            reached = voltage == goal.voltage_v
            if not reached:  # mid-ramp from a stage outside limits a reload narrowed: never send outside
                voltage = min(max(voltage, config.v_min), config.v_max)
            q_um = goal.q_um if reached else config.q_um_for(voltage)
            await self._write(actuator, config, q_um, voltage, goal.x_um)
            self._slew.wrote(began_s, reached)
            if reached:
                self._goal_on_device = True
                for listener in self.reached_listeners:
                    listener(goal, time.monotonic())
                return
            await asyncio.sleep(RAMP_PERIOD_S)

    async def _open(self, actuator: Actuator, config: ActuatorConfig) -> StartPoint:
        """Open the device and learn where the stage is (:func:`locate_stage`); raises like a write."""
        self._slew.rest()
        await self._guarded(actuator.open(), "open")
        sent = tuple(v for v in (self.last_voltage_v, self._tried_v) if v is not None)
        start = await self._guarded(locate_stage(actuator, config, sent), "read back")
        if start.distrust is not None:
            self.log.warning("actuator_readback_untrusted", device=actuator.description, reason=start.distrust,
                             note="where the stage is is unknown: nothing is ramped from it; the next command "
                             "is written as it is")
        self._at_v = start.voltage_v
        return start

    async def _write(self, actuator: Actuator, config: ActuatorConfig, q_um: float, voltage_v: float,
                     x_um: float | None) -> None:
        sent_v = checked_sent_voltage(actuator, config, voltage_v)
        self._tried_v = sent_v
        self._at_v = None  # until the device confirms it, the stage is between the two
        await self._guarded(actuator.command(q_um, voltage_v, x_um=x_um), "write")
        self._at_v = sent_v
        self.last_voltage_v, self.last_write_t = sent_v, time.time()
        self.writes += 1

    async def _close_quietly(self, actuator: Actuator) -> None:
        """Close a failed device before reopening it (a failure to close is only logged)."""
        try:
            await self._guarded(actuator.close(), "close")
        except asyncio.CancelledError:
            raise
        except Exception as error:
            self.log.warning("actuator_close_failed", error=_reason(error))

    @staticmethod
    async def _guarded(step: Any, what: str) -> Any:
        # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancellation
        try:
            async with asyncio.timeout(WRITE_TIMEOUT_S):
                return await step
        except TimeoutError:
            raise DeviceError(f"actuator {what} timed out after {WRITE_TIMEOUT_S:g} s") from None

    # --- state changes --------------------------------------------------------------------------

    def _enter_fault(self, actuator: Actuator, reason: str) -> None:
        self.write_failures += 1
        self.fault_reason = reason
        self._fault_since = time.monotonic()
        self._episode_failures = 1
        self.failures(device=actuator.description, error=reason)

    def _still_failing(self, actuator: Actuator, reason: str) -> None:
        self.write_failures += 1
        self._episode_failures += 1
        self.fault_reason = reason

    def _recovered(self, actuator: Actuator) -> None:
        self.log.info("actuator_recovered", device=actuator.description,
                      after_s=round(time.monotonic() - self._fault_since, 3), failures=self._episode_failures)
        self.fault_reason = None
        self._episode_failures = 0


def _reason(error: BaseException) -> str:
    return str(error) if isinstance(error, DeviceError) else f"{type(error).__name__}: {error}"
