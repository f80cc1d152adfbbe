"""The Zenoh payloads of the wire format, pinned byte for byte (a public contract, README).

Each expected value below was produced by the code before the wire format moved to
``nanodrift.bus.protocol`` (commit c198473); a refactoring that changes a single byte of a command, an
error or a procedure step fails here. Computed numbers are compared with ``helpers.floats.assert_same``:
every byte but a float's last bits (which another CPU's or BLAS' rounding may move) is pinned.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
import pytest
from helpers.daemon_harness import write_test_model
from helpers.floats import assert_same

from nanodrift.bus.actuator import ZenohActuator
from nanodrift.bus.protocol import encode_command, encode_error, parse_target
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.compensation import Command, Compensator, Refusal, Target
from nanodrift.config import ActuatorConfig, parse_config
from nanodrift.drivers.base import Reading, SensorConfig
from nanodrift.service.table import SensorTable

UNIX_NOW = 1700000000.25


@pytest.fixture
def compensator(tmp_path: Path) -> Compensator:
    model = write_test_model(tmp_path / "m.json")
    table = SensorTable([SensorConfig(name=n, kind="x", max_age_s=5.0) for n in ("T1", "T2", "T3")])
    for name, value in {"T1": 21.8, "T2": 21.9, "T3": 30.0}.items():
        table.update(name, Reading(value, t=10.0))
    comp = Compensator(model, {"x": ActuatorConfig()}, table)
    comp.observe(10.0, {"T1": 21.8, "T2": 21.9})
    return comp


def command_bytes(comp: Compensator, target: Target) -> bytes:
    return encode_command(comp.compensate(target, now=11.0, unix_now=UNIX_NOW))


def error_bytes(refusal: Refusal) -> bytes:
    return encode_error(refusal)


def test_command_payload_bytes(compensator: Compensator) -> None:
    assert_same(command_bytes(compensator, Target("k", {"x": 200.0})), (
        b'{"id":"k","x_um":200.0,"q_um":176.62999999999997,"voltage_v":3.5325999999999995,'
        b'"temperatures_c":{"T1":21.8,"T2":21.9},"model":"m-735e979167ac","t":1700000000.25,"extrapolating":[],'
        b'"q_sigma_um":null}'
    ))
    assert_same(command_bytes(compensator, Target(None, {"x": 0.0})), (
        b'{"id":null,"x_um":0.0,"q_um":-23.53,"voltage_v":-0.4706,'
        b'"temperatures_c":{"T1":21.8,"T2":21.9},"model":"m-735e979167ac","t":1700000000.25,"extrapolating":[],'
        b'"q_sigma_um":null}'
    ))
    assert_same(command_bytes(compensator, Target('quo"te\\ \u00e9', {"x": 12.5})), (
        b'{"id":"quo\\"te\\\\ \\u00e9","x_um":12.5,"q_um":-11.006523437500002,"voltage_v":-0.22013046875000006,'
        b'"temperatures_c":{"T1":21.8,"T2":21.9},"model":"m-735e979167ac","t":1700000000.25,"extrapolating":[],'
        b'"q_sigma_um":null}'
    ))


def test_command_payload_bytes_when_extrapolating(compensator: Compensator) -> None:
    compensator.readings.update("T2", Reading(23.0, t=10.5))
    compensator.observe(10.5, {"T2": 23.0})
    assert_same(command_bytes(compensator, Target(-7, {"x": 490.0})), (
        b'{"id":-7,"x_um":490.0,"q_um":466.85198,"voltage_v":9.3370396,'
        b'"temperatures_c":{"T1":21.8,"T2":23.0},"model":"m-735e979167ac","t":1700000000.25,'
        b'"extrapolating":["x","T2"],"q_sigma_um":null}'
    ))


def test_command_payload_bytes_with_uncertainty_and_correction(compensator: Compensator) -> None:
    """Issue 12: ``q_sigma_um`` after ``extrapolating``, then ``correction_um`` (adaptation on), inside q."""
    assert compensator.model is not None
    compensator.model.fit = {"rmse_um": 0.025}  # a model without covariance: sigma is its residual RMS
    compensator.evaluators = {"x": compensator.model.evaluator()}
    compensator.observe(10.0, {"T1": 21.8, "T2": 21.9})
    assert_same(command_bytes(compensator, Target("k", {"x": 200.0})), (
        b'{"id":"k","x_um":200.0,"q_um":176.62999999999997,"voltage_v":3.5325999999999995,'
        b'"temperatures_c":{"T1":21.8,"T2":21.9},"model":"m-735e979167ac","t":1700000000.25,"extrapolating":[],'
        b'"q_sigma_um":0.025}'
    ))
    compensator.monitor = Adapting(-0.25)
    assert_same(command_bytes(compensator, Target("k", {"x": 200.0})), (
        b'{"id":"k","x_um":200.0,"q_um":176.37999999999997,"voltage_v":3.5275999999999996,'
        b'"temperatures_c":{"T1":21.8,"T2":21.9},"model":"m-735e979167ac","t":1700000000.25,"extrapolating":[],'
        b'"q_sigma_um":0.025,"correction_um":-0.25}'
    ))
    # the tracker behind it (issue 19): the corrected command's own σ follows its correction
    tracker = BiasTracker(600.0, 1.0)
    tracker.update(0.0, 0.3)
    tracker.update(30.0, 0.1)
    compensator.monitor = Adapting(tracker.correction_um, tracker)
    # σ² = u²·0.025² + (1 - u²)·RMS², u = exp(-60/600), RMS of the residuals 0.3 and 0.1 as weighted
    assert_same(command_bytes(compensator, Target("k", {"x": 200.0})), (
        b'{"id":"k","x_um":200.0,"q_um":176.61049176980026,"voltage_v":3.532209835396005,'
        b'"temperatures_c":{"T1":21.8,"T2":21.9},"model":"m-735e979167ac","t":1700000000.25,"extrapolating":[],'
        b'"q_sigma_um":0.025,"correction_um":-0.019508230199714392,"q_sigma_adapted_um":0.09692232753519878}'
    ))


class Adapting:
    """The compensator's monitor hook as the health unit gives it: a correction, and the tracker behind it."""

    def __init__(self, correction_um: float, tracker: BiasTracker | None = None) -> None:
        self.correction, self.tracker = correction_um, tracker

    def correction_um(self) -> dict[str, float]:
        return {"x": self.correction}

    def sigma_adapted_um(self, sigma_um: dict[str, float], wander_um: dict[str, float]) -> dict[str, float] | None:
        return {"x": self.tracker.sigma_um(sigma_um["x"], wander_um["x"])} if self.tracker is not None else None

    def served(self, now: float, command: Command) -> None:
        pass


def test_error_payload_bytes(compensator: Compensator) -> None:
    def refusal_of(payload: bytes) -> Refusal:
        with pytest.raises(Refusal) as caught:
            parse_target(payload)
        return caught.value

    assert error_bytes(refusal_of(b'{"x_um": "100", "id": 8}')) == (
        b'{"id":8,"error":"\'x_um\' must be a number, got str","kind":"bad_payload"}'
    )
    assert error_bytes(refusal_of(b'{"id": "\\u00e9"}')) == (
        b'{"id":"\\u00e9","error":"missing field \'x_um\' (target position in um)","kind":"bad_payload"}'
    )
    assert error_bytes(refusal_of(b"nope")) == (
        b'{"id":null,"error":"payload is not valid JSON (Expecting value: line 1 column 1 (char 0)); '
        b'expected {\\"x_um\\": number, \\"id\\": ...}","kind":"bad_payload"}'
    )
    with pytest.raises(Refusal) as stale:
        compensator.compensate(Target("s", {"x": 100.0}), now=15.5, unix_now=UNIX_NOW)
    assert error_bytes(stale.value) == (
        b'{"id":"s","error":"channel T1 is stale: last reading 5.5 s old (max_age_s 5)","kind":"stale"}'
    )


class RecordingPublisher:
    def __init__(self) -> None:
        self.payloads: list[bytes] = []

    def put(self, payload: bytes) -> None:
        self.payloads.append(payload)


def test_procedure_step_payload_bytes(monkeypatch: pytest.MonkeyPatch) -> None:
    """A calibration step published on the command key (no model, named after its procedure)."""
    monkeypatch.setattr(time, "time", lambda: UNIX_NOW)
    actuator = ZenohActuator(parse_config({"cell": "lab1", "sensors": []}), procedure="validation")
    publisher = RecordingPublisher()
    actuator._publisher = publisher  # type: ignore[assignment]
    asyncio.run(actuator.command(240.0, 4.8))
    asyncio.run(actuator.command(np.float64(12.25), 0.245))
    assert publisher.payloads == [
        b'{"id":"validation-1","x_um":240.0,"q_um":240.0,"voltage_v":4.8,"temperatures_c":{},"model":null,'
        b'"t":1700000000.25,"procedure":"validation"}',
        b'{"id":"validation-2","x_um":12.25,"q_um":12.25,"voltage_v":0.245,"temperatures_c":{},"model":null,'
        b'"t":1700000000.25,"procedure":"validation"}',
    ]
