"""The daemon's health unit: is the served model still right, and (``[adapt] mode = "bias"``) its correction.

The pure pieces are ``nanodrift.calibration.residuals``'s (the same classes ``validate --adapt`` runs):
served commands and position readings go through :class:`SettleTracker` into :class:`HealthMonitor`
(rolling statistics, state, advice with :class:`RangeWatch`'s "since when outside the training
range") and, with adaptation on, :class:`BiasTracker`, whose correction the compensator adds to every
later command.

Threads. The target path (Zenoh's threads, under ``state.lock``) only appends ``(cell time, command)``
to :attr:`HealthUnit.served`, a bounded deque the compensator holds: the answer never waits for the
monitor. Everything else runs on the asyncio loop: the sensor ingest feeds position and temperature
readings under ``state.lock`` (a few float operations; the queued commands are taken in time order
before each reading), and :meth:`HealthUnit.flush`, outside the lock, logs and publishes a change
of state. ``status`` (and the metrics scrape) read :meth:`HealthUnit.document` under ``state.lock``.

Only fresh ``ok`` readings of the ``role = "position"`` sensor count: a faulted reading (the sensor
table's judgement too: out of range, non-finite, future-stamped), a frozen one, one older than the
sensor's ``max_age_s``, or a silence longer than ``max_age_s`` inside an averaging window voids that
window, so an interferometer the daemon does not believe never feeds the monitor or the tracker, and
the advice names it (:attr:`HealthUnit.position_problem`) instead of blaming the cell. A repeated
sample (same time stamp) is not news and is skipped.

Time: the settle windows run on the cell clock (the drivers' monotonic clock, like the readings and the
served commands), so a step of the system clock neither stalls nor skews them; the wall clock only
labels what is handed to the recorder (``t_s``, the file's day), with every polled temperature channel
over the window (:class:`nanodrift.service.recorder.PolledChannels`).

``nanodrift/<cell>/health`` is published at once when the state changes and every
:data:`PUBLISH_INTERVAL_S` of wall time besides: it is read by people and dashboards, who live in
wall time; on the cell clock a simulated cell at ``speed = 100`` would publish it 20 times a second.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections import deque
from collections.abc import Callable, Mapping
from typing import Any

import zenoh

from nanodrift.bus.protocol import Command, dumps
from nanodrift.bus.session import Bus
from nanodrift.calibration.residuals import BiasTracker, HealthMonitor, RangeWatch, Settled, SettleTracker
from nanodrift.config import Config
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Model
from nanodrift.service.cell_compensator import CellCompensator
from nanodrift.service.compensator import Compensator
from nanodrift.service.recorder import Polled, PolledChannels

#: the health document is published this often (wall clock, s) besides at every change of state
PUBLISH_INTERVAL_S = 5.0
#: commands waiting for the next position reading; a hold needs only the newest, so a flood loses nothing
SERVED_QUEUE = 1024
#: temperature readings are kept this long beyond a window and the sensors' max ages (a late closing reading)
POLLED_MARGIN_S = 10.0


class HealthUnit:
    """Served commands and position readings in; the ``health`` document, log events and the correction out."""

    def __init__(self, config: Config, model: Model | CellModel | None, log: Any, *, axis: str = "x") -> None:
        self.log = log
        #: the axis this unit watches (a multi-axis cell has one unit per axis: ``nanodrift.service.cell_health``)
        self.axis = axis
        self.served: deque[tuple[float, Command]] = deque(maxlen=SERVED_QUEUE)
        #: called on the loop, outside the state lock, with every settled target, the unix time it settled
        #: at (a label only) and every polled temperature channel over its window (the recorder's
        #: ``on_settled``); a listener must not block
        self.settled_listeners: list[Callable[[Settled, float, Polled], None]] = []
        self._compensator: Compensator | CellCompensator | None = None
        self._publisher: Any = None
        self._fresh: list[tuple[Settled, float, Polled]] = []
        self.polled = PolledChannels({}, 0.0)
        #: the daemon drives the output itself: a hold settles from when the output reached its command
        #: (a slewed ramp takes seconds), told through :meth:`on_reached`; else from the command
        self.awaits_reach = False
        self._reached: deque[tuple[float, float]] = deque(maxlen=SERVED_QUEUE)
        #: why the position sensor's last reading was not believed ("" when it was): the advice names it
        self.position_problem = ""
        #: labels settled rows (unix s): the drivers' ``DriverContext.label_clock`` once they start
        self.label_clock: Callable[[], float] = time.time
        self._configure(config, model)
        self._configure_polled(config)
        self._announced = self.monitor.state

    # --- configuration (under state.lock) ------------------------------------------------------

    def _configure(self, config: Config, model: Model | CellModel | None) -> None:
        health, adapt = config.health, config.adapt
        # a multi-axis cell's health per axis is not built yet: its state stays unknown
        position = None if config.multi_axis else next((s for s in config.sensors if s.role == "position"), None)
        self._settings = _settings(config)
        self.model_id = model.id if model is not None else None
        self.position_channel: str | None = position.name if position is not None else None
        self.position_max_age_s: float = position.max_age_s if position is not None else math.inf
        self.settle = SettleTracker(health.settle_s, health.window_s)
        self.monitor = HealthMonitor(health.history, health.alarm_rms_nm, has_position_sensor=position is not None)
        ranges: dict[str, tuple[float, float]] = {}
        if isinstance(model, Model):
            training = model.training
            position_range = training.x_range if self.axis == "x" else training.position_ranges[self.axis]
            ranges = {self.axis: position_range, **training.channel_ranges}
        self.ranges = RangeWatch(ranges)
        # adaptation per axis is not built yet: a multi-axis cell serves without a correction
        per_axis = config.multi_axis
        self.tracker = BiasTracker(adapt.tau_s, adapt.max_um) if adapt.mode == "bias" and not per_axis else None
        self.served.clear()
        self._reached.clear()
        self._last_position_t: float | None = None

    def attach(self, compensator: Compensator | CellCompensator) -> None:
        """Serve through ``compensator`` (at start and after every reload): it queues its commands
        here (only with a position sensor) and adds the tracker's correction (only with adaptation on)."""
        self._compensator = compensator
        compensator.served = self.served if self.position_channel is not None else None
        compensator.correction_um = self.tracker.correction_um if self.tracker is not None else None
        if not isinstance(compensator, CellCompensator):  # a cell's axes attach through their own views
            compensator.tracker = self.tracker

    def reconfigure(self, config: Config, compensator: Compensator | CellCompensator) -> None:
        """A reload (under state.lock): a new model, new ``[health]`` monitor or ``[adapt]`` settings or
        another position sensor start the monitor and the tracker afresh (residuals of the old model say
        nothing about the new one); otherwise (recording settings included) they carry on through the
        new compensator."""
        model = compensator.model
        model_id = model.id if model is not None else None
        if model_id != self.model_id or _settings(config) != self._settings:
            self._configure(config, model)
        self._configure_polled(config)
        self.attach(compensator)

    def _configure_polled(self, config: Config) -> None:
        """Every configured temperature channel, for the rows of settled targets; kept over a reload
        that polls the same channels (the readings of a window in progress still count)."""
        max_age_s = {s.name: s.max_age_s for s in config.sensors if s.role == "temperature"}
        position_age_s = self.position_max_age_s if math.isfinite(self.position_max_age_s) else 0.0
        keep_s = (config.health.settle_s + config.health.window_s + max(max_age_s.values(), default=0.0)
                  + position_age_s + POLLED_MARGIN_S)
        if max_age_s != self.polled.max_age_s or keep_s != self.polled.keep_s:
            self.polled = PolledChannels(max_age_s, keep_s)

    # --- readings (on the loop, under state.lock) ----------------------------------------------

    def on_temperatures(self, t: float, temps: Mapping[str, float]) -> None:
        """Good temperature readings: since when each channel is outside the training range (advice)."""
        self.ranges.observe(t, temps)

    def on_channel(self, name: str, t: float, value_c: float, ok: bool) -> None:
        """One reading of a temperature channel (ok or not) taken at ``t``: the rows carry every polled channel."""
        self.polled.observe(name, t, value_c, ok)

    def on_position(self, now: float, t: float, value_um: float, ok: bool, problem: str = "",
                    channel: str | None = None) -> None:
        """One reading of the position sensor taken at ``t``; ``ok``: ok and fresh at ``now``; else
        ``problem`` says why not (``stale: value frozen at ...``), for the advice. (``channel``: which
        sensor; a one-axis cell has one position sensor.)"""
        if self.position_channel is None:
            return
        self.position_problem = "" if ok else (problem or "not ok")
        last = self._last_position_t
        if not ok:
            self._feed(now, math.nan, False)
            return
        if last is not None and t <= last:
            return  # the same sample again: no news
        if last is not None and t - last > self.position_max_age_s:
            self._feed(last + self.position_max_age_s, math.nan, False)  # silent meanwhile: it went stale
        self._last_position_t = t
        self._feed(t, value_um, True)

    def on_reached(self, t: float, q_um: Mapping[str, float]) -> None:
        """The outputs reached command ``q_um`` (per axis: this unit's axis is taken) at cell time ``t`` (on
        the loop: the queue is the loop's)."""
        q = q_um.get(self.axis)
        if q is not None:
            self._reached.append((t, q))

    def _feed(self, t: float, value_um: float, ok: bool) -> None:
        served = self.served
        if served and served[0][0] <= t:
            # a window that ended before the next command is complete: close it first (a reading past
            # its end closes it; the value of a reading past the end is never used)
            self._settled(self.settle.position(served[0][0], math.nan, False))
            while served and served[0][0] <= t:  # with no reading between them, only the last can be held
                t_command, command = served.popleft()
            self.settle.commanded(t_command, command.x_um, command.q_um, command.temperatures_c, command.id,
                                  reached=not self.awaits_reach)
            self.ranges.observe(t_command, {self.axis: command.x_um})
        reached = self._reached
        while reached and reached[0][0] <= t:
            self.settle.reached(*reached.popleft())
        self._settled(self.settle.position(t, value_um, ok))

    def _settled(self, settled: Settled | None) -> None:
        if settled is None:
            return
        self.monitor.add(settled)
        if self.tracker is not None:
            correction = self.tracker.update(settled.t, settled.residual_um)
            if self._compensator is not None:
                self._compensator.correction_um = correction
        # the cell clock decided the window; the label clock (the wall clock, or a simulated lab's own
        # clock when it runs faster) only labels the row (t_s, the file's day)
        polled = self.polled.window(settled.t - self.settle.window_s, settled.t)
        self._fresh.append((settled, self.label_clock(), polled))

    # --- what it says ----------------------------------------------------------------------------

    @property
    def state(self) -> str:
        return self.monitor.state

    @property
    def correction_um(self) -> float | None:
        return self.tracker.correction_um if self.tracker is not None else None

    def document(self) -> dict[str, object]:
        """The ``health`` payload (README: health): state, residual statistics, correction, advice."""
        outside = self.ranges.outside()
        problem = self.position_problem
        suspect = f"position sensor {self.position_channel!r} is {problem}" if problem else None
        return self.monitor.document(correction_um=self.correction_um, extrapolating=[o.channel for o in outside],
                                     outside=outside, sensor_problem=suspect)

    def flush(self) -> None:
        """On the loop, outside the state lock: hand on settled targets, log and publish a change of state."""
        if self._fresh:
            fresh, self._fresh = self._fresh, []
            for listener in self.settled_listeners:
                for settled, unix_s, polled in fresh:
                    listener(settled, unix_s, polled)
        state = self.monitor.state
        if state == self._announced:
            return
        previous, self._announced = self._announced, state
        doc = self.document()
        fields = {key: doc[key] for key in ("residual_rms_nm", "residual_mean_nm", "n", "correction_um", "advice")}
        if state == "degraded":
            self.log.warning("health_degraded", was=previous, **fields)
        elif previous == "degraded":
            self.log.info("health_recovered", state=state, **fields)
        self.publish(doc)

    # --- publishing (on the loop) ----------------------------------------------------------------

    def start(self, bus: Bus) -> asyncio.Task[None]:
        """Declare ``health``, publish the first document and then every :data:`PUBLISH_INTERVAL_S`."""
        self._publisher = bus.session.declare_publisher(bus.keys.health)
        self.publish(self.document())
        return asyncio.create_task(self._periodic(), name="health")

    async def _periodic(self) -> None:
        while True:
            await asyncio.sleep(PUBLISH_INTERVAL_S)
            self.flush()
            self.publish(self.document())

    def publish(self, doc: Mapping[str, object]) -> None:
        if self._publisher is None:
            return
        try:
            self._publisher.put(dumps(doc))
        except zenoh.ZError as error:  # the session is closing: the next one will say it again
            self.log.warning("health_publish_failed", error=str(error))


def _settings(config: Config) -> tuple[object, ...]:
    """What the monitor and the tracker are made of (not the recording keys of ``[health]``)."""
    health = config.health
    position = next((s for s in config.sensors if s.role == "position"), None)
    return (health.settle_s, health.window_s, health.history, health.alarm_rms_nm, config.adapt, position)
