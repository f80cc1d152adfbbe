"""The ``stop`` key: a client ends every ramp, and each output holds the value it has.

A ``stop`` comes as a put or as a query on ``<prefix>/<cell>/stop``, on Zenoh's thread like a target:
there it is placed among the served commands (:meth:`Actuation.stop_mark`: it ends the commands served
before it, never a target sent after it) and handed to the loop. Its payload is empty or ``{"id": ...}``
(:func:`nanodrift.bus.protocol.parse_stop`). :meth:`nanodrift.service.actuation.Actuation.halt` carries
it out between two writes: the command in flight ends ``stopped`` (its ``done``), the goal is forgotten,
and the next target moves again as usual.

- A put is not answered; a bad payload is logged (``stop_refused``) and ignored.
- A query is answered once the ramps have ended: ``{"id", "voltage_v", "held": true}``, ``voltage_v``
  what each output holds (a number in a one-axis cell, ``{axis: V}`` in a cell of several, null where
  unknown); a bad payload gets a reply error ``{"id", "error", "kind": "bad_payload"}``.
- A stop when nothing moves changes nothing and is answered the same way.
"""

from __future__ import annotations

import asyncio
from typing import Any

import zenoh

from nanodrift.bus.protocol import Stop, encode_stop_error, encode_stop_reply, parse_stop, wire_voltage
from nanodrift.bus.session import Bus
from nanodrift.compensation import Refusal
from nanodrift.service.actuation import Actuation


class StopHandler:
    """``on_stop`` for the bus: thread-safe (Zenoh's thread), the stop itself carried out on the loop."""

    def __init__(self, actuation: Actuation, bus: Bus, loop: asyncio.AbstractEventLoop, log: Any,
                 axes: tuple[str, ...]) -> None:
        self.actuation = actuation
        self.bus = bus
        self.loop = loop
        self.log = log
        self.axes = axes
        self._tasks: set[asyncio.Task[None]] = set()

    def on_stop(self, payload: bytes, query: zenoh.Query | None) -> None:
        upto = self.actuation.stop_mark()  # first: a target that arrives after this stop is not ended by it
        try:
            stop = parse_stop(payload)
        except Refusal as refused:
            if query is None:
                self.loop.call_soon_threadsafe(self._refused, refused.message)
            else:
                self._reply_err(query, encode_stop_error(refused.id, refused.message))
            return
        self.loop.call_soon_threadsafe(self._start, stop, query, upto)

    def _refused(self, reason: str) -> None:
        self.log.warning("stop_refused", reason=reason)

    def _start(self, stop: Stop, query: zenoh.Query | None, upto: int) -> None:
        task = self.loop.create_task(self._stop(stop, query, upto), name="stop")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _stop(self, stop: Stop, query: zenoh.Query | None, upto: int) -> None:
        try:
            held = await self.actuation.halt(upto)
        except Exception as error:  # a bug: said, and a querier is not left waiting
            self.log.error("stop_failed", id=stop.id, error=f"{type(error).__name__}: {error}", exc_info=error)
            if query is not None:
                self._reply_err(query, encode_stop_error(stop.id, f"internal error: {type(error).__name__}"))
            return
        voltage = wire_voltage(held, self.axes)
        self.log.info("stop_served", id=stop.id, voltage_v=voltage, query=query is not None)
        if query is not None:
            try:
                self.bus.reply(query, self.bus.keys.stop, encode_stop_reply(stop.id, voltage))
            except zenoh.ZError as error:
                self._reply_failed(str(error))

    def _reply_err(self, query: zenoh.Query, payload: bytes) -> None:
        try:
            self.bus.reply_err(query, payload)
        except zenoh.ZError as error:  # (maybe on Zenoh's thread: logged on the loop)
            self.loop.call_soon_threadsafe(self._reply_failed, str(error))

    def _reply_failed(self, error: str) -> None:
        self.log.warning("stop_reply_failed", error=error)
