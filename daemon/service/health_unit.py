"""The daemon's health unit: is the served model still right on every axis, and (``[adapt] mode = "bias"``)
each axis' correction.

The pure pieces are ``nanodrift.calibration.residuals``'s (the same classes ``validate --adapt`` runs):
per axis with a ``role = "position"`` sensor (``[[sensors]] axis``, x by default), served commands and that
sensor's readings go through :class:`SettleTracker` into :class:`HealthMonitor` (rolling statistics, state,
advice with :class:`RangeWatch`'s "since when outside the training range") and, with adaptation on,
:class:`BiasTracker`, whose correction the compensator adds to that axis' later commands. A one-axis cell
is a cell of one axis, ``x``; only the edges keep its shapes: its ``health`` document is its axis' (a
cell of several: the worst state, with every axis' document under ``"axes"``) and its recorded row has
the one-axis columns (:func:`nanodrift.service.recorder.record_row`, of every watched axis' :class:`Settled`
once each held the same command).

A row is one command the stage held: the unit numbers every command it is handed (:meth:`HealthUnit.served`)
and pairs the axes' settled windows by that number, never by the client's id (absent, or repeated: ``nanodrift
target`` numbers each invocation from 0), so no row mixes one command's x with another's y. A hold that cannot
be recorded because no position reading fell inside its window (a sensor polling slower than ``window_s``)
is counted (``holds_unrecorded`` in the health document, a metric) and logged once per axis with the reason;
a residual too large to be a reading (:func:`nanodrift.calibration.residuals.believable_residual`) is counted
(``residuals_rejected``) and feeds nothing.

Threads. The target path (Zenoh's threads, under ``state.lock``) only appends ``(cell time, command)``
to each watched axis' bounded queue: the answer never waits for the monitor. Everything else runs on
the asyncio loop: the sensor ingest feeds position and temperature readings under ``state.lock`` (a few
float operations; the queued commands are taken in time order before each reading), and
:meth:`HealthUnit.flush`, outside the lock, logs and publishes a change of state. ``status`` (and the
metrics scrape) read :meth:`HealthUnit.document` under ``state.lock``.

Only fresh ``ok`` readings of an axis' position sensor count: a faulted reading (the sensor table's
judgement too: out of range, non-finite, future-stamped), a frozen one, one older than the sensor's
``max_age_s``, or a silence longer than ``max_age_s`` inside an averaging window voids that window, so an
interferometer the daemon does not believe never feeds the monitor or the tracker, and the advice names
it (``position_problem``) instead of blaming the cell. A repeated sample (same time stamp) is not news.

Time: the settle windows run on the cell clock (the drivers' monotonic clock, like the readings and the
served commands), so a step of the system clock neither stalls nor skews them; the wall clock only
labels what is handed to the recorder (``t_s``, the file's day), with every polled temperature channel
over the window (:class:`nanodrift.service.recorder.PolledChannels`).

``<prefix>/<cell>/health`` is published at once when the state changes and every
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

from nanodrift.bus.protocol import dumps
from nanodrift.bus.session import Bus
from nanodrift.calibration.residuals import (
    BiasTracker,
    HealthMonitor,
    RangeWatch,
    Settled,
    SettleTracker,
    believable_residual,
)
from nanodrift.compensation import Command, axis_models, one_axis
from nanodrift.config import Config
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Model
from nanodrift.service.recorder import Polled, PolledChannels

#: the health document is published this often (wall clock, s) besides at every change of state
PUBLISH_INTERVAL_S = 5.0
#: commands waiting for the next position reading; a hold needs only the newest, so a flood loses nothing
SERVED_QUEUE = 1024
#: temperature readings are kept this long beyond a window and the sensors' max ages (a late closing reading)
POLLED_MARGIN_S = 10.0
#: targets held on some axes, waiting for the others (oldest dropped beyond this)
MAX_PENDING_TARGETS = 64
#: a cell's state is its worst axis'
_RANK = {"degraded": 2, "ok": 1, "unknown": 0}


class AxisWatch:
    """One axis' settle windows, statistics, range watch and bias tracker (a reload keeps what did not change)."""

    def __init__(self, axis: str, config: Config, model: Model | None, log: Any) -> None:
        health, adapt = config.health, config.adapt
        position = config.position_sensors().get(axis)
        self.axis = axis
        self.log = log
        #: what it is made of: a change (a new model of this axis, other settings or sensor) starts it afresh
        self.key = (model.id if model is not None else None, health.settle_s, health.window_s, health.history,
                    health.alarm_rms_nm, adapt, position)
        self.position_channel: str | None = position.name if position is not None else None
        self.position_max_age_s: float = position.max_age_s if position is not None else math.inf
        self.position_interval_s: float = position.interval_s if position is not None else math.nan
        self.window_s = health.window_s
        self.settle = SettleTracker(health.settle_s, health.window_s)
        self.monitor = HealthMonitor(health.history, health.alarm_rms_nm, has_position_sensor=position is not None)
        ranges: dict[str, tuple[float, float]] = {}
        if model is not None:
            training = model.training
            position_range = training.x_range if axis == "x" else training.position_ranges[axis]
            ranges = {axis: position_range, **training.channel_ranges}
        self.ranges = RangeWatch(ranges)
        self.tracker = BiasTracker(adapt.tau_s, adapt.max_um) if adapt.mode == "bias" else None
        self.served: deque[tuple[float, int, Command]] = deque(maxlen=SERVED_QUEUE)
        self.reached: deque[tuple[float, float]] = deque(maxlen=SERVED_QUEUE)
        self.last_position_t: float | None = None
        #: cell time between the last two new readings: what the poll really achieves (a sped-up simulated
        #: clock polls far slower, in cell time, than ``interval_s``)
        self.position_gap_s = math.nan
        #: why the position sensor's last reading was not believed ("" when it was): the advice names it
        self.position_problem = ""
        self.announced = self.monitor.state
        self.unfilled_logged = False

    @property
    def holds_unrecorded(self) -> int:
        """Holds that ended with no position reading inside their window: no residual, no row."""
        return self.settle.unfilled_windows

    def log_unfilled_once(self) -> None:
        """The first hold this axis could not record: say why, once (the count goes on in the document)."""
        if self.unfilled_logged or self.holds_unrecorded == 0:
            return
        self.unfilled_logged = True
        gap_s = self.position_gap_s if math.isfinite(self.position_gap_s) else None
        seen = f", the last readings {gap_s:.3g} s apart on the cell's clock" if gap_s is not None else ""
        self.log.warning(
            "hold_unrecorded", position_sensor=self.position_channel, interval_s=self.position_interval_s,
            reading_gap_s=gap_s, window_s=self.window_s,
            reason=(f"no reading of position sensor {self.position_channel!r} fell inside the {self.window_s:g} s "
                    f"averaging window after the stage held the target: it polls slower than [health] window_s "
                    f"(interval_s = {self.position_interval_s:g} s{seen}); the held target gets no residual and no "
                    "record row"),
            fix="set [health] window_s above the position sensor's interval_s, or poll it faster")

    def document(self) -> dict[str, object]:
        """This axis' ``health`` document (README: health): state, residual statistics, correction, advice."""
        outside = self.ranges.outside()
        problem = self.position_problem
        suspect = f"position sensor {self.position_channel!r} is {problem}" if problem else None
        correction = self.tracker.correction_um if self.tracker is not None else None
        doc = self.monitor.document(correction_um=correction, extrapolating=[o.channel for o in outside],
                                    outside=outside, sensor_problem=suspect)
        return {**doc, "holds_unrecorded": self.holds_unrecorded, "residuals_rejected": self.monitor.rejected}

    def log_change(self) -> None:
        state = self.monitor.state
        if state == self.announced:
            return
        previous, self.announced = self.announced, state
        doc = self.document()
        fields = {key: doc[key] for key in ("residual_rms_nm", "residual_mean_nm", "n", "correction_um", "advice")}
        if state == "degraded":
            self.log.warning("health_degraded", was=previous, **fields)
        elif previous == "degraded":
            self.log.info("health_recovered", state=state, **fields)


class HealthUnit:
    """Served commands and position readings in; the ``health`` document, log events and corrections out."""

    def __init__(self, config: Config, model: Model | CellModel | None, log: Any) -> None:
        self.log = log
        self.axes = config.axis_names  # a one-axis cell's document and recorded rows keep its own shapes
        #: called on the loop, outside the state lock, with every settled target (axis -> :class:`Settled`), the
        #: unix time it settled at (a label only) and every
        #: polled temperature channel over its window (the recorder's ``on_settled``); must not block
        self.settled_listeners: list[Callable[[Any, float, Polled], None]] = []
        #: the daemon drives the outputs itself: a hold settles from when the outputs reached its command
        #: (a slewed ramp takes seconds), told through :meth:`on_reached`; else from the command
        self.awaits_reach = False
        #: labels settled rows (unix s): the drivers' ``DriverContext.label_clock`` once they start
        self.label_clock: Callable[[], float] = time.time
        self.watches: dict[str, AxisWatch] = {}
        self.polled = PolledChannels({}, 0.0)
        self._corrections: dict[str, float] | None = None
        self._fresh: list[tuple[str, Settled, float, Polled]] = []
        #: command sequence number -> the axes that settled it so far
        self._pending: dict[int, dict[str, tuple[Settled, float, Polled]]] = {}
        self._sequence = 0  # the number of the last command handed to :meth:`served`
        self._publisher: Any = None
        self.reconfigure(config, model)
        self._announced = self.state

    def reconfigure(self, config: Config, model: Model | CellModel | None) -> None:
        """At start and at a reload (under state.lock): an axis with a new model, new ``[health]`` monitor or
        ``[adapt]`` settings or another position sensor starts its monitor and tracker afresh (residuals of
        the old model say nothing about the new one); the others carry on (recording settings included)."""
        models = axis_models(model)
        for axis in self.axes:
            log = self.log if one_axis(self.axes) else self.log.bind(axis=axis)
            watch = AxisWatch(axis, config, models.get(axis), log)
            old = self.watches.get(axis)
            if old is None or old.key != watch.key:
                watch.announced = old.announced if old is not None else watch.announced  # a reset is logged
                self.watches[axis] = watch
        trackers = {a: w.tracker for a, w in self.watches.items() if w.tracker is not None}
        self._corrections = {a: t.correction_um for a, t in trackers.items()} if trackers else None
        # every configured temperature channel, for the rows of settled targets; kept over a reload that polls
        # the same channels (the readings of a window in progress still count)
        max_age_s = {s.name: s.max_age_s for s in config.sensors if s.role == "temperature"}
        position_age_s = max((w.position_max_age_s for w in self.watches.values()
                              if math.isfinite(w.position_max_age_s)), default=0.0)
        keep_s = (config.health.settle_s + config.health.window_s + max(max_age_s.values(), default=0.0)
                  + position_age_s + POLLED_MARGIN_S)
        if max_age_s != self.polled.max_age_s or keep_s != self.polled.keep_s:
            self.polled = PolledChannels(max_age_s, keep_s)

    # --- the compensator's hook, its Monitor: an argument it is built with (Zenoh's threads, under state.lock)

    def correction_um(self) -> Mapping[str, float] | None:
        """Each axis' bias correction (None: adaptation off)."""
        return self._corrections

    def sigma_adapted_um(self, sigma_um: Mapping[str, float],
                         wander_um: Mapping[str, float]) -> Mapping[str, float] | None:
        """The σ each corrected axis' command keeps (:meth:`BiasTracker.sigma_um`); None: adaptation off."""
        if self._corrections is None:  # no tracker: on every target, so answered before any comprehension
            return None
        return {a: w.tracker.sigma_um(sigma_um[a], wander_um.get(a, 0.0))
                for a, w in self.watches.items() if w.tracker is not None}

    def served(self, now: float, command: Command) -> None:
        """A command went out at cell time ``now``: numbered, and queued for each axis with a position sensor."""
        self._sequence += 1
        for watch in self.watches.values():
            if watch.position_channel is not None:
                watch.served.append((now, self._sequence, command))

    # --- readings (on the loop, under state.lock) ----------------------------------------------

    def on_temperatures(self, t: float, temps: Mapping[str, float]) -> None:
        """Good temperature readings: since when each channel is outside the training range (advice)."""
        for watch in self.watches.values():
            watch.ranges.observe(t, temps)

    def on_channel(self, name: str, t: float, value_c: float, ok: bool) -> None:
        """One reading of a temperature channel (ok or not) taken at ``t``: the rows carry every polled channel."""
        self.polled.observe(name, t, value_c, ok)

    def on_position(self, now: float, t: float, value_um: float, ok: bool, problem: str = "",
                    channel: str | None = None) -> None:
        """One reading of position sensor ``channel`` taken at ``t``; ``ok``: ok and fresh at ``now``; else
        ``problem`` says why not (``stale: value frozen at ...``), for the advice. Other channels: ignored."""
        for watch in self.watches.values():
            if watch.position_channel is None or watch.position_channel != channel:
                continue
            watch.position_problem = "" if ok else (problem or "not ok")
            last = watch.last_position_t
            if not ok:
                self._feed(watch, now, math.nan, False)
            elif last is None or t > last:  # the same sample again is no news
                if last is not None and t - last > watch.position_max_age_s:  # silent meanwhile: it went stale
                    self._feed(watch, last + watch.position_max_age_s, math.nan, False)
                watch.position_gap_s = t - last if last is not None else math.nan
                watch.last_position_t = t
                self._feed(watch, t, value_um, True)

    def on_reached(self, t: float, q_um: Mapping[str, float]) -> None:
        """The outputs reached command ``q_um`` (per axis) at cell time ``t`` (on the loop: the queues are its)."""
        for axis, watch in self.watches.items():
            if axis in q_um:
                watch.reached.append((t, q_um[axis]))

    def _feed(self, watch: AxisWatch, t: float, value_um: float, ok: bool) -> None:
        served, axis = watch.served, watch.axis
        if served and served[0][0] <= t:
            # a window that ended before the next command is complete: close it first (a reading past
            # its end closes it; the value of a reading past the end is never used)
            self._settled(watch, watch.settle.position(served[0][0], math.nan, False))
            while served and served[0][0] <= t:  # with no reading between them, only the last can be held
                t_command, sequence, command = served.popleft()
            x_um = command.positions_um[axis]
            watch.settle.commanded(t_command, x_um, command.q_um[axis], command.temperatures_c, sequence,
                                   reached=not self.awaits_reach)
            watch.ranges.observe(t_command, {axis: x_um})
        reached = watch.reached
        while reached and reached[0][0] <= t:
            watch.settle.reached(*reached.popleft())
        self._settled(watch, watch.settle.position(t, value_um, ok))

    def _settled(self, watch: AxisWatch, settled: Settled | None) -> None:
        if settled is None:
            return
        watch.monitor.add(settled)  # counts an unbelievable residual as rejected
        if not believable_residual(settled.residual_um * 1e3):
            return  # a broken reading: no correction, no row
        if watch.tracker is not None and self._corrections is not None:
            self._corrections[watch.axis] = watch.tracker.update(settled.t, settled.residual_um)
        # the cell clock decided the window; the label clock (the wall clock, or a simulated lab's own
        # clock when it runs faster) only labels the row (t_s, the file's day)
        polled = self.polled.window(settled.t - watch.settle.window_s, settled.t)
        self._fresh.append((watch.axis, settled, self.label_clock(), polled))

    def _row(self, axis: str, settled: Settled, unix_s: float,
             polled: Polled) -> tuple[dict[str, Settled], float, Polled] | None:
        """The recorded row of an axis' settled command, once every watched axis held that same command
        (paired by the daemon's sequence number; labelled when the last one settled)."""
        watched = [a for a, w in self.watches.items() if w.position_channel is not None]
        assert settled.sequence is not None  # every command the unit is handed is numbered
        key = settled.sequence
        axes = self._pending.setdefault(key, {})
        axes[axis] = (settled, unix_s, polled)
        if len(self._pending) > MAX_PENDING_TARGETS:  # an axis that never settles must not grow this
            self._pending.pop(next(iter(self._pending)))
        if not all(a in axes for a in watched):
            return None
        del self._pending[key]
        last = max(watched, key=lambda a: axes[a][1])
        valid = all(axes[a][2].valid for a in watched)
        return {a: axes[a][0] for a in watched}, axes[last][1], Polled(axes[last][2].values_c, valid)

    # --- what it says ----------------------------------------------------------------------------

    @property
    def state(self) -> str:
        return max((w.monitor.state for w in self.watches.values()), key=lambda s: _RANK.get(s, 0))

    def document(self) -> dict[str, object]:
        """The ``health`` payload: a one-axis cell's is its axis' document; a cell of several's the worst
        state, every axis' correction and every axis' document under ``"axes"``."""
        if one_axis(self.axes):
            return self.watches["x"].document()
        corrections = {a: w.tracker.correction_um for a, w in self.watches.items() if w.tracker is not None}
        return {"state": self.state, "correction_um": corrections or None,
                "holds_unrecorded": sum(w.holds_unrecorded for w in self.watches.values()),
                "residuals_rejected": sum(w.monitor.rejected for w in self.watches.values()),
                "axes": {axis: watch.document() for axis, watch in self.watches.items()}}

    def flush(self) -> None:
        """On the loop, outside the state lock: hand on settled targets, log and publish a change of state."""
        if self._fresh:
            fresh, self._fresh = self._fresh, []
            rows = [row for item in fresh if (row := self._row(*item)) is not None]
            for listener in self.settled_listeners:
                for row in rows:
                    listener(*row)
        for watch in self.watches.values():
            watch.log_change()  # each axis' own lines (with its axis in a cell of several)
            watch.log_unfilled_once()
        state = self.state
        if state != self._announced:
            self._announced = state
            self.publish(self.document())

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
