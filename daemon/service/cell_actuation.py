"""A multi-axis cell's outputs: every axis of one command written before any axis of the next.

The multi-axis twin of :mod:`nanodrift.service.actuation` (a one-axis cell keeps that module, unchanged),
with the same rules per axis, applied by one task for all axes so that commands never interleave on a
shared line (a GCS controller's port, a Modbus module's connection):

- **The goal** is the latest served command (all axes); it survives a reload and a reopen, and a goal
  the new limits forbid on any axis is dropped whole (the stage holds).
- **Each step** computes every axis' next voltage under its own ``max_slew_um_per_s`` and writes the
  axes in the cell's order; axes that reached the goal are not written again for it. A ramp ends when
  every axis holds its goal.
- **Where each axis is** (:func:`nanodrift.service.actuation.locate_stage`): its read-back checked
  against its limits and what was sent to it, else unknown (the next command is written as it is).
- **What is sent** is checked per axis (:func:`checked_sent_voltage`): inside that axis' limits, for
  every axis of a step before any axis is written, or nothing of the step is written and the cell is
  in fault.
- **Faults**: a failure on any axis puts the cell's output in fault (targets refused with
  ``actuator_fault`` naming the axis); every axis is closed and reopened with backoff and the goal
  written again.
- **Shutdown**: :meth:`CellActuation.stop` with ``final=True`` ramps every axis with a finite
  ``safe_voltage_v`` to it, together, within ``SAFE_RAMP_BUDGET_S``, retrying a transient failure.
"""

from __future__ import annotations

import asyncio
import random
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from nanodrift.config import SAFE_RAMP_BUDGET_S, ActuatorConfig
from nanodrift.drivers.base import Actuator, DeviceError
from nanodrift.logs import RateLimitedLog
from nanodrift.motion import RAMP_PERIOD_S, Slew
from nanodrift.service.actuation import (
    INITIAL_BACKOFF_S,
    MAX_BACKOFF_S,
    WRITE_PERIOD_S,
    WRITE_TIMEOUT_S,
    checked_sent_voltage,
    locate_stage,
)


@dataclass(frozen=True, slots=True)
class CellGoal:
    """A served command every axis should hold: q and voltage per axis, and the target's positions."""

    q_um: Mapping[str, float]
    voltage_v: Mapping[str, float]
    positions_um: Mapping[str, float] | None = None


@dataclass
class AxisOutput:
    """One axis' device and what is known of it."""

    axis: str
    actuator: Actuator
    config: ActuatorConfig
    slew: Slew = field(default_factory=Slew)
    at_v: float | None = None  # where the output is (ramps start there); None: unknown
    tried_v: float | None = None  # the last voltage sent, confirmed or not
    last_voltage_v: float | None = None
    last_write_t: float | None = None  # unix time: a label for people
    writes: int = 0


class AxisFault(Exception):
    """A failure on one axis: the message names it."""


class CellActuation:
    """The goal (latest wins), the task that writes it to every axis' device, and their state."""

    def __init__(self, log: Any, *, safe_budget_s: float = SAFE_RAMP_BUDGET_S) -> None:
        self.log = log
        self.failures = RateLimitedLog(log, "actuator_failed", level="error")
        self.safe_budget_s = safe_budget_s
        self._lock = threading.Lock()
        self._active = False
        self._pending: CellGoal | None = None
        self._wake_pending = False
        self._event = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._outputs: dict[str, AxisOutput] = {}
        self._goal: CellGoal | None = None
        self._goal_on_device = True
        #: set while in fault (read without a lock on Zenoh's threads)
        self.fault_reason: str | None = None
        self._fault_since = 0.0
        self.write_failures = 0
        self._known: dict[str, AxisOutput] = {}  # axis -> its last output (kept over a restart on the same device)
        #: told (on the loop) when every axis holds a served goal: the goal and the monotonic time
        self.reached_listeners: list[Callable[[CellGoal, float], None]] = []

    # --- the target path (any thread) -----------------------------------------------------------

    def offer(self, q_um: Mapping[str, float], voltage_v: Mapping[str, float],
              positions_um: Mapping[str, float] | None = None) -> bool:
        """Make this the command every axis gets next; True: the caller must wake the loop."""
        with self._lock:
            self._pending = CellGoal(q_um, voltage_v, positions_um)
            if not self._active:
                return False
            wake = not self._wake_pending
            self._wake_pending = True
            return wake

    def wake(self) -> None:
        self._event.set()

    def doc(self) -> dict[str, Any]:
        """The outputs' state for ``status``: the cell's, then per axis."""
        return {
            "state": "fault" if self.fault_reason is not None else ("ok" if self._outputs else "closed"),
            "reason": self.fault_reason,
            "failures": self.write_failures,
            "axes": {axis: {"device": out.actuator.description, "last_voltage_v": out.last_voltage_v,
                            "last_write_t": out.last_write_t, "writes": out.writes}
                     for axis, out in self._outputs.items()},
        }

    # --- lifecycle (the loop) -------------------------------------------------------------------

    async def start(self, actuators: Mapping[str, Actuator], configs: Mapping[str, ActuatorConfig]) -> None:
        """Open every axis' device, find where each axis is, and start writing the goal."""
        outputs = {}
        for axis, actuator in actuators.items():
            known = self._known.get(axis)
            out = AxisOutput(axis, actuator, configs[axis])
            if known is not None and known.actuator.description == actuator.description:
                out.last_voltage_v, out.last_write_t, out.tried_v = known.last_voltage_v, known.last_write_t, \
                    known.tried_v
                out.writes = known.writes
            actuator.limits_v = (configs[axis].v_min, configs[axis].v_max)
            outputs[axis] = out
        self._outputs = dict(outputs)
        self._known.update(outputs)
        self.fault_reason = None
        self._goal_on_device = self._goal is None
        try:
            await self._open_all()
            self.log.info("actuator_open", axes={a: o.actuator.description for a, o in outputs.items()},
                          voltage_v={a: o.at_v for a, o in outputs.items()})
        except Exception as error:
            self._enter_fault(_reason(error, "open"))
        with self._lock:
            self._active, self._wake_pending = True, False
        self._task = asyncio.create_task(self._drive(), name="cell-actuator")

    async def stop(self, *, final: bool = False) -> None:
        """Stop writing and close every axis' device; ``final``: first ramp every axis to its finite
        ``safe_voltage_v``, whatever happened before."""
        with self._lock:
            self._active = False
        outputs, self._outputs = self._outputs, {}
        fault, self.fault_reason = self.fault_reason, None
        try:
            task, self._task = self._task, None
            while task is not None and not task.done():
                task.cancel()
                await asyncio.wait({task}, timeout=1.0)
            error = task.exception() if task is not None and not task.cancelled() else None
            if error is not None:
                self.log.error("actuator_task_failed", error=repr(error))
        finally:
            try:
                if final and outputs:
                    await self._write_safe(outputs, reopen=fault is not None
                                           or any(o.at_v is None for o in outputs.values()))
            finally:
                for out in outputs.values():
                    try:
                        await out.actuator.close()
                    except Exception as error:
                        self.log.warning("actuator_close_failed", axis=out.axis, error=str(error))

    async def _write_safe(self, outputs: Mapping[str, AxisOutput], *, reopen: bool) -> None:
        safe = {a: o for a, o in outputs.items() if o.config.safe_q_um is not None}
        if not safe:
            return
        goal = CellGoal({a: o.config.safe_q_um for a, o in safe.items()},  # type: ignore[misc]
                        {a: o.config.safe_voltage_v for a, o in safe.items()})
        deadline = time.monotonic() + self.safe_budget_s
        attempts, error_text = 0, ""
        while True:
            attempts += 1
            try:
                async with asyncio.timeout(max(0.0, deadline - time.monotonic())):
                    if reopen:
                        await self._close_all(safe)
                        await self._open_all(safe)
                    await self._move_to(goal, safe, follow_pending=False)
                self.log.info("actuator_safe", voltage_v=dict(goal.voltage_v), attempts=attempts)
                return
            except TimeoutError:
                error_text = f"not reached within {self.safe_budget_s:g} s" + (f" ({error_text})" if error_text else "")
                break
            except Exception as error:
                error_text, reopen = str(error), True
                remaining = deadline - time.monotonic()
                if remaining <= INITIAL_BACKOFF_S:
                    break
                await asyncio.sleep(min(INITIAL_BACKOFF_S * attempts, remaining / 2))
        self.log.error("actuator_safe_failed", voltage_v=dict(goal.voltage_v), error=error_text, attempts=attempts)

    # --- writing --------------------------------------------------------------------------------

    def _take_pending(self) -> CellGoal | None:
        with self._lock:
            pending, self._pending = self._pending, None
            if pending is None:
                self._wake_pending = False
            return pending

    def _next_goal(self) -> CellGoal | None:
        pending = self._take_pending()
        if pending is not None:
            return pending
        return self._goal if not self._goal_on_device else None

    async def _drive(self) -> None:
        backoff = INITIAL_BACKOFF_S
        while True:
            if self.fault_reason is not None:
                await asyncio.sleep(backoff * random.uniform(0.8, 1.2))
                backoff = min(backoff * 2.0, MAX_BACKOFF_S)
                try:
                    await self._open_all()
                except asyncio.CancelledError:
                    raise
                except Exception as error:
                    self.write_failures += 1
                    self.fault_reason = _reason(error, "reopen")
                    await self._close_all()
                    continue
                goal = self._next_goal()
                if goal is None:
                    self._recovered()
                    continue
            else:
                goal = self._next_goal()
                if goal is None:
                    await self._event.wait()
                    self._event.clear()
                    continue
            self._goal, self._goal_on_device = goal, False
            try:
                await self._move_to(goal, self._outputs, follow_pending=True)
            except asyncio.CancelledError:
                raise
            except Exception as error:
                reason = _reason(error, "write")
                if self.fault_reason is None:
                    self._enter_fault(reason)
                else:
                    self.write_failures += 1
                    self.fault_reason = reason
                await self._close_all()
                continue
            if self.fault_reason is not None:
                self._recovered()
            backoff = INITIAL_BACKOFF_S
            await asyncio.sleep(WRITE_PERIOD_S)

    async def _move_to(self, goal: CellGoal, outputs: Mapping[str, AxisOutput], *, follow_pending: bool) -> None:
        """Write ``goal`` to every axis (ramped per axis); each step writes the axes in order."""
        reached: set[str] = set()
        while True:
            if follow_pending:
                newer = self._take_pending()
                if newer is not None:
                    goal = self._goal = newer
                    reached = set()
            refused = [a for a, o in outputs.items() if not o.config.within_limits(goal.voltage_v[a])]
            if refused:  # a reload narrowed the limits under it: the stage holds, every axis
                self.log.warning("actuator_goal_dropped", axes=refused, voltage_v=dict(goal.voltage_v),
                                 reason="the served command is outside the limits now in force: the stage holds")
                self._goal, self._goal_on_device = None, True
                return
            began_s = time.monotonic()
            step = []  # every axis' value of this step, each checked before any axis is written
            for axis, out in outputs.items():
                if axis in reached:
                    continue
                goal_v = goal.voltage_v[axis]
                voltage = out.slew.next_voltage(out.config, out.at_v, goal_v, began_s)
                at_goal = voltage == goal_v
                if not at_goal:
                    voltage = min(max(voltage, out.config.v_min), out.config.v_max)
                try:
                    sent_v = checked_sent_voltage(out.actuator, out.config, voltage)
                except ValueError as error:
                    raise AxisFault(f"axis {axis}: {error}") from None
                q_um = goal.q_um[axis] if at_goal else out.config.q_um_for(voltage)
                x_um = goal.positions_um.get(axis) if goal.positions_um is not None else None
                step.append((out, q_um, voltage, sent_v, x_um, at_goal))
            for out, q_um, voltage, sent_v, x_um, at_goal in step:
                await self._write(out, q_um, voltage, sent_v, x_um)
                out.slew.wrote(began_s, at_goal)
                if at_goal:
                    reached.add(out.axis)
            if len(reached) == len(outputs):
                self._goal_on_device = True
                if follow_pending:  # a served goal (not the safe stop's)
                    for listener in self.reached_listeners:
                        listener(goal, time.monotonic())
                return
            await asyncio.sleep(RAMP_PERIOD_S)

    async def _write(self, out: AxisOutput, q_um: float, voltage_v: float, sent_v: float,
                     x_um: float | None) -> None:
        out.tried_v = sent_v
        out.at_v = None
        await _guarded(out.actuator.command(q_um, voltage_v, x_um=x_um), out.axis, "write")
        out.at_v = sent_v
        out.last_voltage_v, out.last_write_t = sent_v, time.time()
        out.writes += 1

    async def _open_all(self, outputs: Mapping[str, AxisOutput] | None = None) -> None:
        for out in (outputs if outputs is not None else self._outputs).values():
            out.slew.rest()
            await _guarded(out.actuator.open(), out.axis, "open")
            sent = tuple(v for v in (out.last_voltage_v, out.tried_v) if v is not None)
            start = await _guarded(locate_stage(out.actuator, out.config, sent), out.axis, "read back")
            if start.distrust is not None:
                self.log.warning("actuator_readback_untrusted", axis=out.axis, device=out.actuator.description,
                                 reason=start.distrust)
            out.at_v = start.voltage_v

    async def _close_all(self, outputs: Mapping[str, AxisOutput] | None = None) -> None:
        for out in (outputs if outputs is not None else self._outputs).values():
            try:
                await _guarded(out.actuator.close(), out.axis, "close")
            except asyncio.CancelledError:
                raise
            except Exception as error:
                self.log.warning("actuator_close_failed", axis=out.axis, error=str(error))

    # --- state changes --------------------------------------------------------------------------

    def _enter_fault(self, reason: str) -> None:
        self.write_failures += 1
        self.fault_reason = reason
        self._fault_since = time.monotonic()
        self.failures(error=reason)

    def _recovered(self) -> None:
        self.log.info("actuator_recovered", after_s=round(time.monotonic() - self._fault_since, 3))
        self.fault_reason = None


async def _guarded(step: Any, axis: str, what: str) -> Any:
    try:
        async with asyncio.timeout(WRITE_TIMEOUT_S):
            return await step
    except TimeoutError:
        raise AxisFault(f"axis {axis}: actuator {what} timed out after {WRITE_TIMEOUT_S:g} s") from None
    except (DeviceError, ValueError) as error:
        raise AxisFault(f"axis {axis}: {error}") from error


def _reason(error: BaseException, what: str) -> str:
    if isinstance(error, AxisFault | DeviceError):
        text = str(error)
    else:
        text = f"{type(error).__name__}: {error}"
    return text if what == "write" else f"{what} failed: {text}"
