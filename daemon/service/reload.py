"""SIGHUP: re-read the config file and the model; apply a valid edit, refuse a bad one.

A refused edit (bad TOML, unknown key, corrupt model, a plugin refusing its sensors) is logged with
every problem and the running configuration keeps serving. Cell and ``[zenoh]`` changes wait for
the next restart. The drivers are restarted only when the sensors, hubs, plugin sections or the
actuator changed; the swap of table, compensator and config is atomic for the target path.

Two edits are refused whatever else they say: one that switches between the simulated cell and
hardware, and one that removes every sensor of a running cell (an emptied file): both need a
restart, so a slip of the editor never changes what the stage is.

The new serving state is built as at start (``nanodrift.service.state``: the same model gives the same
reason to refuse it). ``[health]`` and ``[adapt]`` apply with the swap: the health unit serves through the
new compensator, and an axis' new model or changed settings start its monitor and bias tracker afresh.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable
from dataclasses import KW_ONLY, dataclass, field
from pathlib import Path
from typing import Any, Protocol

from nanodrift.config import BUILTIN_SOURCE, ConfigError, load_config, missing_model_channels
from nanodrift.drivers.base import DriverContext, DriverSetupError
from nanodrift.drivers_set import DriverSet
from nanodrift.sdnotify import Notifier
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.state import CellState, load_serving_model, serving_state


class DriverHost(Protocol):
    """Who runs the drivers (the runner): the current set, and how to build, stop and start one."""

    drivers: DriverSet | None

    def build_drivers(self, config: Any, context: DriverContext | None) -> DriverSet: ...

    async def stop_drivers(self) -> None: ...

    async def start_drivers(self, drivers: DriverSet) -> None: ...


@dataclass(eq=False)
class Reloader:
    state: CellState
    config_path: Path | None
    host: DriverHost
    notifier: Notifier
    log: Any
    _: KW_ONLY
    status_line: Callable[[], str]
    table_replaced: Callable[[], None]
    health: HealthUnit
    _lock: asyncio.Lock = field(default_factory=asyncio.Lock, init=False)
    _stopped: DriverSet | None = field(default=None, init=False)  # the drivers a reload in progress stopped

    async def reload(self) -> bool:
        """One reload at a time; systemd is told RELOADING, then READY whatever the outcome."""
        async with self._lock:
            self.notifier.reloading(time.monotonic_ns() // 1000)
            self._stopped = None
            try:
                return await self._reload()
            except Exception as error:  # never lost in a dead task: refused, logged with the reason, counted
                stopped, self._stopped = self._stopped, None
                if stopped is not None:  # it failed after stopping the running drivers, before the swap
                    await self.host.start_drivers(stopped)
                return self.refuse_internal(error)
            finally:
                self.notifier.ready(self.status_line())

    def source(self) -> str:
        """What the daemon's config came from, as its log lines name it: the file, or the built-in default."""
        return str(self.config_path) if self.config_path else BUILTIN_SOURCE

    def refuse_internal(self, error: BaseException) -> bool:
        """A failure no check foresaw (a bug): refused like any bad edit, with its traceback."""
        return self._refuse(self.source(), [f"internal error: {type(error).__name__}: {error}"], exc_info=error)

    def _refuse(self, source: str, problems: list[str], **details: Any) -> bool:
        self.state.counters.reload_failures += 1
        self.log.error("reload_refused", config=source, problems=problems, **details)
        return False

    async def _reload(self) -> bool:
        state = self.state
        source = self.source()
        try:
            new = load_config(self.config_path)
        except ConfigError as error:
            return self._refuse(source, error.problems)
        old = state.config
        if new.axis_names != old.axis_names:
            return self._refuse(source, [f"axes: the edited config has axes {', '.join(new.axis_names)}, the daemon "
                                         f"runs axes {', '.join(old.axis_names)}: a reload never adds or removes "
                                         "axes (systemctl restart nanodrift)"])
        model, problem = load_serving_model(new)  # what the start would say of it
        if model is None:
            return self._refuse(source, [f"model.path: {problem}"])
        if new.cell != old.cell or new.zenoh != old.zenoh:
            self.log.warning("reload_needs_restart",
                             detail="cell and [zenoh] changes (its prefix too) apply at the next restart")
            new = new.model_copy(update={"cell": old.cell, "zenoh": old.zenoh})
            new._source = old.source if self.config_path is None else str(self.config_path)
        if new.virtual_cell != old.virtual_cell:
            now, was = ("the simulated cell", "hardware") if new.virtual_cell else ("hardware", "the simulated cell")
            return self._refuse(source, [f"the edited config describes {now}, the daemon runs {was}: a reload "
                                         "never switches between them (systemctl restart nanodrift)"])
        if old.sensors and not new.sensors:
            return self._refuse(source, ["sensors: the edited config lists no sensors (an emptied file?); a reload "
                                         "never removes every sensor of a running cell (restart to run one "
                                         "without sensors)"])
        drivers_changed = (new.sensors, new.hubs, new.sections, new.actuator, new.axes,
                           new.sensor_workspaces()) != (old.sensors, old.hubs, old.sections, old.actuator, old.axes,
                                                        old.sensor_workspaces())
        if drivers_changed:
            running = self.host.drivers
            context = running.context if running is not None and new.sections == old.sections else None
            try:
                drivers = self.host.build_drivers(new, context)
            except DriverSetupError as error:
                return self._refuse(source, [f"sensors: {error}"])
            await self.host.stop_drivers()
            self._stopped = running  # started again if anything fails before the swap
        with state.lock:  # the swap is atomic for the target path on Zenoh's threads
            # [actuator] too when the drivers change: a position sensor's default range follows the workspace
            compensator = serving_state(new, model, self.health, running=state.compensator,
                                        table=None if drivers_changed else state.table)
            state.compensator = compensator
            state.config = new
            self._stopped = None
        self.health.flush()  # a reset state is logged and published at once
        if drivers_changed:
            self.table_replaced()
            await self.host.start_drivers(drivers)
        state.counters.reloads += 1
        missing = missing_model_channels(new, model.channels)
        self.log.info("reload_applied", config=source, model=model.id, sensors=list(state.table.entries),
                      drivers_restarted=drivers_changed, missing_channels=missing or None)
        return True
