"""The simulated cell's clocks: scaled wall time for the daemon, virtual time for procedures.

:class:`ScaledClock` (``[simulation] speed``; the tests' emulated cell too): real sleeps, simulated time faster.

:class:`VirtualClock`: sleeps take no wall time, so hours of simulated procedure run in seconds.
A discrete-event scheduler on top of asyncio: ``sleep`` registers a wake-up time and waits; a single
advancer task moves simulated time to the earliest pending wake-up only when no other task is
runnable (the event loop's ready queue is empty), then wakes every sleeper due at that instant.
So several tasks sleeping concurrently interleave exactly as they would in real time. A lone sleeper
(nothing else runnable, no timer due, no other sleeper: a procedure's polls) skips the scheduler and
jumps to its wake-up at once, which is what the advancer would do, without its rounds of the loop.

Only for code whose waits all go through this clock (the simulated drivers, the procedures): a task
waiting on real I/O is not "runnable", and simulated time would run ahead of it.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import time
from typing import Any


class ScaledClock:
    """Real sleeps, but simulated time runs ``speed`` times faster than the wall clock."""

    def __init__(self, speed: float = 1.0, start: float | None = None) -> None:
        # monotonic like nanodrift.drivers.base.MonotonicClock: a wall-clock step moves neither
        if speed <= 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.speed = speed
        #: what ``now()`` read when the clock was made (unix seconds of the simulated lab)
        self.start_unix_s = time.time() if start is None else start
        self._mono0 = time.monotonic()

    def now(self) -> float:
        return self.start_unix_s + self.speed * (time.monotonic() - self._mono0)

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds) / self.speed)


class VirtualClock:
    """Sleeps take no wall time: simulated time jumps to the next wake-up when nothing else can run.

    The common case of a procedure, one task sleeping while nothing else is runnable, waiting or due, takes
    no scheduler round: the time jumps at once (what the advancer would do after its idle rounds), and the
    task yields to the loop every :attr:`YIELD_EVERY` such sleeps (I/O and signal handlers, a Ctrl-C, get
    in: what arrives then is as if it came during the wake-up). Anything else goes through the scheduler.
    """

    #: fast sleeps between two yields to the event loop
    YIELD_EVERY = 16

    def __init__(self, start: float = 0.0) -> None:
        self._now = float(start)
        self._heap: list[tuple[float, int, asyncio.Future[None]]] = []
        self._seq = itertools.count()
        self._advancer: asyncio.Task[None] | None = None
        self._unyielded = 0

    def now(self) -> float:
        return self._now

    async def sleep(self, seconds: float) -> None:
        loop = asyncio.get_running_loop()
        wake = self._now + max(0.0, float(seconds))
        if not self._heap and self._loop_idle(loop):
            # no other sleeper, nothing runnable or due: the advancer would wake this sleeper next, at ``wake``
            self._now = max(self._now, wake)
            self._unyielded += 1
            if self._unyielded < self.YIELD_EVERY:
                return
            self._unyielded = 0
            await asyncio.sleep(0)
            return
        future: asyncio.Future[None] = loop.create_future()
        heapq.heappush(self._heap, (wake, next(self._seq), future))
        if self._advancer is None or self._advancer.done():
            self._advancer = loop.create_task(self._advance(loop), name="VirtualClock.advance")
        await future

    @staticmethod
    def _loop_idle(loop: asyncio.AbstractEventLoop) -> bool:
        """Whether nothing but the caller could run now: no callback ready, no timer due (False when this loop
        does not show its queues: then every sleep goes through the scheduler)."""
        ready: Any = getattr(loop, "_ready", None)
        scheduled: Any = getattr(loop, "_scheduled", None)
        if ready is None or scheduled is None or ready:
            return False
        return not scheduled or scheduled[0].when() > loop.time()

    async def _advance(self, loop: asyncio.AbstractEventLoop) -> None:
        idle_rounds = 0
        while self._heap:
            await asyncio.sleep(0)
            if getattr(loop, "_ready", None):  # other callbacks are runnable
                idle_rounds = 0
                continue
            if idle_rounds < 1:  # one more round: callbacks scheduled by the last wake-ups settle
                idle_rounds += 1
                continue
            idle_rounds = 0
            while self._heap and self._heap[0][2].done():  # cancelled sleepers
                heapq.heappop(self._heap)
            if not self._heap:
                break
            due = self._heap[0][0]
            self._now = max(self._now, due)
            while self._heap and self._heap[0][0] <= due:
                _, _, future = heapq.heappop(self._heap)
                if not future.done():
                    future.set_result(None)
