"""Prometheus metrics for the lab's monitoring (``[metrics] listen``): read from the cell at scrape time.

Nothing is updated on the loop: a custom collector builds the ``status`` document (under the state
lock, as the ``status`` queryable does) when Prometheus scrapes, and turns it into metric families.
Health and actuator state are read from that document when it carries them, so this module does not
depend on how they are measured. The one thing measured on the target path is the answer latency:
:class:`AnswerLatency` counts it into fixed buckets (a bisect and two additions under an
uncontended lock), and the collector exposes the counts as a histogram.

The HTTP endpoint that serves them is :mod:`nanodrift.service.metrics_server`'s. :class:`AnswerLatency` lives in
:mod:`nanodrift.service.latency` (imported here too): the target path counts latencies whether or not metrics are
served, and a daemon with ``[metrics] listen = ""`` never imports prometheus_client (nor this module).

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


#: the health document's counts, exported as counters (``_total``): (family name, document key, help)
HEALTH_COUNTERS = (
    ("nanodrift_health_holds_unrecorded", "holds_unrecorded",
     "held targets with no position reading inside window_s (the sensor polls slower): no residual, no record row"),
    ("nanodrift_health_residuals_rejected", "residuals_rejected",
     "settled residuals refused as too large to be a reading (their square is not finite)"),
)


def _health_counters(docs: dict[str, dict[str, Any]], cell: str) -> Iterator[Any]:
    """:data:`HEALTH_COUNTERS` of each axis' health document (``{"": doc}``: a one-axis cell, no axis label)."""
    labelled = "" not in docs
    for name, key, text in HEALTH_COUNTERS:
        family = CounterMetricFamily(name, text, labels=["cell", "axis"] if labelled else ["cell"])
        for axis, health in docs.items():
            number = _number(health.get(key))
            if number is not None:
                family.add_metric([cell, axis] if labelled else [cell], number)
        yield family


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
        axes = _axes_of_positions(doc)  # a multi-axis cell: each position channel's axis as a label
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
        health = doc.get("health")
        if not isinstance(health, dict):
            return
        if isinstance(health.get("axes"), dict):
            yield from self._axis_health(health["axes"], cell)
            yield from _health_counters({axis: h for axis, h in health["axes"].items() if isinstance(h, dict)}, cell)
            return
        yield from _health_counters({"": health}, cell)
        for name, key, scale, text in (
            ("nanodrift_health_residual_rms_meters", "residual_rms_nm", 1e-9, "RMS of the settled residuals"),
            ("nanodrift_health_residual_mean_meters", "residual_mean_nm", 1e-9, "mean of the settled residuals"),
            ("nanodrift_health_correction_meters", "correction_um", 1e-6, "the adaptive correction applied"),
        ):
            number = _number(health.get(key))
            if number is not None:
                family = GaugeMetricFamily(name, text, labels=["cell"])
                family.add_metric([cell], number * scale)
                yield family
        count = _number(health.get("n"))
        if count is not None:
            residuals = GaugeMetricFamily("nanodrift_health_residuals", "settled residuals in the rolling statistics",
                                          labels=["cell"])
            residuals.add_metric([cell], count)
            yield residuals
        if health.get("state") is not None:
            current = str(health["state"])
            state = GaugeMetricFamily("nanodrift_health_state",
                                      "1 for the health state the daemon is in (unknown, ok, degraded)",
                                      labels=["cell", "state"])
            for name in dict.fromkeys((*HEALTH_STATES, current)):
                state.add_metric([cell, name], 1.0 if name == current else 0.0)
            yield state

    def _actuator(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        if isinstance(doc.get("axes"), dict):
            yield from self._axis_actuators(doc["axes"], cell)
            return
        actuator = doc.get("actuator")
        if not isinstance(actuator, dict) or actuator.get("state") is None:
            return
        kind, current = str(actuator.get("kind", "")), str(actuator["state"])
        family = GaugeMetricFamily("nanodrift_actuator_state", "1 for the state the actuator is in (ok, fault, closed)",
                                   labels=["cell", "kind", "state"])
        for state in dict.fromkeys((*ACTUATOR_STATES, current)):
            family.add_metric([cell, kind, state], 1.0 if state == current else 0.0)
        ok = GaugeMetricFamily("nanodrift_actuator_ok", "1 unless the actuator is in fault", labels=["cell", "kind"])
        ok.add_metric([cell, kind], 0.0 if current == "fault" else 1.0)
        yield from (family, ok)

    def _axis_health(self, axes: dict[str, Any], cell: str) -> Iterator[Any]:
        """A multi-axis cell's health: the one-axis families with an ``axis`` label."""
        families = {key: GaugeMetricFamily(name, text, labels=["cell", "axis"]) for name, key, text in (
            ("nanodrift_health_residual_rms_meters", "residual_rms_nm", "RMS of the settled residuals"),
            ("nanodrift_health_residual_mean_meters", "residual_mean_nm", "mean of the settled residuals"),
            ("nanodrift_health_correction_meters", "correction_um", "the adaptive correction applied"),
            ("nanodrift_health_residuals", "n", "settled residuals in the rolling statistics"))}
        scale = {"residual_rms_nm": 1e-9, "residual_mean_nm": 1e-9, "correction_um": 1e-6, "n": 1.0}
        state = GaugeMetricFamily("nanodrift_health_state",
                                  "1 for the health state the daemon is in (unknown, ok, degraded)",
                                  labels=["cell", "axis", "state"])
        for axis, health in axes.items():
            if not isinstance(health, dict):
                continue
            for key, family in families.items():
                number = _number(health.get(key))
                if number is not None:
                    family.add_metric([cell, axis], number * scale[key])
            if health.get("state") is not None:
                current = str(health["state"])
                for name in dict.fromkeys((*HEALTH_STATES, current)):
                    state.add_metric([cell, axis, name], 1.0 if name == current else 0.0)
        yield from (*families.values(), state)

    def _axis_actuators(self, axes: dict[str, Any], cell: str) -> Iterator[Any]:
        """A multi-axis cell's outputs: the one-axis families with an ``axis`` label, and each output's voltage."""
        family = GaugeMetricFamily("nanodrift_actuator_state", "1 for the state the actuator is in (ok, fault, closed)",
                                   labels=["cell", "axis", "kind", "state"])
        ok = GaugeMetricFamily("nanodrift_actuator_ok", "1 unless the actuator is in fault",
                               labels=["cell", "axis", "kind"])
        volts = GaugeMetricFamily("nanodrift_actuator_voltage_volts", "the last voltage written to each axis' output",
                                  labels=["cell", "axis"])
        for axis, each in axes.items():
            actuator = each.get("actuator") if isinstance(each, dict) else None
            if not isinstance(actuator, dict) or actuator.get("state") is None:
                continue
            kind, current = str(actuator.get("kind", "")), str(actuator["state"])
            for state in dict.fromkeys((*ACTUATOR_STATES, current)):
                family.add_metric([cell, axis, kind, state], 1.0 if state == current else 0.0)
            ok.add_metric([cell, axis, kind], 0.0 if current == "fault" else 1.0)
            last = _number(actuator.get("last_voltage_v"))
            if last is not None:
                volts.add_metric([cell, axis], last)
        yield from (family, ok, volts)


def _axes_of_positions(doc: dict[str, Any]) -> dict[str, str] | None:
    """position channel -> its axis in a multi-axis cell's status (None: a one-axis cell)."""
    axes = doc.get("axes")
    if not isinstance(axes, dict):
        return None
    return {str(each["position_sensor"]): axis for axis, each in axes.items()
            if isinstance(each, dict) and each.get("position_sensor")}
