"""The stage gets the latest command: coalesced, ramped when the jump is large, never on the answer's path.

Answers hand their command over with :meth:`Actuation.offer` from Zenoh's threads; the writes run
on the asyncio loop. A target asks for a wake of the loop only when the loop is idle: while a write
is under way, newer commands just replace the pending one, and the loop takes the newest as soon as
the write returns (no pause: a target arriving in a stream waits for at most the write in progress).

- **Latest wins, in order**: the device gets every served command in order unless a newer one
  supersedes it before the write.
- **Where the stage is** (:func:`locate_stage`, the one rule the procedures use too): the output read
  back at open when the device can say (``Actuator.read_back``: Modbus with ``verify``, a serial
  controller with a readback query), else the last voltage written to *this* device (an edit that
  switches to another device forgets it), else a finite ``safe_voltage_v`` (where a clean stop left
  the stage), else unknown.
- **Slew** (``[actuator] max_slew_um_per_s > 0``): a larger jump is written as sub-commands every
  ``RAMP_PERIOD_S``, each no further from the last write than the limit allows for the time since
  that write *returned* (so even the device's own timestamps never see a faster move), ending at
  the target; the first move after a start is ramped from where the stage is. A newer command during
  a ramp re-plans from where the stage is. When that is unknown the first move is written as is,
  and ``actuator_unramped`` says so (once).
- **Faults**: a failed open, read back or write (``DeviceError``, any error, a timeout) or readback
  mismatch puts the actuator in ``fault`` with the reason; it is closed and reopened with backoff and
  the latest command written again. Meanwhile ``fault_reason`` is set and targets are refused
  (``actuator_fault``, ``daemon.service.targets``). One ``actuator_failed`` line per episode,
  ``actuator_recovered`` when a write succeeds again; when nothing was ever commanded (the open at
  start failed) there is nothing to write, and a reopen that succeeds (with its read back, where the
  device has one) ends the fault: refusing targets until a write succeeds would refuse for ever,
  since only a served target gives the stage a command.
- **Shutdown**: :meth:`Actuation.stop` with ``final=True`` writes a finite ``safe_voltage_v``
  (checked against the limits, ramped like any command) before closing.
"""

from __future__ import annotations

import asyncio
import math
import random
import threading
import time
from dataclasses import dataclass
from typing import Any

from daemon.config import SAFE_RAMP_BUDGET_S, ActuatorConfig
from daemon.logs import RateLimitedLog
from drivers.base import Actuator, DeviceError

RAMP_PERIOD_S = 0.02  # a ramp's sub-commands are this far apart (at least)
WRITE_PERIOD_S = RAMP_PERIOD_S  # and so are any two writes: an output needs no more than 50 updates a second
WRITE_TIMEOUT_S = 3.0  # a write that takes longer is a fault
#: shutdown gives up on reaching safe_voltage_v after this long: its share of the unit's stop timeout
SAFE_TIMEOUT_S = SAFE_RAMP_BUDGET_S
INITIAL_BACKOFF_S = 0.2
MAX_BACKOFF_S = 5.0


def ramp_step(at_q_um: float, target_q_um: float, max_step_um: float) -> float:
    """The next sub-command from ``at_q_um`` towards ``target_q_um``: the target itself when it is
    within ``max_step_um``, else ``max_step_um`` closer."""
    delta = target_q_um - at_q_um
    if abs(delta) <= max_step_um:
        return target_q_um
    return at_q_um + math.copysign(max_step_um, delta)


def plan_ramp(start_q_um: float, target_q_um: float, max_slew_um_per_s: float,
              period_s: float = RAMP_PERIOD_S) -> list[float]:
    """Every sub-command from ``start_q_um`` to ``target_q_um`` (inclusive of the target, not of the
    start) at one per ``period_s``; one element when the limit is off or the jump is small."""
    if max_slew_um_per_s <= 0:
        return [target_q_um]
    step = max_slew_um_per_s * period_s
    out = [ramp_step(start_q_um, target_q_um, step)]
    while out[-1] != target_q_um:
        out.append(ramp_step(out[-1], target_q_um, step))
    return out


@dataclass(frozen=True, slots=True)
class StageStart:
    """Where the stage is before the first move (``voltage_v`` None: unknown) and how that is known."""

    voltage_v: float | None
    known_from: str  # "read back" | "last written" | "safe_voltage_v" | "unknown"


async def locate_stage(actuator: Actuator, config: ActuatorConfig, last_voltage_v: float | None) -> StageStart:
    """The one rule for where the stage is after ``actuator.open()``: the output read back when the
    device can say; else ``last_voltage_v`` (the last voltage written to this device, when known);
    else a finite ``safe_voltage_v``; else unknown. A failed read back raises, like a failed write."""
    read = await actuator.read_back()
    if read is not None:
        field, value = read
        voltage = value if field == "voltage_v" else config.voltage(value)
        if math.isfinite(voltage):
            return StageStart(voltage, "read back")
    if last_voltage_v is not None and math.isfinite(last_voltage_v):
        return StageStart(last_voltage_v, "last written")
    if math.isfinite(config.safe_voltage_v):
        return StageStart(config.safe_voltage_v, "safe_voltage_v")
    return StageStart(None, "unknown")


@dataclass(frozen=True, slots=True)
class Goal:
    """A command the stage should hold."""

    q_um: float
    voltage_v: float
    x_um: float | None = None


class Actuation:
    """The pending command (latest wins), the task that gives it to the drivers' actuator, its state."""

    def __init__(self, log: Any) -> None:
        self.log = log
        self.failures = RateLimitedLog(log, "actuator_failed", level="error")
        self._lock = threading.Lock()  # guards the three below; never held across an await or a publish
        self._active = False
        self._pending: Goal | None = None  # not yet given to the stage
        self._wake_pending = False
        self._event = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._actuator: Actuator | None = None
        self._config: ActuatorConfig | None = None
        self._goal: Goal | None = None  # the latest command taken; rewritten after a fault
        #: set while in fault (read without a lock on Zenoh's threads: one attribute, atomic)
        self.fault_reason: str | None = None
        self._fault_since = 0.0
        self._episode_failures = 0
        # what status shows (kept across a restart on the same device: the stage keeps its voltage)
        self.last_voltage_v: float | None = None
        self.last_write_t: float | None = None
        self.writes = 0
        self.write_failures = 0
        self._device: str | None = None  # the description of the device last_voltage_v was written to
        self._at_v: float | None = None  # where the stage is (the ramps start there); None: unknown
        self._unramped_told = False  # actuator_unramped is said once per start
        self._last_end = 0.0  # time.monotonic() when the last write returned

    # --- the target path (any thread) -----------------------------------------------------------

    def offer(self, q_um: float, voltage_v: float, x_um: float | None = None) -> bool:
        """Make this the command the stage gets next (any thread). True: the caller must wake the loop
        (``loop.call_soon_threadsafe(actuation.wake)``); it is asked at most once per burst."""
        with self._lock:
            if not self._active:
                return False
            self._pending = Goal(q_um, voltage_v, x_um)
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
        """Open ``actuator``, find where the stage is, and start writing to it; a failure to open (or to
        read the output back) is a fault (reopened with backoff)."""
        self._actuator, self._config = actuator, config
        self.fault_reason, self._goal = None, None
        if actuator.description != self._device:  # another device: what the old one was given says nothing
            self._device = actuator.description
            self.last_voltage_v = self.last_write_t = None
        self._at_v, self._unramped_told = None, False
        actuator.limits_v = (config.v_min, config.v_max)
        try:
            start = await self._open(actuator, config, self.last_voltage_v)
            self.log.info("actuator_open", device=actuator.description, voltage_v=start.voltage_v,
                          known_from=start.known_from)
        except Exception as error:
            self._enter_fault(actuator, f"open failed: {_reason(error)}")
        with self._lock:
            self._active, self._wake_pending, self._pending = True, False, None
        self._task = asyncio.create_task(self._drive(actuator), name="actuator")

    async def stop(self, *, final: bool = False) -> None:
        """Stop writing and close the actuator (a failure to close is logged). ``final`` (the daemon
        stops): first put a finite ``safe_voltage_v`` on the stage."""
        with self._lock:
            self._active = False
        if self._task is not None:
            self._task.cancel()
            try:
                await self._task
            except asyncio.CancelledError:
                pass
            self._task = None
        actuator, self._actuator = self._actuator, None
        if actuator is None:
            return
        fault, self.fault_reason = self.fault_reason, None  # a stopped actuator refuses nothing (reload to zenoh)
        if final and self._config is not None:
            await self._write_safe(actuator, self._config, reopen=fault is not None)
        try:
            await actuator.close()
        except Exception as error:
            self.log.warning("actuator_close_failed", error=str(error))

    async def _write_safe(self, actuator: Actuator, config: ActuatorConfig, *, reopen: bool) -> None:
        safe_v, safe_q = config.safe_voltage_v, config.safe_q_um
        if safe_q is None:
            return  # nan: leave the stage where it is
        if not config.within_limits(safe_v):  # the config refuses this; never write it anyway
            self.log.error("actuator_safe_refused", voltage_v=safe_v, v_min=config.v_min, v_max=config.v_max)
            return
        try:
            async with asyncio.timeout(SAFE_TIMEOUT_S):
                if reopen:  # closed after its fault
                    await self._open(actuator, config, self._at_v)
                await self._move_to(actuator, config, Goal(safe_q, safe_v), follow_pending=False)
        except Exception as error:
            self.log.error("actuator_safe_failed", voltage_v=safe_v, error=_reason(error))
            return
        self.log.info("actuator_safe", voltage_v=safe_v, device=actuator.description)

    # --- writing --------------------------------------------------------------------------------

    def _take_pending(self) -> Goal | None:
        with self._lock:
            pending, self._pending = self._pending, None
            if pending is None:
                self._wake_pending = False
            return pending

    async def _drive(self, actuator: Actuator) -> None:
        assert self._config is not None
        config = self._config
        backoff = INITIAL_BACKOFF_S
        while True:
            if self.fault_reason is not None:
                await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
                backoff = min(backoff * 2.0, MAX_BACKOFF_S)
                try:
                    await self._open(actuator, config, self._at_v)
                except asyncio.CancelledError:
                    raise
                except Exception as error:
                    self._still_failing(actuator, f"reopen failed: {_reason(error)}")
                    await self._close_quietly(actuator)
                    continue
                pending = self._take_pending()
                goal = pending or self._goal
                if goal is None:  # nothing was ever commanded: the device opens (and reads back) again
                    self._recovered(actuator)
                    continue
            else:
                pending = self._take_pending()
                if pending is None:
                    await self._event.wait()
                    self._event.clear()
                    continue
                goal = pending
            self._goal = goal
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
        slew = config.max_slew_um_per_s
        while True:
            if follow_pending:
                newer = self._take_pending()
                if newer is not None:
                    goal = self._goal = newer
            at_v = self._at_v
            if slew <= 0 or at_v is None:
                if slew > 0 and not self._unramped_told:
                    self._unramped_told = True
                    self.log.warning("actuator_unramped", device=actuator.description, voltage_v=goal.voltage_v,
                                     reason="where the stage is is unknown (the device cannot be read back, nothing "
                                     "was written to it yet, safe_voltage_v = nan): the first move is not ramped")
                await self._write(actuator, goal.q_um, goal.voltage_v, goal.x_um)
                return
            at_q = config.q_um_for(at_v)
            elapsed = min(time.monotonic() - self._last_end, RAMP_PERIOD_S)
            next_q = ramp_step(at_q, goal.q_um, slew * elapsed)
            if next_q == goal.q_um:
                await self._write(actuator, goal.q_um, goal.voltage_v, goal.x_um)
                return
            voltage = config.voltage(next_q)
            if not config.within_limits(voltage):  # rounding at a limit, or limits narrowed by a reload
                voltage = min(max(voltage, config.v_min), config.v_max)
                next_q = config.q_um_for(voltage)
            await self._write(actuator, next_q, voltage, goal.x_um)
            await asyncio.sleep(RAMP_PERIOD_S)

    async def _open(self, actuator: Actuator, config: ActuatorConfig, last_voltage_v: float | None) -> StageStart:
        """Open the device and learn where the stage is (:func:`locate_stage`); raises like a write."""
        await self._guarded(actuator.open(), "open")
        start = await self._guarded(locate_stage(actuator, config, last_voltage_v), "read back")
        self._at_v = start.voltage_v
        return start

    async def _write(self, actuator: Actuator, q_um: float, voltage_v: float, x_um: float | None) -> None:
        await self._guarded(actuator.command(q_um, voltage_v, x_um=x_um), "write")
        self._last_end = time.monotonic()
        self._at_v = voltage_v
        self.last_voltage_v, self.last_write_t = voltage_v, time.time()
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
