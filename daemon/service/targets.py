"""The hot path: answer each target exactly once, a command or an error with its id.

Runs on Zenoh's callback threads (handing each target to the asyncio loop first costs a thread
wake-up, more than the latency budget; benchmarks/daemon_latency.py ``--targets-on-loop``).

Two locks, taken in this order:

- ``answer_lock`` (this module's; the loop never takes it) is held from the computation to the
  publish, so answers leave in the order they were computed: the stage's output node applies the
  last ``command`` it sees, which must be the last one computed.
- ``state.lock`` (shared with the loop) is held only while the answer is computed, never while it
  is published: a publish that waits on a congested subscriber cannot stop sensor polling, reloads
  or status.

While the output device is in fault (``Actuation.fault_reason``) every target is refused with kind
``actuator_fault`` before the model sees it.

A ``compensate`` reply goes to its querier after both locks are released. What is not on the
answer's path (the actuator, the log) is handed to the loop with ``call_soon_threadsafe``, at most
once per burst. At ``--log-level debug`` (checked once, when the handler is made) every answer is
handed to the loop too and logged there (``target_answered``: id, x, q, V, latency in µs); at info
that costs nothing. The answer latency (arrival to publish) is counted into the metrics' histogram
buckets under the answer lock (:class:`nanodrift.service.latency.AnswerLatency`).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import threading
import time
from typing import Any

import zenoh

from nanodrift.bus.protocol import encode_command, encode_error, parse_target
from nanodrift.bus.session import Bus
from nanodrift.compensation import Command, Refusal, Target, one_axis
from nanodrift.logs import RateLimitedLog
from nanodrift.service.actuation import Actuation
from nanodrift.service.latency import AnswerLatency
from nanodrift.service.state import CellState


def debug_enabled(log: Any) -> bool:
    """Whether ``log`` writes debug lines (structlog's filtering logger, else the stdlib's root level)."""
    try:
        return bool(log.is_enabled_for(logging.DEBUG))
    except AttributeError:
        return logging.getLogger().isEnabledFor(logging.DEBUG)


class TargetHandler:
    """``on_target`` for the bus: thread-safe, never blocks the loop."""

    def __init__(self, state: CellState, bus: Bus, loop: asyncio.AbstractEventLoop,
                 actuation: Actuation, log: Any, latency: AnswerLatency | None = None) -> None:
        self.state = state
        #: the cell's axes (fixed for the daemon's life: a reload never changes them)
        self.cell_axes = state.config.axis_names
        self.latency = latency or AnswerLatency()
        #: checked once: at info level the hot path never builds a debug line
        self.debug = debug_enabled(log)
        self.bus = bus
        self.loop = loop
        self.actuation = actuation
        self.log = log
        self.answer_lock = threading.Lock()
        #: refused targets are logged through a token bucket (a flood costs a summary line); under state.lock
        self.refused_log = RateLimitedLog(log, "target_refused")

    def on_target(self, payload: bytes, query: zenoh.Query | None) -> None:
        """Answer one target: compute under ``state.lock``, publish under ``answer_lock``, then reply."""
        started = time.perf_counter()
        state, bus = self.state, self.bus
        command: Command | None = None
        refusal: Refusal | None = None
        failure: Exception | None = None
        log_refusal = wake_actuator = False
        suppressed = 0
        with self.answer_lock:
            with state.lock:
                if not state.serving and not state.stopping:
                    if query is not None:  # starting: nothing answers yet (the liveliness token is not up)
                        query.drop()
                    return
                state.counters.targets += 1
                target: Target | None = None
                try:
                    target = parse_target(payload, self.cell_axes)
                    if state.stopping:
                        raise Refusal("shutting_down", "the daemon is stopping: target not served", target.id)
                    fault = self.actuation.fault_reason
                    if fault is not None:  # before the model: a refused target must not move `dir` or lags
                        raise Refusal("actuator_fault",
                                      f"actuator fault: {fault}; the stage holds its last position", target.id)
                    command = state.compensator.compensate(target, state.clock.now(), time.time())
                    state.counters.commands += 1
                except Refusal as refused:
                    refusal = refused
                except Exception as error:  # a bug must still produce an answer, and a traceback in the log
                    failure = error
                    refusal = Refusal("internal", f"internal error: {type(error).__name__}: {error}",
                                      target.id if target is not None else None)
                if refusal is not None:
                    state.counters.errors[refusal.kind] += 1
                    log_refusal = self.refused_log.limiter.allow()
                    if log_refusal:
                        suppressed = self.refused_log.limiter.take_suppressed()
            try:
                if command is not None:
                    data = encode_command(command)  # published once, all axes
                    bus.publish_command(data)
                    wake_actuator = self.actuation.offer(command.q_um, command.voltage_v, command.positions_um,
                                                         command.id)
                else:
                    assert refusal is not None
                    data = encode_error(refusal)
                    bus.publish_error(data)
                elapsed_s = time.perf_counter() - started
                self.latency.observe(elapsed_s)
            except zenoh.ZError as error:  # the bus itself failed (session closing): say so, free the query
                self.loop.call_soon_threadsafe(self._log_bus_failure, error)
                if query is not None:
                    with contextlib.suppress(zenoh.ZError):
                        query.drop()
                return
        if query is not None:
            try:
                if command is not None:
                    bus.reply(query, bus.keys.compensate, data)
                else:
                    bus.reply_err(query, data)
            except zenoh.ZError as error:
                self.loop.call_soon_threadsafe(self._log_bus_failure, error)
        if command is not None:  # after the answer is out: the command this one replaced ends superseded
            self.actuation.tell_superseded()
        # after the answer is out, and at most once per burst: wake the loop
        if wake_actuator:
            self.loop.call_soon_threadsafe(self.actuation.wake)
        if failure is not None:
            self.loop.call_soon_threadsafe(self._log_failure, failure)
        if log_refusal and refusal is not None:
            self.loop.call_soon_threadsafe(self._log_refusal, refusal, suppressed)
        if self.debug:
            self.loop.call_soon_threadsafe(self._log_answer, command, refusal, elapsed_s)

    def take_suppressed(self) -> int:
        """Refused targets not logged since the last call (for the periodic summary)."""
        with self.state.lock:
            return self.refused_log.limiter.take_suppressed()

    def _log_refusal(self, refusal: Refusal, suppressed_before: int) -> None:
        fields: dict[str, Any] = {"id": refusal.id, "kind": refusal.kind, "reason": refusal.message}
        if suppressed_before:
            fields["suppressed_before"] = suppressed_before
        self.log.warning("target_refused", **fields)

    def _log_answer(self, command: Command | None, refusal: Refusal | None, elapsed_s: float) -> None:
        latency_us = round(elapsed_s * 1e6, 1)
        if command is not None and one_axis(self.cell_axes):
            self.log.debug("target_answered", id=command.id, x_um=command.positions_um["x"],
                           q_um=round(command.q_um["x"], 6), voltage_v=round(command.voltage_v["x"], 6),
                           latency_us=latency_us)
        elif command is not None:
            self.log.debug("target_answered", id=command.id, positions_um=dict(command.positions_um),
                           q_um=dict(command.q_um), voltage_v=dict(command.voltage_v), latency_us=latency_us)
        elif refusal is not None:
            self.log.debug("target_answered", id=refusal.id, error=refusal.kind, reason=refusal.message,
                           latency_us=latency_us)

    def _log_bus_failure(self, error: Exception) -> None:
        self.log.error("answer_not_sent", error=str(error))

    def _log_failure(self, error: Exception) -> None:
        self.log.error("target_failed", error=repr(error), exc_info=error)
