"""Prometheus metrics for the lab's monitoring (``[metrics] listen``): read from the cell at scrape time.

Nothing is updated on the loop: a custom collector builds the ``status`` document (under the state
lock, as the ``status`` queryable does) when Prometheus scrapes, and turns it into metric families.
Health and actuator state are read from that document when it carries them, so this module does not
depend on how they are measured. The one thing measured on the target path is the answer latency:
:class:`AnswerLatency` counts it into fixed buckets (a bisect and two additions under an
uncontended lock), and the collector exposes the counts as a histogram.

The HTTP endpoint that serves them is :mod:`nanodrift.service.metrics_server`'s; :class:`AnswerLatency` is
:mod:`nanodrift.service.latency`'s (why: there).

Names follow Prometheus' conventions: ``nanodrift_`` prefix, base units (seconds, metres), counters
ending ``_total``; every series carries the ``cell`` label.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterator
from typing import Any

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.registry import Collector

from nanodrift.model.provenance import version
from nanodrift.service.latency import LATENCY_BUCKETS_S as LATENCY_BUCKETS_S  # re-exported: the metrics' names
from nanodrift.service.latency import AnswerLatency as AnswerLatency

#: every value of ``nanodrift_sensor_state`` / ``nanodrift_actuator_state``'s ``state`` label (a state set)
SENSOR_STATES = ("ok", "stale", "fault")
ACTUATOR_STATES = ("ok", "fault", "closed")
#: every value of ``nanodrift_health_state``'s ``state`` label (the health document's states)
HEALTH_STATES = ("unknown", "ok", "degraded")
#: every kind of refusal the daemon produces (``Refusal(kind, ...)``; ``stale``/``fault`` are a channel's
#: state): ``nanodrift_errors_total`` has a series from 0 for each, so ``rate()`` works from the first error
ERROR_KINDS = ("out_of_workspace", "no_model", "missing_channel", "stale", "fault", "voltage_limit",
               "actuator_fault", "bad_payload", "shutting_down", "internal")


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


class CellCollector(Collector):
    """Metric families from one status document per scrape (``status_doc`` takes the state lock)."""

    def __init__(self, status_doc: Callable[[], dict[str, Any]], latency: AnswerLatency) -> None:
        self.status_doc = status_doc
        self.latency = latency
        self.version = version()

    def collect(self) -> Iterator[Any]:
        doc = self.status_doc()
        cell = str(doc.get("cell", ""))
        yield from self._counters(doc, cell)
        yield self._latency(cell)
        yield from self._sensors(doc, cell)
        yield from self._cell(doc, cell)
        yield from self._health(doc, cell)
        yield from self._actuator(doc, cell)
        build = GaugeMetricFamily("nanodrift_build_info", "1, labelled with the daemon's version",
                                  labels=["cell", "version"])
        build.add_metric([cell, self.version], 1.0)
        yield build

    def _counters(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        counters = doc.get("counters") or {}
        for name, key, text in (
            ("nanodrift_targets_total", "targets", "targets received (each gets one command or one error)"),
            ("nanodrift_commands_total", "commands", "commands computed and published"),
            ("nanodrift_reloads_total", "reloads", "configuration reloads applied"),
            ("nanodrift_reload_failures_total", "reload_failures", "configuration reloads refused"),
        ):
            family = CounterMetricFamily(name, text, labels=["cell"])
            family.add_metric([cell], float(counters.get(key) or 0))
            yield family
        errors = CounterMetricFamily("nanodrift_errors_total", "targets refused, by error kind",
                                     labels=["cell", "kind"])
        counts = {str(kind): count for kind, count in (counters.get("errors") or {}).items()}
        for kind in dict.fromkeys((*ERROR_KINDS, *sorted(counts))):  # the known kinds first, from 0
            errors.add_metric([cell, kind], float(counts.get(kind) or 0))
        yield errors

    def _latency(self, cell: str) -> HistogramMetricFamily:
        cumulative, total = self.latency.snapshot()
        bounds = [repr(b) for b in LATENCY_BUCKETS_S] + ["+Inf"]
        family = HistogramMetricFamily("nanodrift_answer_latency_seconds",
                                       "from a target's arrival to its answer published", labels=["cell"])
        family.add_metric([cell], list(zip(bounds, [float(c) for c in cumulative], strict=True)), total)
        return family

    def _sensors(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        """Readings in base units by role (the model reads temperatures in °C, positions in µm), the
        age, and the state as a state set (one series per state, 1 for the current one)."""
        temperature = GaugeMetricFamily("nanodrift_temperature_celsius", "each temperature channel's last reading",
                                        labels=["cell", "channel"])
        axes: dict[str, str] | None = None  # a multi-axis cell: each position channel's axis as a label
        if isinstance(doc.get("axes"), dict):
            axes = {str(each["position_sensor"]): axis for axis, each in doc["axes"].items()
                    if isinstance(each, dict) and each.get("position_sensor")}
        position = GaugeMetricFamily("nanodrift_position_meters", "each position channel's last reading",
                                     labels=["cell", "channel", "axis"] if axes is not None else ["cell", "channel"])
        age = GaugeMetricFamily("nanodrift_sensor_age_seconds", "age of each channel's last reading",
                                labels=["cell", "channel"])
        states = GaugeMetricFamily("nanodrift_sensor_state", "1 for the state each channel is in (ok, stale, fault)",
                                   labels=["cell", "channel", "state"])
        for name, sensor in sorted((doc.get("sensors") or {}).items()):
            if not isinstance(sensor, dict):
                continue
            reading = _number(sensor.get("value"))
            if reading is not None and sensor.get("role") == "temperature":
                temperature.add_metric([cell, name], reading)
            elif reading is not None and sensor.get("role") == "position":
                position.add_metric([cell, name] if axes is None else [cell, name, axes.get(name, "x")], reading * 1e-6)
            seconds = _number(sensor.get("age_s"))
            if seconds is not None:
                age.add_metric([cell, name], seconds)
            for state in SENSOR_STATES:
                states.add_metric([cell, name, state], 1.0 if sensor.get("state") == state else 0.0)
        yield from (temperature, position, age, states)

    def _cell(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        healthy = GaugeMetricFamily("nanodrift_healthy", "1 while every sensor poller makes progress",
                                    labels=["cell"])
        healthy.add_metric([cell], 1.0 if doc.get("healthy") else 0.0)
        uptime = GaugeMetricFamily("nanodrift_uptime_seconds", "since the daemon started", labels=["cell"])
        uptime.add_metric([cell], _number(doc.get("uptime_s")) or 0.0)
        model = GaugeMetricFamily("nanodrift_model_info", "1, labelled with the model id being served (none: none)",
                                  labels=["cell", "model"])
        info = doc.get("model")
        model.add_metric([cell, str(info.get("id")) if isinstance(info, dict) else "none"], 1.0)
        extrapolating = GaugeMetricFamily("nanodrift_extrapolating",
                                          "1 while a channel (or x) is outside the model's training range",
                                          labels=["cell"])
        extrapolating.add_metric([cell], 1.0 if doc.get("extrapolating") else 0.0)
        yield from (healthy, uptime, model, extrapolating)

    def _health(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        """The health document's families; a multi-axis cell's (every axis' document under ``"axes"``) with an
        ``axis`` label. A one-axis cell leaves out a gauge it has no value for."""
        health = doc.get("health")
        if not isinstance(health, dict):
            return
        multi = isinstance(health.get("axes"), dict)
        docs = {a: h for a, h in health["axes"].items() if isinstance(h, dict)} if multi else {"": health}
        labels = ["cell", "axis"] if multi else ["cell"]
        gauges = [(GaugeMetricFamily(name, text, labels=labels), key, scale) for name, key, scale, text in (
            ("nanodrift_health_residual_rms_meters", "residual_rms_nm", 1e-9, "RMS of the settled residuals"),
            ("nanodrift_health_residual_mean_meters", "residual_mean_nm", 1e-9, "mean of the settled residuals"),
            ("nanodrift_health_correction_meters", "correction_um", 1e-6, "the adaptive correction applied"),
            ("nanodrift_health_residuals", "n", 1.0, "settled residuals in the rolling statistics"))]
        state = GaugeMetricFamily("nanodrift_health_state",
                                  "1 for the health state the daemon is in (unknown, ok, degraded)",
                                  labels=[*labels, "state"])
        #: the health document's counts, exported as counters (``_total``)
        counters = [(CounterMetricFamily(name, text, labels=labels), key) for name, key, text in (
            ("nanodrift_health_holds_unrecorded", "holds_unrecorded", "held targets with no position reading "
             "inside window_s (the sensor polls slower): no residual, no record row"),
            ("nanodrift_health_residuals_rejected", "residuals_rejected",
             "settled residuals refused as too large to be a reading (their square is not finite)"))]
        for axis, each in docs.items():
            where = [cell, axis] if multi else [cell]
            for family, key, scale in gauges:
                number = _number(each.get(key))
                if number is not None:
                    family.add_metric(where, number * scale)
            if each.get("state") is not None:
                current = str(each["state"])
                for name in dict.fromkeys((*HEALTH_STATES, current)):
                    state.add_metric([*where, name], 1.0 if name == current else 0.0)
            for counter, key in counters:
                number = _number(each.get(key))
                if number is not None:
                    counter.add_metric(where, number)
        if multi:
            yield from (*(g for g, _, _ in gauges), state, *(c for c, _ in counters))
        else:
            yield from (c for c, _ in counters)
            yield from (f for f in (*(g for g, _, _ in gauges), state) if f.samples)

    def _actuator(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        """The actuator's state; a multi-axis cell's outputs with an ``axis`` label, and each output's voltage."""
        axes = doc.get("axes")
        multi = isinstance(axes, dict)
        actuators = ({axis: each.get("actuator") if isinstance(each, dict) else None for axis, each in axes.items()}
                     if isinstance(axes, dict) else {"": doc.get("actuator")})
        labels = ["cell", "axis"] if multi else ["cell"]
        family = GaugeMetricFamily("nanodrift_actuator_state", "1 for the state the actuator is in (ok, fault, closed)",
                                   labels=[*labels, "kind", "state"])
        ok = GaugeMetricFamily("nanodrift_actuator_ok", "1 unless the actuator is in fault", labels=[*labels, "kind"])
        volts = GaugeMetricFamily("nanodrift_actuator_voltage_volts", "the last voltage written to each axis' output",
                                  labels=["cell", "axis"])
        for axis, actuator in actuators.items():
            if not isinstance(actuator, dict) or actuator.get("state") is None:
                continue
            where = [cell, axis] if multi else [cell]
            kind, current = str(actuator.get("kind", "")), str(actuator["state"])
            for state in dict.fromkeys((*ACTUATOR_STATES, current)):
                family.add_metric([*where, kind, state], 1.0 if state == current else 0.0)
            ok.add_metric([*where, kind], 0.0 if current == "fault" else 1.0)
            last = _number(actuator.get("last_voltage_v"))
            if multi and last is not None:
                volts.add_metric(where, last)
        if multi:
            yield from (family, ok, volts)
        elif family.samples:
            yield from (family, ok)
