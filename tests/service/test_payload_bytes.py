"""The service's status and telemetry payloads, pinned byte for byte (a public contract, README).

Each expected value below was produced by the code before the service was split into a package
(commit c198473); a refactoring that changes a single byte of a status or a telemetry payload fails here.
Fields are only ever appended (issue 26 appended the health document's ``holds_unrecorded`` and
``residuals_rejected``).
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import write_test_model

from nanodrift.assembly import build_drivers
from nanodrift.bus.protocol import dumps
from nanodrift.config import Config, parse_config
from nanodrift.drivers.base import MonotonicClock, Reading, SensorConfig, SensorGroup
from nanodrift.service import Service
from nanodrift.service.status import status_doc


class RecordingBus:
    """Stands for the Zenoh bus: keeps every telemetry payload published."""

    def __init__(self) -> None:
        self.telemetry: list[tuple[str, str, bytes]] = []

    def publish_telemetry(self, role: str, channel: str, payload: bytes) -> None:
        self.telemetry.append((role, channel, payload))


class Group(SensorGroup):
    names = ("T1", "T2", "interferometer")

    async def open(self) -> None: ...

    async def read(self) -> dict[str, Reading]:
        return {}

    async def close(self) -> None: ...


def pinned_config(tmp_path: Path) -> Config:
    model_path = tmp_path / "model.json"
    write_test_model(model_path)
    config = parse_config({"cell": "pin", "model": {"path": str(model_path)}, "sensors": []}, source="pin.toml")
    sensors = [SensorConfig(name="T1", kind="x", max_age_s=2.0), SensorConfig(name="T2", kind="x"),
               SensorConfig(name="interferometer", kind="x", role="position", max_age_s=1.0)]
    pinned = config.model_copy(update={"sensors": sensors})
    pinned._source = "pin.toml"
    return pinned


def run_pinned_service(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> tuple[Service, RecordingBus, Any]:
    clock = [1700000000.5]
    # the wall clock labels, the monotonic clock decides: pin both to one value (MonotonicClock reads
    # its unix origin plus monotonic time elapsed since its monotonic origin)
    monkeypatch.setattr(time, "time", lambda: clock[0])
    monkeypatch.setattr(time, "monotonic", lambda: clock[0])
    monkeypatch.setattr(MonotonicClock, "_origin_unix_s", 0.0)
    monkeypatch.setattr(MonotonicClock, "_origin_mono_s", 0.0)
    service = Service(pinned_config(tmp_path), build_drivers=build_drivers)
    bus = RecordingBus()
    service.bus = bus  # type: ignore[assignment]
    service.ingest.on_readings(Group(), {
        "T1": Reading(21.8, t=1700000000.0, unit="degC"),
        "T2": Reading.fault(1700000000.125, "thermocouple open", unit="degC"),
        "interferometer": Reading(240.0005, t=1700000000.25),
    })
    return service, bus, clock


def test_telemetry_payload_bytes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    service, bus, clock = run_pinned_service(tmp_path, monkeypatch)
    assert bus.telemetry == [
        ("temperature", "T1", b'{"value":21.8,"unit":"degC","t":1700000000.0,"state":"ok"}'),
        ("temperature", "T2",
         b'{"value":null,"unit":"degC","t":1700000000.125,"state":"fault","reason":"thermocouple open"}'),
        ("position", "interferometer", b'{"value":240.0005,"unit":"um","t":1700000000.25,"state":"ok"}'),
    ]
    bus.telemetry.clear()
    service.watch.check()  # first look: the states are recorded, an ok channel is not news
    clock[0] += 2.5  # T1 (max_age_s 2) and the interferometer (1) are now stale
    service.watch.check()
    assert bus.telemetry == [
        ("temperature", "T1", b'{"value":21.8,"unit":"degC","t":1700000000.0,"state":"stale",'
                              b'"reason":"last reading 3.0 s old (max_age_s 2)"}'),
        ("position", "interferometer", b'{"value":240.0005,"unit":"um","t":1700000000.25,"state":"stale",'
                                       b'"reason":"last reading 2.8 s old (max_age_s 1)"}'),
    ]


def test_status_payload_bytes(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    service, _, clock = run_pinned_service(tmp_path, monkeypatch)
    clock[0] += 0.75
    model_path = str(tmp_path / "model.json").encode()
    expected = (
        b'{"cell":"pin","t":1700000001.25,"uptime_s":0.75,"config":"pin.toml","model":{"id":"m-735e979167ac",'
        b'"terms":["x^3","x^2","x","T1","T2","1"],"channels":["T1","T2"],"missing_channels":[],'
        b'"training":{"x_um":[0.0,480.0],"channels":{"T1":[21.5,22.1],"T2":[21.6,22.05]},"rows":100,'
        b'"t_span_s":3600.0},"ready":false,"created":null},"model_path":"@MODEL@","model_problem":null,'
        b'"sensors":{"T1":{"role":"temperature","value":21.8,"unit":"degC","t":1700000000.0,"age_s":1.25,'
        b'"max_age_s":2.0,"state":"ok","reason":""},"T2":{"role":"temperature","value":null,"unit":"degC",'
        b'"t":1700000000.125,"age_s":1.125,"max_age_s":5.0,"state":"fault","reason":"thermocouple open"},'
        b'"interferometer":{"role":"position","value":240.0005,"unit":"um","t":1700000000.25,"age_s":1.0,'
        b'"max_age_s":1.0,"state":"ok","reason":""}},"extrapolating":[],"actuator":{"volts_per_um":0.02,'
        b'"offset_v":0.0,"v_min":-2.0,"v_max":12.0,"x_min_um":0.0,"x_max_um":500.0,"kind":"zenoh",'
        b'"max_slew_um_per_s":0.0,"safe_voltage_v":null,"state":"ok","reason":null,"output":"published",'
        b'"device":null},'
        b'"counters":{"targets":0,"commands":0,"errors":{},"errors_total":0,"reloads":0,"reload_failures":0},'
        b'"healthy":true,"health":{"state":"unknown","residual_rms_nm":null,"residual_mean_nm":null,"n":0,'
        b'"correction_um":null,"extrapolating":[],"advice":null,"holds_unrecorded":0,"residuals_rejected":0}}'
    ).replace(b"@MODEL@", model_path)
    assert dumps(status_doc(service.state, service.healthy(), health=service.health)) == expected
