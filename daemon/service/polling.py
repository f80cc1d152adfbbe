"""Poll one sensor group forever: open, read every ``interval_s``, reopen with backoff on failure.

A poll that raises :class:`DeviceError` or takes longer than ``timeout_s`` closes the group and
reopens it with exponential backoff and jitter, while its channels read as faulted (with the reason).
:func:`pollers_healthy` is what the watchdog and ``status`` call health: every poller alive and
making progress.
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Awaitable, Callable, Iterable
from typing import Any

from drivers.base import Clock, DeviceError, Reading, SensorGroup


class GroupPoller:
    """Polls one group forever: open, read every ``interval_s``, reopen with backoff on failure."""

    INITIAL_BACKOFF_S = 0.2
    MAX_BACKOFF_S = 30.0

    def __init__(
        self,
        group: SensorGroup,
        clock: Clock,
        on_readings: Callable[[SensorGroup, dict[str, Reading]], None],
        on_failure: Callable[[SensorGroup, str, float], None],
        on_recovered: Callable[[SensorGroup], None] | None = None,
    ) -> None:
        self.group = group
        self.clock = clock
        self.on_readings = on_readings
        self.on_failure = on_failure
        self.on_recovered = on_recovered
        self.last_progress = time.monotonic()  # a poll attempt finished (for the watchdog)
        self.failures = 0
        self.task: asyncio.Task[None] | None = None
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
        try:
            async with asyncio.timeout(max(1.0, self.group.timeout_s)):
                await self.group.close()
        except Exception:  # closing a broken device must not stop the reopen cycle
            pass

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
                        self.failures = 0
                        backoff = self.INITIAL_BACKOFF_S
                        if self.on_recovered is not None:
                            self.on_recovered(self.group)
                    self.on_readings(self.group, readings)
                    await self.clock.sleep(self.group.interval_s)
            except asyncio.CancelledError:
                raise
            except Exception as error:  # DeviceError, timeouts, and plugin bugs alike: reopen
                self.failures += 1
                reason = str(error) if isinstance(error, DeviceError) else f"{type(error).__name__}: {error}"
                delay = backoff * random.uniform(0.8, 1.2)
                self.on_failure(self.group, reason, delay)
                await self._close()
                self.last_progress = time.monotonic()
                await asyncio.sleep(delay)
                backoff = min(backoff * 2.0, self.MAX_BACKOFF_S)


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
