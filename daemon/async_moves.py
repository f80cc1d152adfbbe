"""Moves, stops and ``status`` of one cell for an asyncio bridge (``nanodrift ioc``, ``nanodrift.bluesky``), with
no thread held while a move runs.

Why: :meth:`nanodrift.Client.move` blocks its thread until the move's ``done``, which may be minutes (a slewed
ramp) or never (a ``done`` lost, a stalled daemon). Run on asyncio's default executor (6 threads on two cores),
a few such moves took every thread, and a ``stop`` or a ``status`` queued behind them: a put to ``STOP`` waited
for the very moves it should end. Here only the ``compensate`` query runs in a thread, bounded by
``answer_timeout_s``; the ``done`` is a future resolved on the loop by a ``done`` subscriber of this object's
own (registered before the query leaves, so a ``done`` that overtakes the answer is kept). ``stop`` and
``status`` each have a worker of their own, so neither ever waits behind a move's query.
"""

from __future__ import annotations

import asyncio
import functools
import threading
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import zenoh

from nanodrift.bus.session import undeclare_all
from nanodrift.client import Client, Command, Position, json_object, outcome

__all__ = ["ANSWER_TIMEOUT_S", "AsyncMoves", "Moving"]

#: how long a move waits for the daemon's answer (the command or a refusal) before it fails
ANSWER_TIMEOUT_S = 10.0


@dataclass
class Moving:
    """A move the daemon answered: its :class:`~nanodrift.client.Command`, and :meth:`ended` to await its ``done``."""

    command: Command
    _moves: AsyncMoves = field(repr=False)
    _id: str = field(repr=False)
    _done: asyncio.Future[dict[str, Any]] = field(repr=False)

    async def ended(self, timeout_s: float) -> Command:
        """The command with its ``done`` once ``reached``; :class:`~nanodrift.MoveEnded` on ``stopped``,
        ``superseded`` or ``failed``; :class:`TimeoutError` when no ``done`` comes within ``timeout_s``."""
        try:
            done = await asyncio.wait_for(self._done, timeout_s)
        except TimeoutError:
            raise TimeoutError(f"no done for move {self._id!r} within {timeout_s:g} s (the command was answered; "
                               "the output may still be ramping)") from None
        finally:
            self._moves.forget(self._id)
        return outcome(self.command, done)


class AsyncMoves:
    """``client``'s cell moved, stopped and asked for ``status`` from a loop; :meth:`close` before the client's."""

    def __init__(self, client: Client, *, axes: int = 1, answer_timeout_s: float = ANSWER_TIMEOUT_S) -> None:
        self.client = client
        self.answer_timeout_s = answer_timeout_s
        self._lock = threading.Lock()
        self._awaited: dict[str, asyncio.Future[dict[str, Any]]] = {}  # move id -> the future its done resolves
        # a query per axis at once, and one more (an axis' next put while its last still waits for the answer)
        self._queries = ThreadPoolExecutor(max_workers=axes + 1, thread_name_prefix=f"{client.cell}-move")
        self._stops = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{client.cell}-stop")
        self._statuses = ThreadPoolExecutor(max_workers=1, thread_name_prefix=f"{client.cell}-status")
        self._subscribers = [client.session.declare_subscriber(client.keys.done, self._on_done)]

    async def move(self, target: Position, *, answer_timeout_s: float | None = None) -> Moving:
        """Send ``target``; the :class:`Moving` once the daemon answered. :class:`~nanodrift.Refused`,
        :class:`TimeoutError` (no answer within ``answer_timeout_s``, default this object's),
        :class:`ConnectionError` or :class:`RuntimeError` (the client closed) when it did not take the move."""
        loop = asyncio.get_running_loop()
        answer_timeout_s = self.answer_timeout_s if answer_timeout_s is None else answer_timeout_s
        move_id = self.client.new_id()
        done: asyncio.Future[dict[str, Any]] = loop.create_future()
        with self._lock:
            self._awaited[move_id] = done  # before the query leaves: a fast done is kept
        try:
            command = await loop.run_in_executor(self._queries, functools.partial(
                self.client.move, target, wait=False, id=move_id, timeout_s=answer_timeout_s))
        except BaseException:
            self.forget(move_id)
            raise
        return Moving(command, self, move_id, done)

    async def stop(self, timeout_s: float = 5.0) -> dict[str, Any]:
        """:meth:`nanodrift.Client.stop` on a worker no move occupies."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._stops, lambda: self.client.stop(timeout_s=timeout_s))

    async def status(self, timeout_s: float = 2.0) -> dict[str, Any]:
        """:meth:`nanodrift.Client.status` on a worker no move occupies."""
        loop = asyncio.get_running_loop()
        return await loop.run_in_executor(self._statuses, lambda: self.client.status(timeout_s=timeout_s))

    def forget(self, move_id: str) -> None:
        with self._lock:
            self._awaited.pop(move_id, None)

    def _on_done(self, sample: zenoh.Sample) -> None:
        """Zenoh's thread: hand a ``done`` this object awaits to its loop."""
        doc = json_object(sample.payload.to_bytes())
        move_id = doc.get("id") if doc is not None else None
        if doc is None or not isinstance(move_id, str):
            return
        with self._lock:
            awaited = self._awaited.pop(move_id, None)
        if awaited is not None:
            awaited.get_loop().call_soon_threadsafe(_resolve, awaited, doc)

    def close(self) -> None:
        """Undeclare the subscriber; a move still awaiting its ``done`` fails (RuntimeError)."""
        undeclare_all(self._subscribers)
        with self._lock:
            awaited, self._awaited = list(self._awaited.values()), {}
        for each in awaited:
            if not each.get_loop().is_closed():
                each.get_loop().call_soon_threadsafe(_fail, each, RuntimeError(f"the client of cell "
                                                                                f"{self.client.cell!r} is closed"))
        for pool in (self._queries, self._stops, self._statuses):
            pool.shutdown(wait=False, cancel_futures=True)


def _resolve(future: asyncio.Future[dict[str, Any]], doc: dict[str, Any]) -> None:
    if not future.done():
        future.set_result(doc)


def _fail(future: asyncio.Future[dict[str, Any]], error: BaseException) -> None:
    if not future.done():
        future.set_exception(error)
