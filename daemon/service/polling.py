"""Poll one sensor group forever: open, read every ``interval_s``, reopen with backoff on failure.

A poll that raises :class:`DeviceError` or takes longer than ``timeout_s`` closes the group and
reopens it with exponential backoff and jitter, while its channels read as faulted (with the reason).
This back-off is the only one between the daemon and a device: drivers make one connection attempt
when asked and never wait on their own, so the timing of reconnection is decided here, where the
failure episode is known (its first failure, how many attempts, when it ended).
:func:`pollers_healthy` is what the watchdog and ``status`` call health: every poller alive and
making progress.
"""

from __future__ import annotations

import asyncio
import contextlib
import random
import time
from collections.abc import Awaitable, Callable, Iterable
from typing import Any

from nanodrift.drivers.base import Clock, DeviceError, MonotonicClock, Reading, SensorGroup

#: (group, reason, retry_in_s, failures so far in this episode: 1 for the first)
OnFailure = Callable[[SensorGroup, str, float, int], None]
#: (group, failed attempts in the episode that ended, seconds from its first failure to the recovery)
OnRecovered = Callable[[SensorGroup, int, float], None]


class GroupPoller:
    """Polls one group forever: open, read every ``interval_s``, reopen with backoff on failure.

    ``clock`` paces the polls (the group's clock); ``retry_clock`` times the waits between reopen
    attempts: real time unless a test gives a virtual clock, since a device comes back in real time.
    """

    INITIAL_BACKOFF_S = 0.2
    MAX_BACKOFF_S = 30.0
    JITTER = 0.2  # each wait is the backoff times a uniform factor in [1 - JITTER, 1 + JITTER]

    def __init__(
        self,
        group: SensorGroup,
        clock: Clock,
        on_readings: Callable[[SensorGroup, dict[str, Reading]], None],
        on_failure: OnFailure,
        on_recovered: OnRecovered | None = None,
        *,
        retry_clock: Clock | None = None,
    ) -> None:
        self.group = group
        self.clock = clock
        self.retry_clock: Clock = retry_clock or MonotonicClock()
        self.on_readings = on_readings
        self.on_failure = on_failure
        self.on_recovered = on_recovered
        self.last_progress = time.monotonic()  # a poll attempt finished (for the watchdog)
        self.failures = 0  # in the current episode (0: the group is healthy)
        self.failing_since = 0.0  # retry_clock time of the episode's first failure
        self.task: asyncio.Task[None] | None = None
        #: set when the first poll attempt has finished, read or failed: the daemon is ready to answer then
        self.first_attempt = asyncio.Event()
        self._stopping = False

    def start(self) -> asyncio.Task[None]:
        self.task = asyncio.create_task(self._run(), name=f"poll:{','.join(self.group.names)}")
        return self.task

    async def stop(self) -> None:
        self._stopping = True
        task = self.task
        while task is not None and not task.done():
            task.cancel()
            await asyncio.wait({task}, timeout=1.0)  # re-cancel if a driver swallowed the first one
        await self._close()

    async def _close(self) -> None:
        with contextlib.suppress(Exception):  # closing a broken device must not stop the reopen cycle
            async with asyncio.timeout(max(1.0, self.group.timeout_s)):
                await self.group.close()

    async def _guard(self, step: Awaitable[Any], what: str) -> Any:
        # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancellation (stop() hangs)
        try:
            async with asyncio.timeout(self.group.timeout_s):
                return await step
        except TimeoutError:
            raise DeviceError(f"{what} timed out after {self.group.timeout_s:g} s") from None

    async def _run(self) -> None:
        backoff = self.INITIAL_BACKOFF_S
        while not self._stopping:
            try:
                await self._guard(self.group.open(), "open")
                while not self._stopping:
                    readings = await self._guard(self.group.read(), "read")
                    self.last_progress = time.monotonic()
                    if self.failures:
                        failures, self.failures = self.failures, 0
                        backoff = self.INITIAL_BACKOFF_S
                        if self.on_recovered is not None:
                            self.on_recovered(self.group, failures, self.retry_clock.now() - self.failing_since)
                    self.on_readings(self.group, readings)
                    self.first_attempt.set()
                    await self.clock.sleep(self.group.interval_s)
            except Exception as error:  # DeviceError, timeouts, and plugin bugs alike: reopen
                if not self.failures:
                    self.failing_since = self.retry_clock.now()
                self.failures += 1
                reason = str(error) if isinstance(error, DeviceError) else f"{type(error).__name__}: {error}"
                delay = backoff * random.uniform(1.0 - self.JITTER, 1.0 + self.JITTER)
                self.on_failure(self.group, reason, delay, self.failures)
                self.first_attempt.set()
                await self._close()
                self.last_progress = time.monotonic()
                await self.retry_clock.sleep(delay)
                backoff = min(backoff * 2.0, self.MAX_BACKOFF_S)


async def first_attempts(pollers: Iterable[GroupPoller], limit_s: float = 10.0) -> None:
    """Until every poller has finished its first attempt (a device's open and read, or their timeouts),
    at most ``limit_s``: a daemon that says it serves has read what it can, so a client's first target
    is not refused for a reading that was simply not taken yet."""
    waits = [asyncio.ensure_future(p.first_attempt.wait()) for p in pollers]
    if not waits:
        return
    _, pending = await asyncio.wait(waits, timeout=limit_s)
    for wait in pending:
        wait.cancel()


def pollers_healthy(pollers: Iterable[GroupPoller]) -> bool:
    """Every poller's task is alive and finished a poll attempt recently (its backoff allowed for)."""
    limit = GroupPoller.MAX_BACKOFF_S * 1.5
    now = time.monotonic()
    for poller in pollers:
        if poller.task is None or poller.task.done():
            return False
        if now - poller.last_progress > max(limit, 3 * poller.group.interval_s + poller.group.timeout_s):
            return False
    return True
