"""The daemon's lifecycle: signals, the Zenoh session, the drivers, serving, and a clean stop.

Like aiohttp's ``web_runner``: setup and cleanup live here, apart from what serves (the handlers
in ``targets``, ``status``, ``sensors``, ``supervision``, ``reload``, ``actuation``). One asyncio
loop owns the sensors, the actuator, reloads and supervision; targets are answered on Zenoh's
threads (``nanodrift.service.targets``).

Signals: SIGHUP re-reads the config and the model (a bad edit is refused and the running
configuration keeps serving), SIGTERM/SIGINT stop cleanly (liveliness token withdrawn, a finite
``safe_voltage_v`` written to the output device, session closed, exit 0). systemd is told
READY/STATUS/WATCHDOG/STOPPING through ``$NOTIFY_SOCKET``.
"""

from __future__ import annotations

import asyncio
import gc
import signal
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import TYPE_CHECKING, Any

import zenoh

from nanodrift.bus.protocol import encode_done, wire_voltage
from nanodrift.bus.session import Bus, describe_zenoh_error, listen_endpoints, session_config
from nanodrift.compensation import one_axis
from nanodrift.config import Config, missing_model_channels
from nanodrift.drivers.base import DriverContext, DriverSetupError, MonotonicClock
from nanodrift.drivers_set import DriverSet
from nanodrift.errors import UserError
from nanodrift.logs import get_logger
from nanodrift.output_record import OutputRecords, state_directory
from nanodrift.sdnotify import Notifier
from nanodrift.service.actuation import Actuation, Goal
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.latency import AnswerLatency
from nanodrift.service.polling import GroupPoller, first_attempts, pollers_healthy
from nanodrift.service.recorder import Recorder
from nanodrift.service.reload import Reloader
from nanodrift.service.sensors import SensorIngest
from nanodrift.service.state import CellState, load_serving_model, serving_state
from nanodrift.service.status import StatusHandler, status_doc, status_line
from nanodrift.service.stop import StopHandler
from nanodrift.service.supervision import SensorWatch, Supervisor
from nanodrift.service.targets import TargetHandler

if TYPE_CHECKING:  # imported by start_metrics, only when [metrics] listen is set: prometheus_client, http, email
    from nanodrift.service.metrics_server import MetricsServer

#: config (and a running context to keep) -> drivers: ``nanodrift.assembly.build_drivers``, handed in by
#: ``nanodrift run`` so that the service names no plugin
BuildDrivers = Callable[[Config, DriverContext | None], DriverSet]


class Service:
    """The daemon for one cell. ``run()`` returns the exit code."""

    def __init__(
        self,
        config: Config,
        *,
        config_path: str | Path | None = None,
        zenoh_overrides: Mapping[str, Any] | None = None,
        notifier: Notifier | None = None,
        build_drivers: BuildDrivers,
    ) -> None:
        self.build_drivers = build_drivers  # also called by the Reloader
        self.config_path = Path(config_path) if config_path is not None else None
        self.zenoh_overrides = dict(zenoh_overrides or {})
        self.notifier = notifier or Notifier()
        self.log = get_logger("nanodrift.daemon")
        self.health = HealthUnit(config, None, self.log)
        model, problem = load_serving_model(config)  # a model that does not load: served as no_model, with why
        compensator = serving_state(config, model, self.health, model_problem=problem)
        # every output of the cell (one axis: x), by one task; a one-axis cell's log lines keep their shape
        # what each output was last written, kept before every write: the only proof of a read-back at a restart
        records = OutputRecords(state_directory(config.daemon.state_dir), config.cell)
        self.actuation = Actuation(self.log, records=records, position_witness=self._position_reading)
        self.actuation.reached_listeners.append(self._output_reached)
        self.actuation.done_listeners.append(self._publish_done)  # one done per served command
        self.state = CellState(config, compensator, MonotonicClock())  # the drivers' clock once they start
        # [health] record_dir: settled targets to daily CSVs on a thread of its own (read anew after a reload)
        self.recorder = Recorder(lambda: self.state.config.health, self.log)
        self.health.settled_listeners.append(self.recorder.on_settled)
        self.drivers: DriverSet | None = None
        self.pollers: list[GroupPoller] = []
        self.bus: Bus | None = None
        self.stops: StopHandler | None = None  # the ``stop`` key's handler, once the bus is up
        self.ingest = SensorIngest(self.state, self._publish_telemetry, self.log, self.health)
        self.watch = SensorWatch(self.state, self._publish_telemetry, self.log)
        self.reloader = Reloader(self.state, self.config_path, self, self.notifier, self.log,
                                 status_line=self.status_line, table_replaced=self.watch.forget, health=self.health)
        self.latency = AnswerLatency()
        self.metrics: MetricsServer | None = None
        self._stop = asyncio.Event()
        self._tasks: set[asyncio.Task[Any]] = set()

    async def run(self) -> int:
        loop = asyncio.get_running_loop()
        for sig, handler in ((signal.SIGTERM, self._stop.set), (signal.SIGINT, self._stop.set),
                             (signal.SIGHUP, self.request_reload)):
            loop.add_signal_handler(sig, handler)
        self._log_start()
        await self.start_metrics()
        conf = session_config(self.state.config.zenoh, **self.zenoh_overrides)
        try:
            session = zenoh.open(conf)
        except zenoh.ZError as error:
            await self.stop_metrics()
            sentence = describe_zenoh_error(error)
            self.log.error("zenoh_open_failed", error=sentence)
            raise UserError(sentence) from None
        listen = listen_endpoints(conf)
        self.log.info("listening", endpoints=listen, zid=str(session.info.zid()),
                      **({"note": "port 0: zenoh picked a free port; -l tcp/HOST:PORT fixes it"}
                         if any(ep.endswith(":0") for ep in listen) else {}))
        bus = self.bus = Bus(session, self.state.config.cell, self.state.config.zenoh.prefix)
        self.stops = StopHandler(self.actuation, bus, loop, self.log, self.state.config.axis_names)
        try:
            await self.start_drivers(self.build_drivers(self.state.config, None))
        except DriverSetupError as error:
            self.log.error("driver_setup_failed", error=str(error))
            bus.close()
            await self.stop_metrics()
            return 1
        # ready once every device has been read (or has failed) once: at most an open and a read each
        await first_attempts(self.pollers, self.first_attempts_limit_s())
        targets = TargetHandler(self.state, bus, loop, self.actuation, self.log, latency=self.latency)
        with self.state.lock:
            self.state.serving = True
        self.serve(loop, targets, StatusHandler(self.state, bus, self.healthy, self.log, self.actuation, self.health))
        self._tasks.add(self.health.start(bus))  # nanodrift/<cell>/health, cancelled at stop with the others
        line = self.status_line
        supervisor = Supervisor(self.watch, self.notifier, self.log, healthy=self.healthy, status_line=line,
                                refusals_suppressed=targets.take_suppressed,
                                actuator_failures=self.actuation.failures)
        supervising = asyncio.create_task(supervisor.run(), name="supervise")
        self.log.info("serving", cell=self.state.config.cell, keys=f"{bus.keys.prefix}/**", listen=listen,
                      model=self.state.model_id(), sensors=list(self.state.table.entries))
        # what start-up built (imports, the model, the drivers) lives as long as the daemon: out of the
        # collector's full passes, which otherwise scan it all and pause the loop (and the answers waiting
        # on the GIL) for tens of ms (benchmarks/daemon_latency.py's p99). `nanodrift run` froze its imports already
        # (nanodrift.cli), so this pass scans only what was built since: the model, the drivers, the session
        gc.collect()
        gc.freeze()
        self.notifier.ready(line())
        try:
            await self._stop.wait()
        finally:  # whatever ends the wait (a signal, a cancellation), the stage is left safe
            await self._stop_serving(bus, supervising)
        return 0

    async def _stop_serving(self, bus: Bus, supervising: asyncio.Task[None]) -> None:
        """Stop in the order that keeps every promise: targets get ``shutting_down`` until the bus closes,
        the safe ramp runs even if an earlier step fails, and each step runs once."""
        self.notifier.stopping()
        with self.state.lock:
            self.state.serving = False
            self.state.stopping = True  # targets arriving from now on are refused with ``shutting_down``
            counters = self.state.counters.as_dict()
        self.log.info("stopping", counters=counters)
        try:
            supervising.cancel()
            for task in list(self._tasks):
                task.cancel()
        finally:
            try:
                await self.stop_drivers(final=True)  # safe_voltage_v (when finite) before the actuator closes
            finally:
                bus.withdraw()  # clients see the daemon gone
                await asyncio.to_thread(self.recorder.close)  # the rows already queued reach the disk
                bus.close()
                await self.stop_metrics()
                self.log.info("stopped")

    def serve(self, loop: asyncio.AbstractEventLoop, targets: TargetHandler, status: StatusHandler) -> None:
        """Declare the handlers on the bus (a subclass may wrap them: benchmarks/daemon_latency.py)."""
        assert self.bus is not None
        self.bus.serve(loop, targets.on_target, status.on_status, self.stops.on_stop if self.stops else None)

    async def start_metrics(self) -> None:
        """``[metrics] listen``: Prometheus' ``/metrics`` served from this loop, read at scrape time (a
        change needs a restart)."""
        listen = self.state.config.metrics.listen
        if not listen:
            return
        try:  # here, not at the top: a daemon without metrics never loads prometheus_client (~40 ms of imports)
            from nanodrift.service.metrics_server import MetricsServer
        except ImportError as error:  # a broken install fails here, at start, never once serving
            sentence = (f"[metrics] listen = {listen!r}: cannot serve metrics: {error} "
                        "(prometheus_client is a dependency of nanodrift: reinstall it)")
            self.log.error("metrics_failed", error=sentence)
            raise UserError(sentence) from None
        server = MetricsServer(listen, lambda: status_doc(self.state, self.healthy(), self.actuation, self.health),
                               self.latency)
        try:
            await server.start()
        except UserError as error:
            self.log.error("metrics_failed", error=str(error))
            raise
        self.metrics = server
        self.log.info("metrics_listening", url=server.url)

    async def stop_metrics(self) -> None:
        metrics, self.metrics = self.metrics, None
        if metrics is not None:
            await metrics.stop()

    def request_reload(self) -> None:
        """SIGHUP. The Reloader refuses (logs, counts) every failure it meets; what still escapes it is
        retrieved here and refused the same way, never left as "Task exception was never retrieved"."""

        def done(task: asyncio.Task[bool]) -> None:
            self._tasks.discard(task)
            error = None if task.cancelled() else task.exception()
            if error is not None:
                self.reloader.refuse_internal(error)

        task = asyncio.get_running_loop().create_task(self.reloader.reload(), name="reload")
        self._tasks.add(task)
        task.add_done_callback(done)

    def healthy(self) -> bool:
        """The loop runs (we are in it) and every poller is alive and making progress."""
        return pollers_healthy(self.pollers)

    def status_line(self) -> str:
        return status_line(self.state, self.health)

    def _publish_telemetry(self, role: str, channel: str, payload: bytes) -> None:
        if self.bus is not None:  # none before the session is open
            config = self.state.config
            if role == "position" and not one_axis(config.axis_names):  # each axis' sensor on its own key
                self.bus.publish_telemetry(role, channel, payload, config.sensor_axis(channel))
            else:
                self.bus.publish_telemetry(role, channel, payload)

    # --- the drivers (also called by the Reloader) ------------------------------------------------

    async def start_drivers(self, drivers: DriverSet) -> None:
        self.drivers = drivers
        with self.state.lock:
            self.state.clock = drivers.context.clock
            self.health.label_clock = drivers.context.label_clock
            self.health.awaits_reach = bool(drivers.actuators)
        ingest = self.ingest
        self.pollers = [
            GroupPoller(g, drivers.context.clock, ingest.on_readings, ingest.on_group_failure,
                        ingest.on_group_recovered)
            for g in drivers.groups
        ]
        for poller in self.pollers:  # first: a position sensor's reading may prove where an output is
            poller.start()
        # the outputs open once every device has been read (or has failed) once: a line a sensor and an output
        # share is never opened by both at once, and a position sensor's first reading is there to prove with
        await first_attempts(self.pollers, self.first_attempts_limit_s())
        # no outputs (every axis kind = "zenoh", or no actuator): the published command is the actuation, and
        # the actuation still runs, to say each command is reached as it is published
        await self.actuation.start(drivers.actuators, self.state.config.axis_actuators())

    def first_attempts_limit_s(self) -> float:
        """How long the sensors' first reads are awaited: at most an open and a read each."""
        return min(10.0, 0.5 + 2 * max((p.group.timeout_s for p in self.pollers), default=0.0))

    async def stop_drivers(self, *, final: bool = False) -> None:
        """Stop polling and the actuator; ``final`` (the daemon stops, not a reload): the actuator
        first ramps to ``safe_voltage_v`` when it is finite (even if stopping a poller failed)."""
        try:
            await asyncio.gather(*(p.stop() for p in self.pollers), return_exceptions=True)
            self.pollers = []
        finally:
            await self.actuation.stop(final=final)

    async def _position_reading(self, axis: str) -> tuple[str, float] | str:
        """What may prove a read-back nothing on record confirms: the axis' position sensor and its reading when
        it is ok (fresh, believed), else why not. The outputs open after the sensors' first reads
        (:meth:`start_drivers`); a sensor slower than that proves the read-back at a reopen."""
        sensor = self.state.config.position_sensors().get(axis)
        if sensor is None:
            return f"no position sensor measures axis {axis}"
        with self.state.lock:
            table = self.state.table
            problem = table.problem(sensor.name, self.state.clock.now())
            entry = table.entries.get(sensor.name)
            value = entry.value if entry is not None else None
        if problem is not None or value is None:
            state, reason = problem or ("stale", "no reading yet")
            return f"its position sensor {sensor.name} is {state} ({reason})"
        return sensor.name, value

    def _output_reached(self, goal: Any, _monotonic_s: float) -> None:
        """The output holds a served command: the health unit's settle time starts now (cell clock).

        No state lock: the health unit's reach queue is only touched on the loop (here and in the sensor
        ingest), and the target path must not wait for a write's bookkeeping."""
        self.health.on_reached(self.state.clock.now(), goal.q_um)  # q per axis: each health unit takes its own

    def _publish_done(self, goal: Goal, state: str, held: dict[str, float | None], error: str | None) -> None:
        """``done`` for a served command (on the loop, or a target's thread for the one it replaced; the publisher
        drops rather than blocks, as the answers')."""
        bus = self.bus
        if bus is None:
            return
        voltage = wire_voltage(held, self.state.config.axis_names)
        try:
            bus.publish_done(encode_done(goal.id, state, time.time(), voltage, error))
        except zenoh.ZError as failure:
            self.log.warning("done_not_sent", id=goal.id, state=state, error=str(failure))

    def _log_start(self) -> None:
        config, comp = self.state.config, self.state.compensator
        model = comp.model
        missing = missing_model_channels(config, model.channels) if model else []
        if not one_axis(config.axis_names):
            self.log.info("axes", axes={a: {"workspace_um": list(c.workspace_um), "kind": c.kind}
                                        for a, c in config.axis_actuators().items()})
        self.log.info("starting", config=config.source, cell=config.cell,
                      model_path=str(config.model.path), model=model.id if model else None,
                      model_problem=comp.model_problem or None, missing_channels=missing or None)


def run_service(config: Config, build_drivers: BuildDrivers, config_path: str | Path | None = None,
                zenoh_overrides: Mapping[str, Any] | None = None) -> int:
    """Run the daemon until SIGTERM/SIGINT; the exit code."""

    async def main() -> int:
        return await Service(config, config_path=config_path, zenoh_overrides=zenoh_overrides,
                             build_drivers=build_drivers).run()

    return asyncio.run(main())
