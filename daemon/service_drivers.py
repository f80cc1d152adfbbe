"""From the validated config to running driver objects: the context, sensor groups, the actuator.

Each sensor group is polled by its own task at its own ``interval_s``; a poll that raises
:class:`DeviceError` or takes longer than ``timeout_s`` closes the group and reopens it with
exponential backoff and jitter, while its channels read as faulted (with the reason).
"""

from __future__ import annotations

import asyncio
import random
import time
from collections.abc import Awaitable, Callable
from dataclasses import dataclass, field
from typing import Any

from daemon.config import Config
from drivers.base import Actuator, Clock, DeviceError, DriverContext, Reading, ScaledClock, SensorGroup, WallClock
from drivers.registry import load_plugin

SIMULATED = "simulated"


class DriverSetupError(Exception):
    """A plugin refused the configured sensors (the message names the kind)."""


@dataclass
class DriverSet:
    context: DriverContext
    groups: list[SensorGroup]
    actuator: Actuator | None = None
    roles: dict[str, str] = field(default_factory=dict)


def make_context(config: Config) -> DriverContext:
    """The clock and simulation settings the plugins share. Simulated cells may run faster."""
    clock: Clock = WallClock()
    simulation: dict[str, Any] = config.simulation.model_dump()
    if SIMULATED in config.kinds():
        speed = float(simulation.get("speed", 1.0) or 1.0)
        clock = ScaledClock(speed) if speed != 1.0 else WallClock()
    return DriverContext(clock=clock, hubs={h.name: h for h in config.hubs}, simulation=simulation)


def build_drivers(config: Config, context: DriverContext | None = None) -> DriverSet:
    context = context or make_context(config)
    groups: list[SensorGroup] = []
    actuator: Actuator | None = None
    for kind in config.kinds():
        plugin = load_plugin(kind)
        configs = [s for s in config.sensors if s.kind == kind]
        try:
            groups.extend(plugin.create(configs, context))
        except Exception as error:
            raise DriverSetupError(f"driver {kind!r}: {error}") from error
        create_actuator = getattr(plugin, "create_actuator", None)
        if actuator is None and create_actuator is not None:
            actuator = create_actuator(context)
    roles = {s.name: s.role for s in config.sensors}
    return DriverSet(context=context, groups=groups, actuator=actuator, roles=roles)


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
