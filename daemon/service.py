"""The compensation daemon: poll the sensors, answer every target, publish commands and telemetry.

One asyncio loop owns the sensors, the actuator, reloads and supervision; the decisions are the
plain classes of ``daemon.service_core``. Targets are answered on Zenoh's callback thread under
``Service.lock`` (every state change on the loop takes it too): handing each target to the loop
first costs a thread wake-up, more than the latency budget (benchmarks/daemon_latency.py
``--targets-on-loop`` measures that variant). Everything off the answer's path (the actuator, the
log) is handed to the loop with ``call_soon_threadsafe``, at most once per burst.

Signals: SIGHUP re-reads the config and the model (a bad edit is refused and the running
configuration keeps serving), SIGTERM/SIGINT stop cleanly (liveliness token withdrawn, session
closed, exit 0). systemd is told READY/STATUS/WATCHDOG/STOPPING through ``$NOTIFY_SOCKET``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import signal
import threading
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import zenoh

from daemon.bus import Bus, session_config
from daemon.config import Config, ConfigError, load_config, missing_model_channels
from daemon.logs import RateLimitedLog, get_logger
from daemon.model.model import Model, ModelFileError, load_model
from daemon.sdnotify import Notifier, watchdog_interval_s
from daemon.service_core import Compensator, Counters, Refusal, SensorTable, dumps, parse_target
from daemon.service_drivers import DriverSet, DriverSetupError, GroupPoller, build_drivers, make_context
from drivers.base import Reading, SensorGroup, State

SUPERVISE_INTERVAL_S = 0.25
STATUS_INTERVAL_S = 5.0
ACTUATION_COALESCE_S = 0.05  # during a stream of commands the stage takes the latest at most this often
SUPPRESSED_SUMMARY_S = 2.0  # how often "N refused targets not logged" is written during a flood


def load_model_or_problem(path: Path) -> tuple[Model | None, str]:
    try:
        return load_model(path), ""
    except ModelFileError as error:
        return None, str(error)


class Service:
    """The daemon for one cell. ``run()`` returns the exit code."""

    def __init__(
        self,
        config: Config,
        *,
        config_path: str | Path | None = None,
        zenoh_overrides: Mapping[str, Any] | None = None,
        notifier: Notifier | None = None,
    ) -> None:
        self.config = config
        self.config_path = Path(config_path) if config_path is not None else None
        self.zenoh_overrides = dict(zenoh_overrides or {})
        self.notifier = notifier or Notifier()
        self.log = get_logger("nanodrift.daemon")
        self.refused_log = RateLimitedLog(self.log, "target_refused")
        self.actuator_log = RateLimitedLog(self.log, "actuator_failed", level="error")
        self.counters = Counters()
        self.started = time.time()
        self.bus: Bus | None = None
        self.drivers: DriverSet | None = None
        self.pollers: list[GroupPoller] = []
        self.table = SensorTable(config.sensors)
        model, problem = load_model_or_problem(config.model.path)
        self.model_path = config.model.path
        self.compensator = Compensator(model, config.actuator, self.table, problem)
        self._stop = asyncio.Event()
        self._reload_lock = asyncio.Lock()
        self._actuator_task: asyncio.Task[None] | None = None
        self._actuation: tuple[float, float] | None = None  # the latest command not yet given to the stage
        self._actuation_wake_pending = False
        self._actuation_event = asyncio.Event()
        self._states: dict[str, str] = {}
        self._tasks: set[asyncio.Task[Any]] = set()
        self.clock = make_context(config).clock  # replaced by the drivers' context on start
        #: guards what the target path reads (table, compensator, counters) against the loop's writes
        self.lock = threading.Lock()
        self._serving = False
        self._loop: asyncio.AbstractEventLoop | None = None  # set when serving starts
        #: answer targets on the asyncio loop instead of Zenoh's thread (one more thread hop per target)
        self.targets_on_loop = os.environ.get("NANODRIFT_TARGETS_ON_LOOP") == "1"

    # --- lifecycle ----------------------------------------------------------------------------

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        for sig, handler in ((signal.SIGTERM, self.request_stop), (signal.SIGINT, self.request_stop),
                             (signal.SIGHUP, self.request_reload)):
            loop.add_signal_handler(sig, handler)
        self._log_start()
        try:
            session = zenoh.open(session_config(self.config.zenoh, **self.zenoh_overrides))
        except zenoh.ZError as error:
            self.log.error("zenoh_open_failed", error=str(error))
            return 1
        self.bus = Bus(session, self.config.cell)
        try:
            await self._start_drivers(build_drivers(self.config, None))
        except DriverSetupError as error:
            self.log.error("driver_setup_failed", error=str(error))
            self.bus.close()
            return 1
        self._loop = loop
        self._serving = True
        self.bus.serve(loop, self.on_target, self.on_status, targets_on_loop=self.targets_on_loop)
        supervisor = asyncio.create_task(self._supervise(), name="supervise")
        self.log.info("serving", cell=self.config.cell, keys=f"{self.bus.keys.prefix}/**",
                      model=self._model_id(), sensors=list(self.table.entries))
        self.notifier.ready(self._status_line())
        await self._stop.wait()

        self.notifier.stopping()
        with self.lock:
            self._serving = False  # targets arriving from now on are not answered by a half-closed daemon
        self.log.info("stopping", counters=self.counters.as_dict())
        supervisor.cancel()
        for task in list(self._tasks):
            task.cancel()
        self.bus.withdraw()  # clients see the daemon gone first
        await self._stop_drivers()
        self.bus.close()
        self.log.info("stopped")
        return 0

    def request_stop(self) -> None:
        self._stop.set()

    def request_reload(self) -> None:
        task = asyncio.get_running_loop().create_task(self.reload(), name="reload")
        self._tasks.add(task)
        task.add_done_callback(self._tasks.discard)

    async def _start_drivers(self, drivers: DriverSet) -> None:
        self.drivers = drivers
        self.clock = drivers.context.clock
        if drivers.actuator is not None:
            try:
                await drivers.actuator.open()
            except Exception as error:
                self.log.error("actuator_open_failed", error=str(error))
            self._actuation_wake_pending = False
            self._actuator_task = asyncio.create_task(self._drive_actuator(drivers.actuator), name="actuator")
        self.pollers = [
            GroupPoller(g, drivers.context.clock, self._on_readings, self._on_group_failure, self._on_group_recovered)
            for g in drivers.groups
        ]
        for poller in self.pollers:
            poller.start()

    async def _stop_drivers(self) -> None:
        await asyncio.gather(*(p.stop() for p in self.pollers), return_exceptions=True)
        self.pollers = []
        if self._actuator_task is not None:
            self._actuator_task.cancel()
            try:
                await self._actuator_task
            except asyncio.CancelledError:
                pass
            self._actuator_task = None
        if self.drivers is not None and self.drivers.actuator is not None:
            try:
                await self.drivers.actuator.close()
            except Exception as error:
                self.log.warning("actuator_close_failed", error=str(error))

    # --- sensors ------------------------------------------------------------------------------

    def _on_readings(self, group: SensorGroup, readings: Mapping[str, Reading]) -> None:
        temps: dict[str, float] = {}
        t_obs = None
        telemetry = []
        with self.lock:
            for name, reading in readings.items():
                entry = self.table.update(name, reading)
                if entry is None:
                    continue
                if entry.role == "temperature" and entry.device_state == State.OK:
                    temps[name] = reading.value
                    t_obs = reading.t if t_obs is None else max(t_obs, reading.t)
                doc = {"value": reading.value, "unit": entry.unit, "t": reading.t, "state": entry.device_state.value}
                if entry.reason:
                    doc["reason"] = entry.reason
                telemetry.append((entry.role, name, doc))
            if temps and t_obs is not None:
                self.compensator.observe(t_obs, temps)
        if self.bus is not None:
            try:
                for role, name, doc in telemetry:
                    self.bus.publish_telemetry(role, name, dumps(doc))
            except zenoh.ZError as error:  # a bus problem is not the device's fault
                self.log.warning("telemetry_failed", error=str(error))

    def _on_group_failure(self, group: SensorGroup, reason: str, retry_in_s: float) -> None:
        with self.lock:
            self.table.mark_fault(group.names, f"device error: {reason}")
        self.log.warning("sensor_group_failed", channels=list(group.names), reason=reason,
                         retry_in_s=round(retry_in_s, 2))

    def _on_group_recovered(self, group: SensorGroup) -> None:
        self.log.info("sensor_group_recovered", channels=list(group.names))

    # --- targets (the hot path) ---------------------------------------------------------------

    def on_target(self, payload: bytes, query: zenoh.Query | None) -> None:
        """Answer one target exactly once: a command or an error, with its id.

        Runs on Zenoh's callback thread (see ``daemon.bus``): the answer is computed and published
        under ``self.lock``, which every state change on the loop also takes; what is not on the
        answer's path (the actuator, the log) is handed to the loop with ``call_soon_threadsafe``.
        """
        bus, loop = self.bus, self._loop
        refusal: Refusal | None = None
        wake_actuator = log_refusal = False
        suppressed = 0
        with self.lock:
            if not self._serving or bus is None or loop is None:
                if query is not None:
                    query.drop()
                return
            self.counters.targets += 1
            try:
                target = parse_target(payload)
                command = self.compensator.compensate(target, self.clock.now(), time.time())
            except Refusal as refused:
                refusal = refused
            except Exception as error:  # a bug must still produce an answer, and a traceback in the log
                refusal = Refusal("internal", f"internal error: {type(error).__name__}: {error}")
                loop.call_soon_threadsafe(self._log_failure, error)
            try:
                if refusal is None:
                    data = self.compensator.encode(command)
                    bus.publish_command(data)
                    if query is not None:
                        bus.reply(query, bus.keys.compensate, data)
                    self.counters.commands += 1
                    if self._actuator_task is not None:
                        self._actuation = (command["q_um"], command["voltage_v"])
                        wake_actuator = not self._actuation_wake_pending
                        self._actuation_wake_pending = True
                else:
                    self.counters.errors[refusal.kind] += 1
                    data = dumps(refusal.payload())
                    bus.publish_error(data)
                    if query is not None:
                        bus.reply_err(query, data)
                    log_refusal = self.refused_log.limiter.allow()
                    if log_refusal:
                        suppressed = self.refused_log.limiter.take_suppressed()
            except zenoh.ZError as error:  # the bus itself failed (session closing): say so, free the query
                loop.call_soon_threadsafe(self._log_bus_failure, error)
                if query is not None:
                    with contextlib.suppress(zenoh.ZError):
                        query.drop()
                return
        # after the answer is out, and at most once per burst: wake the loop (a wake per target would
        # compete for the CPU with Zenoh's own threads and cost more latency than all the rest)
        if wake_actuator:
            loop.call_soon_threadsafe(self._actuation_event.set)
        elif log_refusal and refusal is not None:
            loop.call_soon_threadsafe(self._log_refusal, refusal, suppressed)

    def _log_refusal(self, refusal: Refusal, suppressed_before: int) -> None:
        fields: dict[str, Any] = {"id": refusal.id, "kind": refusal.kind, "reason": refusal.message}
        if suppressed_before:
            fields["suppressed_before"] = suppressed_before
        self.log.warning("target_refused", **fields)

    def _log_bus_failure(self, error: Exception) -> None:
        self.log.error("answer_not_sent", error=str(error))

    def _log_failure(self, error: Exception) -> None:
        self.log.error("target_failed", error=repr(error), exc_info=error)

    async def _drive_actuator(self, actuator: Any) -> None:
        """Give the stage the latest command; while commands keep coming, look again every
        ``ACTUATION_COALESCE_S`` instead of being woken for each one."""
        while True:
            await self._actuation_event.wait()
            self._actuation_event.clear()
            while True:
                with self.lock:
                    pending, self._actuation = self._actuation, None
                    if pending is None:
                        self._actuation_wake_pending = False
                        break
                try:
                    await actuator.command(*pending)
                except asyncio.CancelledError:
                    raise
                except Exception as error:
                    self.actuator_log(error=str(error))
                await asyncio.sleep(ACTUATION_COALESCE_S)

    # --- status -------------------------------------------------------------------------------

    def status(self) -> dict[str, Any]:
        with self.lock:
            return self._status()

    def _status(self) -> dict[str, Any]:
        now = self.clock.now()
        comp = self.compensator
        return {
            "cell": self.config.cell,
            "t": time.time(),
            "uptime_s": round(time.time() - self.started, 3),
            "config": self.config.source,
            "model": comp.model_info(),
            "model_path": str(self.model_path),
            "model_problem": comp.model_problem or None,
            "sensors": self.table.snapshot(now),
            "extrapolating": sorted(set(comp.extrapolating_now(now)) | set(comp.last_extrapolating)),
            "actuator": self.config.actuator.model_dump(),
            "counters": self.counters.as_dict(),
            "healthy": self._healthy(),
        }

    def on_status(self, query: zenoh.Query) -> None:
        assert self.bus is not None
        try:
            self.bus.reply(query, self.bus.keys.status, dumps(self.status()))
        except zenoh.ZError as error:
            self.log.warning("status_reply_failed", error=str(error))

    def _model_id(self) -> str | None:
        return self.compensator.model.id if self.compensator.model is not None else None

    def _status_line(self) -> str:
        now = self.clock.now()
        states = [self.table.state(n, now)[0] for n in self.table.entries]
        ok = sum(s == State.OK for s in states)
        return (f"cell {self.config.cell}: {ok}/{len(states)} sensors ok, model {self._model_id() or 'none'}, "
                f"{self.counters.commands} commands, {sum(self.counters.errors.values())} refused")

    # --- supervision: staleness, watchdog -----------------------------------------------------

    def _healthy(self) -> bool:
        """The loop runs (we are in it) and every poller is alive and making progress."""
        limit = GroupPoller.MAX_BACKOFF_S * 1.5
        now = time.monotonic()
        for poller in self.pollers:
            if poller.task is None or poller.task.done():
                return False
            if now - poller.last_progress > max(limit, 3 * poller.group.interval_s + poller.group.timeout_s):
                return False
        return True

    async def _supervise(self) -> None:
        watchdog = watchdog_interval_s()
        last_ping = last_status = last_summary = 0.0
        while True:
            now_mono = time.monotonic()
            self._check_states()
            if watchdog is not None and now_mono - last_ping >= watchdog and self._healthy():
                self.notifier.watchdog()
                last_ping = now_mono
            if now_mono - last_summary >= SUPPRESSED_SUMMARY_S:
                with self.lock:
                    suppressed = self.refused_log.limiter.take_suppressed()
                if suppressed:
                    self.log.warning("target_refused_suppressed", suppressed=suppressed)
                self.actuator_log.flush()
                last_summary = now_mono
            if now_mono - last_status >= STATUS_INTERVAL_S:
                self.notifier.status(self._status_line())
                last_status = now_mono
            await asyncio.sleep(SUPERVISE_INTERVAL_S if watchdog is None else min(SUPERVISE_INTERVAL_S, watchdog))

    def _check_states(self) -> None:
        now = self.clock.now()
        with self.lock:
            states = [(name, entry, *self.table.state(name, now)) for name, entry in self.table.entries.items()]
        for name, entry, state, reason in states:
            previous = self._states.get(name)
            if previous == state.value:
                continue
            self._states[name] = state.value
            if previous is None and state == State.STALE and entry.t is None:
                continue  # starting up: nothing read yet is not news
            log = self.log.info if state == State.OK else self.log.warning
            log("sensor_state", channel=name, state=state.value, was=previous, reason=reason)
            if state == State.STALE and self.bus is not None:
                doc = {"value": entry.value, "unit": entry.unit, "t": entry.t, "state": "stale", "reason": reason}
                self.bus.publish_telemetry(entry.role, name, dumps(doc))

    # --- reload -------------------------------------------------------------------------------

    async def reload(self) -> bool:
        """Re-read the config file and the model; apply a valid edit, refuse a bad one."""
        async with self._reload_lock:
            self.notifier.reloading(time.monotonic_ns() // 1000)
            try:
                applied = await self._reload()
            finally:
                self.notifier.ready(self._status_line())
            return applied

    async def _reload(self) -> bool:
        source = str(self.config_path) if self.config_path else "<built-in default config>"
        try:
            new = load_config(self.config_path)
        except ConfigError as error:
            self.counters.reload_failures += 1
            self.log.error("reload_refused", config=source, problems=error.problems)
            return False
        try:
            model = load_model(new.model.path)
        except ModelFileError as error:
            self.counters.reload_failures += 1
            self.log.error("reload_refused", config=source, problems=[f"model.path: {error}"])
            return False
        old = self.config
        if new.cell != old.cell or new.zenoh != old.zenoh:
            self.log.warning("reload_needs_restart", detail="cell and [zenoh] changes apply at the next restart")
            new = new.model_copy(update={"cell": old.cell, "zenoh": old.zenoh})
            new._source = old.source if self.config_path is None else str(self.config_path)
        drivers_changed = (new.sensors, new.hubs, new.simulation) != (old.sensors, old.hubs, old.simulation)
        if drivers_changed:
            context = self.drivers.context if self.drivers and new.simulation == old.simulation else None
            try:
                drivers = build_drivers(new, context)
            except DriverSetupError as error:
                self.counters.reload_failures += 1
                self.log.error("reload_refused", config=source, problems=[f"sensors: {error}"])
                return False
            await self._stop_drivers()
        with self.lock:  # the swap is atomic for the target path on Zenoh's thread
            if drivers_changed:
                table = SensorTable(new.sensors)
                for name, entry in table.entries.items():
                    previous = self.table.entries.get(name)
                    if previous is not None and previous.role == entry.role:
                        entry.value, entry.t = previous.value, previous.t
                        entry.device_state, entry.reason = previous.device_state, previous.reason
                self.table = table
                self._states = {}
            compensator = Compensator(model, new.actuator, self.table)
            old_comp = self.compensator
            if old_comp.model is not None and old_comp.model.id == model.id and old_comp.evaluator is not None:
                compensator.evaluator = old_comp.evaluator  # same model: keep lag filters and direction
            else:
                self._warm(compensator)
            self.compensator = compensator
            self.config = new
            self.model_path = new.model.path
        if drivers_changed:
            await self._start_drivers(drivers)
        self.counters.reloads += 1
        missing = missing_model_channels(new, model.channels)
        self.log.info("reload_applied", config=source, model=model.id, sensors=list(self.table.entries),
                      drivers_restarted=drivers_changed, missing_channels=missing or None)
        return True

    def _warm(self, compensator: Compensator) -> None:
        """Feed a new evaluator the latest good readings so it can serve at once."""
        temps = {n: e.value for n, e in self.table.entries.items()
                 if e.role == "temperature" and e.device_state == State.OK and e.value is not None}
        times = [e.t for n, e in self.table.entries.items() if n in temps and e.t is not None]
        if temps and times:
            compensator.observe(max(times), temps)

    def _log_start(self) -> None:
        model = self.compensator.model
        missing = missing_model_channels(self.config, model.channels) if model else []
        self.log.info("starting", config=self.config.source, cell=self.config.cell,
                      model_path=str(self.config.model.path), model=model.id if model else None,
                      model_problem=self.compensator.model_problem or None, missing_channels=missing or None)


def run_service(config: Config, config_path: str | Path | None = None,
                zenoh_overrides: Mapping[str, Any] | None = None) -> int:
    """Run the daemon until SIGTERM/SIGINT; the exit code."""

    async def main() -> int:
        return await Service(config, config_path=config_path, zenoh_overrides=zenoh_overrides).run()

    return asyncio.run(main())
