"""A cell's outputs get the latest command: coalesced, ramped when the jump is large, never on the answer's path.

One object, :class:`Actuation`, drives every output of a cell, keyed by axis name (a one-axis cell is a
cell of one axis, ``x``). Answers hand their command over with :meth:`Actuation.offer` from Zenoh's
threads; the writes run on the asyncio loop, by one task for all axes, so commands never interleave on
a shared line (a GCS controller's port, a Modbus module's connection). A target asks for a wake of the
loop only when the loop is idle: while a write is under way, newer commands just replace the pending
one, and the loop takes the newest as soon as the write returns. Motion itself (where a move starts,
the slew, the limits of what is sent) is :mod:`nanodrift.motion`'s, the one owner the procedures use
too; this module owns the devices' lifecycle.

- **The goal** is the latest served command (every axis). It survives a reload that touches the
  actuators, a device reopened after a fault, and a target answered while the drivers were being
  swapped: once the (new) outputs are open, the goal is written to them (ramped from where each axis
  is). A goal the new limits forbid on any axis is dropped whole (``actuator_goal_dropped``) and the
  stage holds where it is.
- **Each step** computes every axis' next voltage under its own ``max_slew_um_per_s`` and writes the
  axes in the cell's order, so every axis of one command goes out before any axis of the next; axes
  that reached the goal are not written again for it. A move ends when every axis holds its goal.
- **Where each axis is** (:func:`nanodrift.motion.trusted_start`): its read-back is believed only inside
  its ``[v_min, v_max]`` and when it agrees with what was written to that device: by this process (a claim
  it contradicts, ``actuator_readback_untrusted``, starts the move from the value written), or, at a
  start, as the state directory's record says (:mod:`nanodrift.output_record`, saved before every write),
  or with nothing on record the output's ``power_up_voltage_v``, or (no record, or one it contradicts) as the
  axis' position sensor measures (:attr:`Actuation.position_witness`, within ``position_proof_tolerance_um``);
  each start says which in ``output_proved`` and ``status``' ``proved_by``. Anything else is unproven
  (:class:`UnprovenOutput`): the cell is in fault, the output is never written, and the reason says how to
  confirm it (``nanodrift confirm-output``); the reopen with backoff picks a confirmation up. A device that
  cannot be read back and was never written: the next command is written as it is (``actuator_unramped``,
  once per start).
- **Slew** (``max_slew_um_per_s > 0``): each sub-command covers the time since the previous write returned
  (the device had that value by then; a write cut short by a reload or a stop, from when the device was opened
  and read back again, as its bytes may land that late; a step under one count is not sent but waited for),
  so between any two values a device receives it never moves faster than the rate, however late the loop or
  the device; the ramp waits :meth:`nanodrift.motion.Slew.wait_s` between sub-commands (20 ms, or 9x a slow
  device's write time), so a slow module keeps ~90 % of the rate.
- **What is sent** is checked: the voltage each device will receive (``Actuator.sent_voltage``: a DAC's
  count, a controller's digits) must be inside that axis' limits, for every axis of a step before any
  axis is written, or nothing of the step is written and the cell is in fault.
- **Faults**: a failed open, read back or write (``DeviceError``, any error, a timeout) or readback
  mismatch on any axis puts the cell's output in ``fault`` with the reason (naming the axis in a cell
  of several); every axis is closed and reopened with backoff and the goal written again. Meanwhile
  targets are refused (``actuator_fault``). One ``actuator_failed`` line per episode,
  ``actuator_recovered`` when the devices work again (a write, a reopen with nothing to write, or a
  reload onto devices that open: an episode a reload interrupted is kept until then).
- **How each served command ends** (``done_listeners``; the runner publishes ``done``), exactly once:
  ``reached`` when every output holds it (the write of the ramp's end returned, the driver's read-back
  included, and a closed-loop controller says it is on target: GCS ``ONT?``; ``failed`` when it does not
  within :data:`ON_TARGET_BUDGET_S`); ``superseded`` when a newer command replaced it, pending (replaced in
  :meth:`offer`, told by the target path after its answer, :meth:`tell_superseded`) or in flight (a newer
  one taken mid-ramp); ``failed``
  when a write, read-back or open faults while it is in flight, or a reload's limits drop it (the goal is
  still written once the outputs work again: no second ``done``); ``stopped`` by :meth:`halt` or by the
  daemon's stop. A cell with no output device at all (every axis ``kind = "zenoh"``, or no actuator) still
  runs the drive task with no outputs: the published command is the actuation, so each command is ``reached``
  as soon as the loop takes it (paced as writes are, 50 a second: a command a newer one replaces within that
  is ``superseded``), and what a published axis holds is the latest command's voltage.
- **A client's stop** (:meth:`halt`): the drive task ends its ramp between two writes (a write under way
  completes), every output holds what it has, the command in flight (and a pending one) ends
  ``stopped``, and the goal is forgotten, so a reload or a reopen moves nothing. A stop ends only the
  commands served before it arrived (:meth:`stop_mark`, taken on Zenoh's thread): a target sent after
  it moves. The next command moves
  again, ramped from where each output is held; its first step covers no more than the time since the
  output's last write (:class:`nanodrift.motion.Slew`, kept over a restart on the same device).
- **Shutdown**: :meth:`Actuation.stop` with ``final=True`` ends the command in flight ``stopped``
  (``failed``, with the fault's reason, when the outputs are in fault), then ramps every axis with a finite
  ``safe_voltage_v`` to it, each axis in a task of its own within its own ``SAFE_RAMP_BUDGET_S`` (the unit's
  stop timeout less a margin: a dead module never holds another axis energised; axes on one line take turns
  on its lock), retrying a transient failure, and runs in a ``finally``: an exception on the way out never
  skips it.

The shapes of a one-axis cell (its log lines' fields, its fault's text, its ``status`` actuator) are
kept at the edges: :func:`nanodrift.compensation.one_axis` of the cell's axes says which shapes the lines
take, :meth:`Actuation.axis_doc` is a one-axis cell's ``status`` actuator.

One module on purpose: it is one object whose goal, fault and reopen cycle and shutdown ramp share one
state (the goal, what was sent, the devices open now) driven by one task on the loop; split, each part
would reach into the others' state. The motion rules it applies are already :mod:`nanodrift.motion`'s.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import random
import threading
import time
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from nanodrift.compensation import ONE_AXIS, one_axis
from nanodrift.config import SAFE_RAMP_BUDGET_S, ActuatorConfig
from nanodrift.drivers.base import Actuator, DeviceError
from nanodrift.logs import RateLimitedLog
from nanodrift.motion import RAMP_PERIOD_S, Slew, StartPoint, position_disagreement
from nanodrift.output_record import OutputRecords, RecordError
from nanodrift.outputs import bind_limits, checked_sent_voltage, locate_stage

WRITE_PERIOD_S = RAMP_PERIOD_S  # any two writes are this far apart: a stream is coalesced to 50 writes a second
WRITE_TIMEOUT_S = 3.0  # a write that takes longer is a fault
#: a closed-loop controller not on target this long after the last write of a move: its ``done`` is ``failed``
ON_TARGET_BUDGET_S = 2.0
INITIAL_BACKOFF_S = 0.2
MAX_BACKOFF_S = 5.0
@dataclass(frozen=True, slots=True, eq=False)
class Goal:
    """A command every axis should hold: q and voltage per axis, and the target's positions; ``id`` is the
    served command's and ``served`` False for the safe stop's goal (no ``done`` is owed for it)."""

    q_um: Mapping[str, float]
    voltage_v: Mapping[str, float]
    positions_um: Mapping[str, float] | None = None
    id: str | int | None = None
    served: bool = True
    seq: int = 0  # the order in which commands were served (a stop ends those served before it)


#: asked (on the loop) for an axis' position sensor's fresh reading: (sensor, measured µm), or why there is none
PositionWitness = Callable[[str], Awaitable[tuple[str, float] | str]]
#: how each way of proving a read-back at a start is named (``output_proved``'s ``by``, ``status``' ``proved_by``)
PROOF_NAMES = {"read back": "state", "power-up value": "power_up", "position sensor": "position_sensor"}

#: told (on the loop) when every output holds a goal: the goal and the monotonic time
OnReached = Callable[[Goal, float], None]
#: told once per served command (on the loop; a pending one replaced, on the target's thread), how it ended: the
#: goal, the state (reached, superseded, stopped or failed), what each axis holds now (V, None where unknown)
#: and, when it failed, why
OnDone = Callable[[Goal, str, dict[str, float | None], str | None], None]


@dataclass(eq=False)
class AxisOutput:
    """One axis' device and what is known of it."""

    axis: str
    actuator: Actuator
    config: ActuatorConfig
    slew: Slew = field(default_factory=Slew)
    at_v: float | None = None  # where the output is (ramps start there); None: unknown
    tried_v: float | None = None  # the last voltage sent, confirmed or not
    last_voltage_v: float | None = None  # what status shows (kept across a restart on the same device)
    last_write_t: float | None = None  # unix time: a label for people
    writes: int = 0
    unramped_told: bool = False  # actuator_unramped is said once per start
    #: how the read-back was proved when the daemon started on it: state, operator, power_up, position_sensor
    proved_by: str | None = None


class AxisFault(Exception):
    """A failure on one axis' device: ``text`` says what, ``axis`` where."""

    def __init__(self, axis: str, text: str) -> None:
        super().__init__(f"axis {axis}: {text}")
        self.axis = axis
        self.text = text


class UnprovenOutput(AxisFault):
    """An output whose read-back nothing confirms (:func:`nanodrift.motion.trusted_start`): never moved."""


class Actuation:
    """The goal (latest wins), the task that writes it to every axis' device, and their state."""

    def __init__(self, log: Any, *, safe_budget_s: float = SAFE_RAMP_BUDGET_S,
                 records: OutputRecords | None = None, position_witness: PositionWitness | None = None) -> None:
        self.log = log
        self.failures = RateLimitedLog(log, "actuator_failed", level="error")
        self.record_failures = RateLimitedLog(log, "output_record_failed", level="error")
        self.safe_budget_s = safe_budget_s
        #: what was last written to each output, kept durably before every write (how a restart proves a read-back)
        self.records = records if records is not None else OutputRecords(None, "cell")
        #: a position sensor's reading: what proves a read-back nothing on record confirms (None: nothing does)
        self.position_witness = position_witness
        self.axes: tuple[str, ...] = ONE_AXIS  # the cell's (set by :meth:`start`): the shapes its lines take
        self._lock = threading.Lock()  # guards what offer() touches; never held across an await or a publish
        self._active = False
        self._pending: Goal | None = None  # served, not yet taken by the loop (kept while drivers are swapped)
        self._wake_pending = False
        self._event = asyncio.Event()
        self._task: asyncio.Task[None] | None = None
        self._outputs: dict[str, AxisOutput] = {}  # the devices open now, in the cell's axis order
        self._known: dict[str, AxisOutput] = {}  # axis -> its last output (kept over a restart on the same device)
        self._goal: Goal | None = None  # the latest command taken: survives reloads and reopens
        self._goal_on_device = True  # the goal was written in full to the devices open now
        self.reached_listeners: list[OnReached] = []
        # --- how each served command ends (exactly one ``done`` each) ---
        self.done_listeners: list[OnDone] = []
        self._superseded: list[Goal] = []  # pending commands a newer one replaced before the loop took them
        self._drain_asked = False  # a wake was asked to tell the superseded ones while no drive loop runs
        self._inflight: Goal | None = None  # the served command the loop took and that has not ended yet
        self._offered_v: Mapping[str, float] = {}  # the latest command's voltages: what a published axis holds
        self._seq = 0  # commands served so far (under the lock)
        #: stops asked of the drive task: each one's answer and the last command it ends (its ``seq``)
        self._halt_waiters: list[tuple[asyncio.Future[dict[str, float | None]], int]] = []
        self._halt_event = asyncio.Event()  # a stop was asked: ends a fault's backoff at once
        #: set while in fault (read without a lock on Zenoh's threads: one attribute, atomic)
        self.fault_reason: str | None = None
        self._fault_since = 0.0
        self._episode_failures = 0
        self._stashed_episode: tuple[float, int] | None = None  # a fault a reload stopped, until a device opens
        self.write_failures = 0
        self._unkept_told = False

    # --- the target path (any thread) -----------------------------------------------------------

    def offer(self, q_um: Mapping[str, float], voltage_v: Mapping[str, float],
              positions_um: Mapping[str, float] | None = None, target_id: str | int | None = None) -> bool:
        """Make this the command every axis gets next (any thread). True: the caller must wake the loop
        (``loop.call_soon_threadsafe(actuation.wake)``); it is asked at most once per burst. While the
        drivers are being swapped (a reload) the command waits for the new outputs. A pending command this
        one replaces ends ``superseded`` at the caller's :meth:`tell_superseded`, else when the loop takes the newest
        (while the drivers are swapped, at the wake this asks for, once a burst): nothing piles up."""
        with self._lock:
            self._seq += 1
            goal = Goal(q_um, voltage_v, positions_um, target_id, seq=self._seq)
            if self._pending is not None:
                self._superseded.append(self._pending)
            self._pending = goal
            self._offered_v = voltage_v  # (read on the loop: copied there)
            if not self._active:  # no drive loop (a reload): the loop still tells the superseded ones, once a burst
                wake = bool(self._superseded) and not self._drain_asked
                self._drain_asked = self._drain_asked or wake
                return wake
            wake = not self._wake_pending
            self._wake_pending = True
            return wake

    def wake(self) -> None:
        """(On the loop.) Take the newest command; those it superseded end now."""
        self.tell_superseded()
        self._event.set()

    def tell_superseded(self) -> None:
        """(Any thread.) The commands a newer one replaced before the loop took them end ``superseded`` now. The
        target path calls it after its answer, so each target tells the one it replaced: at 1 kHz the loop would
        otherwise tell ~20 at each of its wakes, holding the GIL while targets wait (benchmarks/daemon_latency.py's
        p99)."""
        with self._lock:
            superseded, self._superseded = self._superseded, []
            self._drain_asked = False
        for goal in superseded:
            self._done(goal, "superseded")

    def doc(self) -> dict[str, Any]:
        """The outputs' state for a cell of several axes' ``status``: the cell's, then per axis."""
        return {
            "state": self._state(),
            "reason": self.fault_reason,
            "failures": self.write_failures,
            "axes": {axis: {"device": out.actuator.description, "last_voltage_v": out.last_voltage_v,
                            "last_write_t": out.last_write_t, "writes": out.writes, "proved_by": out.proved_by}
                     for axis, out in self._outputs.items()},
        }

    def axis_doc(self, axis: str = "x") -> dict[str, Any]:
        """One axis' output for a one-axis cell's ``status`` (state, reason, device, last written voltage and
        time, writes, failures); what was written stays shown while the device is closed."""
        out, known = self._outputs.get(axis), self._known.get(axis)
        return {
            "state": self._state(),
            "reason": self.fault_reason,
            "device": out.actuator.description if out is not None else None,
            "last_voltage_v": known.last_voltage_v if known is not None else None,
            "last_write_t": known.last_write_t if known is not None else None,
            "writes": known.writes if known is not None else 0,
            "failures": self.write_failures,
            "proved_by": known.proved_by if known is not None else None,
        }

    def _state(self) -> str:
        return "fault" if self.fault_reason is not None else ("ok" if self._outputs else "closed")

    # --- lifecycle (the loop) -------------------------------------------------------------------

    async def start(self, actuators: Mapping[str, Actuator], configs: Mapping[str, ActuatorConfig]) -> None:
        """Open every axis' device, find where each axis is, and start writing the goal and what follows; a
        failure to open (or to read an output back) is a fault (reopened with backoff). ``configs``: every
        axis of the cell's, those with no device (published) too."""
        self.axes = tuple(configs)
        outputs: dict[str, AxisOutput] = {}
        for axis, actuator in actuators.items():
            config = configs[axis]
            out = AxisOutput(axis, actuator, config)
            known = self._known.get(axis)
            if known is not None and known.actuator.description == actuator.description:
                # the same device: what it was sent still says where it is (another device's says nothing)
                out.last_voltage_v, out.last_write_t, out.tried_v = known.last_voltage_v, known.last_write_t, \
                    known.tried_v
                out.writes, out.proved_by = known.writes, known.proved_by
                out.slew = known.slew  # when it was last written bounds the first step of the next move
            bind_limits(actuator, config)
            outputs[axis] = out
        self._outputs = outputs
        self._known.update(outputs)
        if outputs and self.records.directory is None and not self._unkept_told:
            self._unkept_told = True
            self.log.warning("output_state_not_kept", reason="no $STATE_DIRECTORY and no [daemon] state_dir: "
                             "a restart cannot prove where an output is, so only its power-up value is believed")
        self.fault_reason = None
        self._goal_on_device = self._goal is None
        if outputs:
            try:
                starts = await self._open_all(outputs)
                self._log_open(starts)
                if self._stashed_episode is not None:
                    since, failures = self._stashed_episode
                    self.log.info("actuator_recovered", **self._devices(), via="reload",
                                  after_s=round(time.monotonic() - since, 3), failures=failures)
            except Exception as error:
                reason = self._fault_text(error, "open failed: ")
                if self._stashed_episode is not None:
                    self._fault_since, self._episode_failures = self._stashed_episode
                    self._still_failing(reason)
                else:
                    self._enter_fault(reason)
                self._end_inflight("failed", reason)  # a command a reload carried over: its outputs fault
            self._stashed_episode = None
        with self._lock:
            self._active, self._wake_pending = True, False
        self._task = asyncio.create_task(self._drive(), name="actuator")

    async def stop(self, *, final: bool = False) -> None:
        """Stop writing and close every axis' device (a failure to close is logged). ``final`` (the daemon
        stops): every command still in flight ends ``stopped`` (``failed``, with the reason, when the outputs
        are in fault), then every axis ramps to its finite ``safe_voltage_v``, whatever happened before. Not
        ``final`` (a reload): the goal and the command in flight wait for the next :meth:`start`."""
        with self._lock:
            self._active = False
        outputs, self._outputs = self._outputs, {}
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
            try:
                if self._halt_waiters:  # a client's stop the cancelled task did not carry out: done here
                    self._halted()
                if final:
                    self._end_all("failed" if fault is not None else "stopped", fault)
            except Exception as error:  # a bug: said, and never a reason to skip the safe ramp
                self.log.error("actuator_done_failed", error=_reason(error))
            if outputs:
                if fault is not None and not final:
                    self._stashed_episode = (self._fault_since, self._episode_failures)
                try:
                    if final:
                        await self._write_safe(outputs, reopen=fault is not None
                                               or any(o.at_v is None for o in outputs.values()))
                finally:
                    for out in outputs.values():
                        try:
                            await out.actuator.close()
                        except Exception as error:
                            self.log.warning("actuator_close_failed", **self._axis(out), error=str(error))

    async def _write_safe(self, outputs: Mapping[str, AxisOutput], *, reopen: bool) -> None:
        """Ramp every axis with a finite ``safe_voltage_v`` to it, each axis on its own and within its own budget
        (a dead module never holds another axis energised), reopening and retrying after a transient failure."""
        safe: dict[str, AxisOutput] = {}
        for axis, out in outputs.items():
            config = out.config
            if config.safe_q_um is None:
                continue  # nan: leave this axis where it is
            if not config.within_limits(config.safe_voltage_v):  # the config refuses this; never write it anyway
                self.log.error("actuator_safe_refused", **self._axis(out), voltage_v=config.safe_voltage_v,
                               v_min=config.v_min, v_max=config.v_max)
                continue
            safe[axis] = out
        if not safe:
            return
        # every axis' line shares its module's lock (a hub, a port): concurrent ramps never interleave a request
        ends = await asyncio.gather(*(self._safe_axis(out, reopen=reopen) for out in safe.values()))
        outcomes = list(zip(safe.values(), ends, strict=True))
        reached = {out.axis: out for out, (text, _) in outcomes if text is None}
        failed = {out.axis: (out, text) for out, (text, _) in outcomes if text is not None}
        attempts = max(n for _, n in ends)
        if reached:
            self.log.info("actuator_safe", **self._per_axis(
                "voltage_v", {a: o.config.safe_voltage_v for a, o in reached.items()}, reached), attempts=attempts)
        if failed:
            self.log.error("actuator_safe_failed",
                           voltage_v=self._value({a: o.config.safe_voltage_v for a, (o, _) in failed.items()}),
                           error="; ".join(text for _, text in failed.values()), attempts=attempts,
                           last_voltage_v=self._value({a: o.last_voltage_v for a, (o, _) in failed.items()}))

    async def _safe_axis(self, out: AxisOutput, *, reopen: bool) -> tuple[str | None, int]:
        """Ramp one axis to its ``safe_voltage_v`` within :attr:`safe_budget_s`: (None, attempts) once there, else
        (why not, attempts). An output whose read-back nothing confirms is never written, so not retried."""
        single = {out.axis: out}
        goal = Goal({out.axis: out.config.safe_q_um}, {out.axis: out.config.safe_voltage_v},  # type: ignore[dict-item]
                    served=False)
        deadline = time.monotonic() + self.safe_budget_s
        attempts, error_text = 0, ""
        while True:
            attempts += 1
            try:
                async with asyncio.timeout(max(0.0, deadline - time.monotonic())):
                    if reopen:
                        await self._close_quietly(single)
                        await self._open_all(single)
                    await self._move_to(goal, single, follow_pending=False)
                return None, attempts
            except TimeoutError:
                budget = f"not reached within {self.safe_budget_s:g} s"
                return budget + (f" ({error_text})" if error_text else ""), attempts
            except UnprovenOutput as error:
                return self._fault_text(error), attempts
            except Exception as error:
                error_text = self._fault_text(error)
                reopen = True
                remaining = deadline - time.monotonic()
                if remaining <= INITIAL_BACKOFF_S:
                    return error_text, attempts
                await asyncio.sleep(min(INITIAL_BACKOFF_S * attempts, remaining / 2))

    # --- writing --------------------------------------------------------------------------------

    def _take_pending(self) -> Goal | None:
        """The newest served command, if one came (on the loop): it is now the command in flight, and
        the one it replaces (and any a newer one replaced before) ends ``superseded``."""
        with self._lock:
            pending, self._pending = self._pending, None
            if pending is None:
                self._wake_pending = False
            superseded, self._superseded = self._superseded, []
        for goal in superseded:
            self._done(goal, "superseded")
        if pending is not None:
            if self._inflight is not None and self._inflight is not pending:
                self._done(self._inflight, "superseded")
            self._inflight = pending
        return pending

    def _next_goal(self) -> Goal | None:
        """A newer served command, else the goal when these devices do not hold it yet."""
        pending = self._take_pending()
        if pending is not None:
            return pending
        return self._goal if not self._goal_on_device else None

    # --- how commands end -----------------------------------------------------------------------

    def held(self) -> dict[str, float | None]:
        """What each axis holds now: an output's last confirmed voltage (None: unknown, e.g. mid-write), a
        published axis' (``kind = "zenoh"``) the latest command's voltage."""
        held: dict[str, float | None] = dict(self._offered_v)
        for axis, out in {**self._known, **self._outputs}.items():
            held[axis] = out.at_v if out.at_v is not None else out.last_voltage_v
        return held

    def _done(self, goal: Goal, state: str, error: str | None = None) -> None:
        if not goal.served:
            return
        held = self.held()
        for listener in self.done_listeners:
            try:
                listener(goal, state, held, error)
            except Exception as failure:  # a listener's bug must not stop the outputs
                self.log.error("done_listener_failed", error=_reason(failure))

    def _end_inflight(self, state: str, error: str | None = None) -> None:
        inflight, self._inflight = self._inflight, None
        if inflight is not None:
            self._done(inflight, state, error)

    def _end_all(self, state: str, error: str | None) -> None:
        """Every command owed a ``done`` ends: those superseded, the one in flight and the pending one."""
        with self._lock:
            pending, self._pending = self._pending, None
            superseded, self._superseded = self._superseded, []
        for goal in superseded:
            self._done(goal, "superseded")
        self._end_inflight(state, error)
        if pending is not None:
            self._done(pending, state, error)

    def stop_mark(self) -> int:
        """Where a stop arriving now falls among the served commands (any thread): it ends those served
        before it, never a target sent after it."""
        with self._lock:
            return self._seq

    async def halt(self, upto: int | None = None) -> dict[str, float | None]:
        """A client's ``stop`` (on the loop): every ramp ends after the write under way, each output holds
        the value it has, the command in flight (and one not yet taken) ends ``stopped``, and the goal is
        forgotten (a reload or a reopen moves nothing). ``upto`` (:meth:`stop_mark` when the stop arrived;
        default: now): a command served after the stop is not ended by it and moves as usual. Returns what
        each axis holds then. Nothing in flight: nothing changes, and the answer is the same."""
        upto = self.stop_mark() if upto is None else upto
        task = self._task
        if task is None or task.done():  # no drive loop (a reload between its stop and start, or stopped)
            return self._halted(upto)
        waiter: asyncio.Future[dict[str, float | None]] = asyncio.get_running_loop().create_future()
        self._halt_waiters.append((waiter, upto))
        self._halt_event.set()
        self._event.set()
        return await waiter

    def _halted(self, upto: int | None = None) -> dict[str, float | None]:
        """Carry out the stops asked (on the loop, between two writes): every command served up to the
        latest of them ends ``stopped``."""
        self._halt_event.clear()
        waiters, self._halt_waiters = self._halt_waiters, []
        last = max([u for _, u in waiters] + ([upto] if upto is not None else []), default=0)
        with self._lock:
            pending = self._pending
            if pending is not None and pending.seq <= last:
                self._pending = None
            else:
                pending = None  # served after the stop: it moves as usual
            superseded, self._superseded = self._superseded, []
        for goal in superseded:
            self._done(goal, "superseded")
        moving = False
        if self._inflight is not None and self._inflight.seq <= last:
            self._end_inflight("stopped")
            moving = True
        if pending is not None:
            self._done(pending, "stopped")
            moving = True
        current = self._goal
        if current is not None and current.seq <= last:
            moving = moving or not self._goal_on_device
            self._goal, self._goal_on_device = None, True
            for out in self._outputs.values():
                out.slew.rest()
        held = self.held()
        if moving:
            self.log.info("actuator_stopped", voltage_v=self._value(held))
        for waiter, _ in waiters:
            if not waiter.done():
                waiter.set_result(held)
        return held

    async def _drive(self) -> None:
        outputs = self._outputs  # this task's devices (a stop swaps them out before it cancels the task)
        backoff = INITIAL_BACKOFF_S
        while True:
            if self._halt_waiters:
                self._halted()
            if self.fault_reason is not None:
                with contextlib.suppress(TimeoutError):  # the back-off, ended at once by a stop
                    async with asyncio.timeout(backoff * random.uniform(0.8, 1.2)):
                        await self._halt_event.wait()
                backoff = min(backoff * 2.0, MAX_BACKOFF_S)
                if self._halt_waiters:
                    continue
                try:
                    await self._open_all(outputs)
                except Exception as error:
                    self._still_failing(self._fault_text(error, "reopen failed: "))
                    await self._close_quietly(outputs)
                    continue
                goal = self._next_goal()
                if goal is None:  # nothing to write: the devices open (and read back) again
                    self._recovered()
                    continue
            else:
                goal = self._next_goal()
                if goal is None:
                    await self._event.wait()
                    self._event.clear()
                    continue
            # not on the devices until a write of it is confirmed: a write that fails leaves it to be
            # written again once the devices work again (the chaos suite found it lost otherwise)
            self._goal, self._goal_on_device = goal, False
            try:
                await self._move_to(goal, outputs, follow_pending=True)
            except Exception as error:
                reason = self._fault_text(error)
                if self.fault_reason is None:
                    self._enter_fault(reason)
                else:
                    self._still_failing(reason)
                self._end_inflight("failed", reason)  # written again once the outputs work, with no second done
                await self._close_quietly(outputs)
                continue
            if self.fault_reason is not None:
                self._recovered()
            backoff = INITIAL_BACKOFF_S
            # Writes are paced at the ramp period: an isolated target is written at once, a stream is
            # coalesced to 50 writes/s (newest wins). Waking the loop for every target of a 1 kHz stream
            # halved the daemon's burst throughput and raised its answer latency (benchmarks/daemon_latency.py).
            # No outputs (every axis published) are paced the same: a stream still wakes the loop 50 times a
            # second, not once per target.
            await asyncio.sleep(WRITE_PERIOD_S)

    async def _move_to(self, goal: Goal, outputs: Mapping[str, AxisOutput], *, follow_pending: bool) -> None:
        """Write ``goal`` to every axis (ramped per axis under its slew limit; each step writes the axes in
        order); with ``follow_pending`` a newer command taken during the ramp becomes the goal (re-planned
        from where each axis is)."""
        reached: set[str] = set()
        while True:
            if follow_pending:
                if self._halt_waiters:  # a stop: the ramp ends here, between two writes
                    self._halted()
                    return
                newer = self._take_pending()
                if newer is not None:
                    goal = self._goal = newer
                    reached = set()
            # a reload narrowed the limits under it, or changed the gain so that its command (what a controller
            # sent positions gets) now means a voltage outside them: the stage holds, every axis
            refused = [a for a, o in outputs.items() if not self._takes(o, goal)]
            if refused:
                self._log_dropped(goal, outputs, refused)
                self._goal, self._goal_on_device = None, True
                if goal is self._inflight:
                    self._end_inflight("failed", "the command is outside the limits now in force on axis "
                                       f"{', '.join(refused)}: the stage holds")
                return
            began_s = time.monotonic()
            step = []  # every axis' value of this step, each checked before any axis is written
            for axis, out in outputs.items():
                if axis in reached:
                    continue
                goal_v = goal.voltage_v[axis]
                if out.at_v is None and out.config.max_slew_um_per_s > 0 and not out.unramped_told:
                    out.unramped_told = True
                    self.log.warning("actuator_unramped", **self._axis(out), device=out.actuator.description,
                                     voltage_v=goal_v, reason="where the stage is is unknown (no trusted read-back, "
                                     "nothing sent to it yet, safe_voltage_v = nan): this move is not ramped")
                voltage = out.slew.next_voltage(out.config, out.at_v, goal_v, began_s)
                at_goal = voltage == goal_v
                if not at_goal:  # mid-ramp from a stage outside limits a reload narrowed: never send outside
                    voltage = min(max(voltage, out.config.v_min), out.config.v_max)
                try:
                    sent_v = checked_sent_voltage(out.actuator, out.config, voltage)
                except ValueError as error:
                    raise AxisFault(axis, _reason(error)) from None
                if not at_goal and sent_v == out.at_v:  # the step is under one count (too soon after a reopen
                    continue  # that followed a cut-short write): the device would get what it holds; wait a pause
                q_um = goal.q_um[axis] if at_goal else out.config.q_um_for(voltage)
                x_goal = goal.positions_um.get(axis) if goal.positions_um is not None else None
                # the ramp's position in the target's frame: a template's x_um moves with the ramp, never ahead
                x_um = None if x_goal is None else x_goal + (q_um - goal.q_um[axis])
                step.append((out, q_um, voltage, sent_v, x_um, at_goal))
            for out, q_um, voltage, sent_v, x_um, at_goal in step:
                write_began_s = time.monotonic()
                try:
                    await self._write(out, q_um, voltage, sent_v, x_um)
                except BaseException:  # (a reload's cancellation too) the device may hold it from now
                    out.slew.cut_short(time.monotonic())
                    raise
                returned_s = time.monotonic()  # the device holds it from no later than now
                out.slew.wrote(returned_s, at_goal, took_s=returned_s - write_began_s)
                if at_goal:
                    reached.add(out.axis)
            if len(reached) == len(outputs):
                off_target = await self._off_target(outputs, interruptible=follow_pending)
                if off_target is None:
                    continue  # a newer command or a stop came while a controller settled: the loop's top takes it
                self._goal_on_device = True
                if off_target:
                    self.log.warning("actuator_not_on_target", axes=off_target, budget_s=ON_TARGET_BUDGET_S)
                    if goal is self._inflight:
                        self._end_inflight("failed", f"axis {', '.join(off_target)}: the controller did not report "
                                           f"on target within {ON_TARGET_BUDGET_S:g} s of the last write")
                    return
                if outputs and goal.served:  # (the safe stop's goal, axis by axis, is no served command)
                    for listener in self.reached_listeners:
                        listener(goal, time.monotonic())
                if goal is self._inflight:
                    self._end_inflight("reached")
                return
            # a slow device waits longer between steps (each covers the pause): it keeps its rate in larger steps
            await asyncio.sleep(max(o.slew.wait_s(o.config, o.at_v, goal.voltage_v[a])
                                    for a, o in outputs.items() if a not in reached))

    async def _off_target(self, outputs: Mapping[str, AxisOutput], *, interruptible: bool) -> list[str] | None:
        """The axes whose device does not say it is on target within :data:`ON_TARGET_BUDGET_S` (a closed-loop
        controller settling: :meth:`Actuator.on_target`; every other device is on target once written), asked
        every ramp period; None when ``interruptible`` and a newer command or a stop came meanwhile."""
        deadline_s = time.monotonic() + ON_TARGET_BUDGET_S
        while True:
            waiting = [axis for axis, out in outputs.items() if _settles(out.actuator)
                       and not await _guarded(out.actuator.on_target(), axis, "on-target query")]
            if not waiting or time.monotonic() >= deadline_s:
                return waiting
            if interruptible and (self._halt_waiters or self._has_pending()):
                return None
            await asyncio.sleep(RAMP_PERIOD_S)

    def _has_pending(self) -> bool:
        with self._lock:
            return self._pending is not None

    async def _write(self, out: AxisOutput, q_um: float, voltage_v: float, sent_v: float,
                     x_um: float | None) -> None:
        await self._record(out, out.at_v if out.at_v is not None else out.last_voltage_v, sent_v)
        out.tried_v = sent_v
        out.at_v = None  # until the device confirms it, the stage is between the two
        await _guarded(out.actuator.command(q_um, voltage_v, x_um=x_um), out.axis, "write")
        out.at_v = sent_v
        out.last_voltage_v, out.last_write_t = sent_v, time.time()
        out.writes += 1

    async def _record(self, out: AxisOutput, confirmed_v: float | None, written_v: float) -> None:
        """Keep on disk, before the write, what the device will hold: a restart believes only that (a failure
        to keep it is said, rate-limited, and never stops the write: the next start then refuses to guess)."""
        if self.records.directory is None:
            return
        try:
            await asyncio.to_thread(self.records.save, out.axis, out.actuator.description, confirmed_v, written_v)
        except OSError as error:
            self.record_failures(**self._axis(out), path=str(self.records.path(out.axis)), error=str(error))

    async def _open_all(self, outputs: Mapping[str, AxisOutput]) -> dict[str, StartPoint]:
        """Open every device and learn where each axis is (:func:`locate_stage`); raises like a write, and
        :class:`UnprovenOutput` for an output whose read-back nothing confirms (it is not moved)."""
        starts = {}
        for axis, out in outputs.items():
            out.slew.rest()
            await _guarded(out.actuator.open(), axis, "open")
            sent = tuple(v for v in (out.last_voltage_v, out.tried_v) if v is not None)
            sent_here = bool(sent)  # written by this process, the device's only writer since
            unreadable, recorded_by = None, "daemon"
            evidence: dict[str, Any] = {}
            if not sent_here:  # a restart: what an earlier run wrote, if the state directory kept it
                try:
                    sent, recorded_by = await asyncio.to_thread(self.records.read, axis, out.actuator.description)
                except RecordError as error:
                    unreadable = f"the state file cannot be read ({error})"
            start = await _guarded(locate_stage(out.actuator, out.config, sent, sent_here=sent_here, prove=True),
                                   axis, "read back")
            out.slew.reopened(time.monotonic())
            if unreadable is not None:
                start = StartPoint(None, "unproven", unreadable)
            elif start.known_from == "unproven" and start.claimed_v is not None:
                start, evidence = await self._prove_by_position(out, start.claimed_v, start.distrust or "")
            if not sent_here:
                self._proved(out, start, recorded_by, evidence)
            if start.known_from == "unproven":
                raise UnprovenOutput(axis, self._unproven_text(out, start))
            if start.distrust is not None:
                self.log.warning("actuator_readback_untrusted", **self._axis(out), device=out.actuator.description,
                                 reason=start.distrust, known_from=start.known_from,
                                 note="nothing is ramped from the read-back; the next move starts from "
                                 + ("the last value written" if start.voltage_v is not None else
                                    "nowhere known: it is written as it is"))
            out.at_v = start.voltage_v
            starts[axis] = start
        return starts

    async def _prove_by_position(self, out: AxisOutput, claimed_v: float,
                                 distrust: str) -> tuple[StartPoint, dict[str, Any]]:
        """A read-back nothing on record confirms, proved by the axis' position sensor (fresh, within
        ``position_proof_tolerance_um`` of the command the voltage means), else still unproven, saying why;
        with the evidence ``output_proved`` states."""
        tolerance_um = out.config.position_proof_tolerance_um
        if math.isnan(tolerance_um) or self.position_witness is None:
            return StartPoint(None, "unproven", distrust, claimed_v), {}
        witness = await _guarded(self.position_witness(out.axis), out.axis, "position sensor's reading")
        if isinstance(witness, str):
            text = f"{distrust}; not proved by a position sensor: {witness}"
            return StartPoint(None, "unproven", text, claimed_v), {}
        sensor, measured_um = witness
        problem = position_disagreement(out.config, claimed_v, measured_um, tolerance_um)
        if problem is not None:
            return StartPoint(None, "unproven", f"{distrust}; {problem} (sensor {sensor})", claimed_v), {}
        evidence = {"sensor": sensor, "measured_um": measured_um, "tolerance_um": tolerance_um,
                    "implied_um": round(out.config.q_um_for(claimed_v), 6), "unconfirmed": distrust}
        return StartPoint(claimed_v, "position sensor"), evidence

    def _proved(self, out: AxisOutput, start: StartPoint, recorded_by: str, evidence: Mapping[str, Any]) -> None:
        """Say how a start (no value written by this process yet) proved the read-back it believes: one
        ``output_proved`` line (with the position sensor's evidence), and ``status``' ``proved_by``."""
        by = PROOF_NAMES.get(start.known_from)
        if by == "state" and recorded_by == "operator":
            by = "operator"
        out.proved_by = by
        if by is not None:
            self.log.info("output_proved", axis=out.axis, by=by, voltage_v=start.voltage_v,
                          device=out.actuator.description, **evidence)

    def _unproven_text(self, out: AxisOutput, start: StartPoint) -> str:
        """What an operator reads in ``status`` and in every refusal: what disagrees, what to check, how to confirm."""
        path = self.records.path(out.axis)
        kept = f"state file {path}" if path is not None else \
            "no state is kept: set [daemon] state_dir, or run under systemd's StateDirectory="
        return (f"{start.distrust}: where the output is cannot be proven ({kept}), so it is not moved and targets "
                f"are refused. Check what {out.actuator.description} holds (a voltmeter on the amplifier's input, "
                f"or the stage's position), then confirm it: nanodrift confirm-output --config <the config> "
                f"--axis {out.axis} --voltage <V>; the daemon retries on its own")

    async def _close_quietly(self, outputs: Mapping[str, AxisOutput]) -> None:
        """Close failed devices before reopening them (a failure to close is only logged)."""
        for out in outputs.values():
            try:
                await _guarded(out.actuator.close(), out.axis, "close")
            except Exception as error:
                self.log.warning("actuator_close_failed", **self._axis(out), error=self._fault_text(error))

    # --- state changes --------------------------------------------------------------------------

    def _enter_fault(self, reason: str) -> None:
        self.write_failures += 1
        self.fault_reason = reason
        self._fault_since = time.monotonic()
        self._episode_failures = 1
        self.failures(**self._devices(), error=reason)

    def _still_failing(self, reason: str) -> None:
        self.write_failures += 1
        self._episode_failures += 1
        self.fault_reason = reason

    def _recovered(self) -> None:
        self.log.info("actuator_recovered", **self._devices(),
                      after_s=round(time.monotonic() - self._fault_since, 3), failures=self._episode_failures)
        self.fault_reason = None
        self._episode_failures = 0

    # --- the shapes of log lines and fault texts (a one-axis cell keeps its own) ----------------

    def _fault_text(self, error: BaseException, prefix: str = "") -> str:
        """The fault's reason: an axis' failure names the axis in a cell of several."""
        if isinstance(error, UnprovenOutput):
            prefix = ""  # it opened: what it claims is the problem
        if isinstance(error, AxisFault):
            return prefix + (error.text if one_axis(self.axes) else str(error))
        return prefix + _reason(error)

    def _axis(self, out: AxisOutput) -> dict[str, Any]:
        """The ``axis`` field of a line about one axis (none in a one-axis cell)."""
        return {} if one_axis(self.axes) else {"axis": out.axis}

    def _devices(self) -> dict[str, Any]:
        """The ``device`` of a one-axis cell's line; nothing in a cell of several (the reason names the axis)."""
        if not one_axis(self.axes):
            return {}
        out = next(iter(self._outputs.values()), None)
        return {"device": out.actuator.description if out is not None else None}

    def _value(self, per_axis: Mapping[str, Any]) -> Any:
        """A per-axis value as a line shows it: the number in a one-axis cell, ``{axis: value}`` otherwise."""
        if one_axis(self.axes) and len(per_axis) == 1:
            return next(iter(per_axis.values()))
        return dict(per_axis)

    def _per_axis(self, name: str, per_axis: Mapping[str, Any], outputs: Mapping[str, AxisOutput]) -> dict[str, Any]:
        """``name=value, device=...`` in a one-axis cell, ``name={axis: value}`` otherwise."""
        if one_axis(self.axes):
            out = next(iter(outputs.values()))
            return {name: per_axis[out.axis], "device": out.actuator.description}
        return {name: dict(per_axis)}

    def _log_open(self, starts: Mapping[str, StartPoint]) -> None:
        outputs = self._outputs
        if one_axis(self.axes):
            out = next(iter(outputs.values()))
            start = starts[out.axis]
            self.log.info("actuator_open", device=out.actuator.description, voltage_v=start.voltage_v,
                          known_from=start.known_from)
        else:
            self.log.info("actuator_open", axes={a: o.actuator.description for a, o in outputs.items()},
                          voltage_v={a: s.voltage_v for a, s in starts.items()},
                          known_from={a: s.known_from for a, s in starts.items()})

    @staticmethod
    def _takes(out: AxisOutput, goal: Goal) -> bool:
        """Whether ``out`` can be sent ``goal`` under the config in force: its voltage, its command at the gain
        now in force, and every field the device's command carries (a template's ``x_um``) within the limits."""
        axis, config = out.axis, out.config
        if not (config.within_limits(goal.voltage_v[axis]) and config.within_limits(config.voltage(goal.q_um[axis]))):
            return False
        try:
            out.actuator.check_command(goal.q_um[axis], goal.voltage_v[axis], x_um=(
                goal.positions_um.get(axis) if goal.positions_um is not None else None))
        except ValueError:
            return False
        return True

    def _log_dropped(self, goal: Goal, outputs: Mapping[str, AxisOutput], refused: list[str]) -> None:
        reason = "the served command is outside the limits now in force: the stage holds"
        if one_axis(self.axes):
            out = outputs[refused[0]]
            self.log.warning("actuator_goal_dropped", device=out.actuator.description,
                             voltage_v=goal.voltage_v[out.axis], v_min=out.config.v_min, v_max=out.config.v_max,
                             held_v=out.at_v, reason=reason)
        else:
            self.log.warning("actuator_goal_dropped", axes=refused, voltage_v=dict(goal.voltage_v),
                             held_v={a: o.at_v for a, o in outputs.items()}, reason=reason)


def _settles(actuator: Actuator) -> bool:
    """Whether a device has an on-target state of its own to ask (a closed-loop controller). One without is
    on target once written (the base's answer): asking it anyway put a timeout guard and a coroutine into
    every write cycle, a stretch of the loop's that targets wait behind (benchmarks/daemon_latency.py's p99)."""
    return getattr(type(actuator), "on_target", None) is not Actuator.on_target


async def _guarded(step: Any, axis: str, what: str) -> Any:
    """Await a device step; its failure (a timeout included) as an :class:`AxisFault` naming the axis."""
    # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancellation
    try:
        async with asyncio.timeout(WRITE_TIMEOUT_S):
            return await step
    except TimeoutError:
        raise AxisFault(axis, f"actuator {what} timed out after {WRITE_TIMEOUT_S:g} s") from None
    except Exception as error:
        raise AxisFault(axis, _reason(error)) from error


def _reason(error: BaseException) -> str:
    return str(error) if isinstance(error, DeviceError) else f"{type(error).__name__}: {error}"
