"""The daemon's decisions without Zenoh: sensor states, compensation, limits, rate-limited logging,
sd_notify datagrams, the watchdog's health check."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import time
from pathlib import Path

import pytest
from helpers.cell_helpers import expected_cell_q, write_cell_model
from helpers.daemon_harness import MODEL_TERMS, expected_q, write_test_model

from nanodrift.compensation import Compensator, Refusal, Target
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import MonotonicClock, Reading, SensorConfig, SensorGroup, State
from nanodrift.logs import RateLimiter
from nanodrift.motion import VoltageLimitError
from nanodrift.sdnotify import Notifier, watchdog_interval_s
from nanodrift.service.polling import GroupPoller, pollers_healthy
from nanodrift.service.table import SensorTable


def sensors(*names: str, max_age_s: float = 5.0) -> list[SensorConfig]:
    return [SensorConfig(name=n, kind="x", max_age_s=max_age_s) for n in names]


def test_sensor_states_ok_stale_fault_and_recovery() -> None:
    table = SensorTable(sensors("T1", "T2", max_age_s=5.0))
    assert table.state("T1", 0.0) == (State.STALE, "no reading yet")
    table.update("T1", Reading(21.5, t=100.0))
    assert table.state("T1", 104.9) == (State.OK, "")
    state, reason = table.state("T1", 105.5)
    assert state == State.STALE and "5.5 s old" in reason
    table.update("T1", Reading.fault(106.0, "burnout"))
    assert table.state("T1", 106.0) == (State.FAULT, "burnout")
    assert table.entries["T1"].value == 21.5  # the last good value is kept for status, never used
    table.update("T1", Reading(21.6, t=107.0))
    assert table.state("T1", 107.0) == (State.OK, "")
    table.mark_fault(["T1"], "device error: port gone")
    assert table.state("T1", 107.0) == (State.FAULT, "device error: port gone")
    table.update("T2", Reading(float("nan"), t=1.0))
    assert table.state("T2", 1.0)[0] == State.FAULT
    assert table.state("T9", 0.0)[0] == State.FAULT
    snapshot = table.snapshot(108.0)
    assert snapshot["T1"]["state"] == "fault" and snapshot["T1"]["age_s"] == pytest.approx(1.0)




TEMPS = {"T1": 21.8, "T2": 21.9}
#: a one-axis cell and an XY cell: the same compensator, the same tests
CELLS = pytest.mark.parametrize("axes", [("x",), ("x", "y")], ids=["one-axis", "xy"])


def expected(axes: tuple[str, ...], x_um: float, temps: dict[str, float]) -> dict[str, float]:
    """Every axis' q for the target with every axis at ``x_um`` (the harness' one-axis model, or the cell's)."""
    if axes == ("x",):
        return {"x": expected_q(x_um, temps)}
    return expected_cell_q(dict.fromkeys(axes, x_um), temps)


def at(target_id: object, axes: tuple[str, ...], x_um: float) -> Target:
    return Target(target_id, dict.fromkeys(axes, x_um))


@pytest.fixture
def compensator(tmp_path: Path, axes: tuple[str, ...]) -> Compensator:
    model = write_test_model(tmp_path / "m.json") if axes == ("x",) else write_cell_model(tmp_path / "m.json", axes)
    table = SensorTable(sensors("T1", "T2", "T3", max_age_s=5.0))
    for name, value in {**TEMPS, "T3": 30.0}.items():
        table.update(name, Reading(value, t=10.0))
    comp = Compensator(model, dict.fromkeys(axes, ActuatorConfig()), table)
    comp.observe(10.0, TEMPS)
    return comp


@CELLS
def test_compensation_matches_the_model_and_the_actuator_gain(compensator: Compensator, axes: tuple[str, ...]) -> None:
    command = compensator.compensate(at("k", axes, 200.0), now=11.0, unix_now=1234.5)
    assert command.q_um == pytest.approx(expected(axes, 200.0, TEMPS), abs=1e-12)
    assert command.voltage_v == pytest.approx({a: 0.02 * q for a, q in command.q_um.items()}, abs=1e-15)
    assert compensator.model is not None
    assert command.temperatures_c == {c: TEMPS[c] for c in compensator.model.channels}  # the model's channels only
    assert "T3" not in command.temperatures_c
    assert command.t == 1234.5 and command.id == "k"
    assert command.model == compensator.model.id
    assert command.extrapolating == []
    if axes == ("x",):
        assert set(MODEL_TERMS) == set(compensator.model.term_names())


@CELLS
def test_refusals_stale_workspace_voltage_and_no_model(compensator: Compensator, axes: tuple[str, ...]) -> None:
    with pytest.raises(Refusal) as stale:
        compensator.compensate(at(1, axes, 100.0), now=15.5, unix_now=0.0)
    assert stale.value.kind == "stale" and "T1" in stale.value.message and stale.value.id == 1
    with pytest.raises(Refusal) as outside:
        compensator.compensate(at(2, axes, 500.01), now=11.0, unix_now=0.0)
    assert outside.value.kind == "out_of_workspace" and f"{axes[-1]}_um 500.01 outside" in outside.value.message
    limits = ActuatorConfig(v_max=4.0)  # on the last axis: a cell of several refuses the whole target
    tight = Compensator(compensator.model, {**compensator.limits, axes[-1]: limits}, compensator.readings)
    tight.evaluators = compensator.evaluators
    with pytest.raises(Refusal) as volts:
        tight.compensate(at(3, axes, 250.0), now=11.0, unix_now=0.0)
    assert volts.value.kind == "voltage_limit" and "outside [-2, 4] V" in volts.value.message
    with pytest.raises(VoltageLimitError) as procedure:  # a procedure's step is refused in the same words
        limits.checked_voltage(expected(axes, 250.0, TEMPS)[axes[-1]])
    if axes == ("x",):
        assert str(procedure.value) == volts.value.message
    else:  # ... naming the axis, and that nothing moves
        assert volts.value.message == f"axis {axes[-1]}: {procedure.value}: no axis moves"
    assert all(v <= 4.0 for v in tight.compensate(at(4, axes, 150.0), now=11.0, unix_now=0.0).voltage_v.values())
    none = Compensator(None, compensator.limits, compensator.readings, model_problem="m.json: no such model file")
    with pytest.raises(Refusal) as no_model:
        none.compensate(at(5, axes, 1.0), now=11.0, unix_now=0.0)
    assert no_model.value.kind == "no_model" and "no such model file" in no_model.value.message


@CELLS
def test_missing_channel_and_extrapolation(compensator: Compensator, axes: tuple[str, ...]) -> None:
    only_t3 = SensorTable(sensors("T3"))
    only_t3.update("T3", Reading(21.8, t=10.0))
    missing = Compensator(compensator.model, compensator.limits, only_t3)
    with pytest.raises(Refusal) as caught:
        missing.compensate(at(1, axes, 1.0), now=10.0, unix_now=0.0)
    assert caught.value.kind == "missing_channel" and "T1" in caught.value.message
    compensator.readings.update("T1", Reading(23.0, t=10.5))
    compensator.observe(10.5, {"T1": 23.0})
    command = compensator.compensate(at(2, axes, 490.0), now=11.0, unix_now=0.0)
    assert command.extrapolating == [*axes, "T1"]
    assert compensator.extrapolating_now() == ["T1"]


def test_rate_limiter_lets_a_burst_through_then_counts() -> None:
    now = [0.0]
    limiter = RateLimiter(rate=2.0, burst=3, clock=lambda: now[0])
    assert [limiter.allow() for _ in range(5)] == [True, True, True, False, False]
    assert limiter.take_suppressed() == 2 and limiter.take_suppressed() == 0
    now[0] = 1.0  # two tokens back
    assert [limiter.allow() for _ in range(3)] == [True, True, False]


@pytest.mark.parametrize("abstract", [False, True])
def test_sd_notify_datagrams_reach_path_and_abstract_sockets(tmp_path: Path, abstract: bool) -> None:
    server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
    if abstract:
        name = f"nanodrift-test-{os.getpid()}-{id(server)}"
        server.bind("\0" + name)
        address = "@" + name
    else:
        address = str(tmp_path / "notify.sock")
        server.bind(address)
    server.settimeout(2.0)
    notifier = Notifier(address)
    try:
        assert notifier.enabled
        assert notifier.ready("serving cell0")
        assert server.recv(4096) == b"READY=1\nSTATUS=serving cell0"
        assert notifier.watchdog()
        assert server.recv(4096) == b"WATCHDOG=1"
        assert notifier.stopping()
        assert server.recv(4096) == b"STOPPING=1\nSTATUS=stopping"
    finally:
        notifier.close()
        server.close()
    assert not Notifier("").enabled and not Notifier("").ready()


def test_watchdog_interval_is_half_of_systemds(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("WATCHDOG_USEC", "30000000")
    monkeypatch.setenv("WATCHDOG_PID", str(os.getpid()))
    assert watchdog_interval_s() == 15.0
    monkeypatch.setenv("WATCHDOG_PID", "1")  # meant for another process
    assert watchdog_interval_s() is None
    monkeypatch.delenv("WATCHDOG_USEC")
    assert watchdog_interval_s() is None



def test_logs_are_json_lines_for_journald_and_readable_on_a_terminal(capsys: pytest.CaptureFixture[str]) -> None:
    import structlog

    from nanodrift.logs import RateLimitedLog, configure_logging, get_logger

    try:
        configure_logging("info", json_lines=True)
        get_logger().warning("sensor_state", channel="T2", state="stale")
        line = json.loads(capsys.readouterr().err.strip())
        assert line["event"] == "sensor_state" and line["channel"] == "T2" and line["level"] == "warning"
        configure_logging("info", json_lines=False)
        log = RateLimitedLog(get_logger(), "target_refused", RateLimiter(rate=0.0, burst=2))
        for _ in range(5):
            log(kind="bad_payload")
        log.flush()
        lines = capsys.readouterr().err.strip().splitlines()
        assert len(lines) == 3 and not lines[0].startswith("{")
        assert "target_refused_suppressed" in lines[2] and "suppressed=3" in lines[2]
    finally:
        structlog.reset_defaults()


def test_a_refused_target_does_not_move_the_models_motion_state(tmp_path: Path) -> None:
    """A target refused for its voltage never reaches the stage, so `dir` must not see it as a move."""
    terms = {**MODEL_TERMS, "dir": 0.05}
    model = write_test_model(tmp_path / "dir.json", terms)
    table = SensorTable(sensors("T1", "T2"))
    for name, value in {"T1": 21.8, "T2": 21.9}.items():
        table.update(name, Reading(value, t=10.0))
    comp = Compensator(model, {"x": ActuatorConfig(v_max=4.0)}, table)  # 4 V ~ 200 um
    comp.observe(10.0, {"T1": 21.8, "T2": 21.9})
    comp.compensate(Target(1, {"x": 100.0}), now=11.0, unix_now=0.0)
    with pytest.raises(Refusal):
        comp.compensate(Target(2, {"x": 400.0}), now=11.0, unix_now=0.0)  # never sent to the stage
    after = comp.compensate(Target(3, {"x": 180.0}), now=11.0, unix_now=0.0).q_um["x"]
    # 100 -> 180 is a step up from where the stage really is (down only from the refused 400)
    assert after == pytest.approx(expected_q(180.0, {"T1": 21.8, "T2": 21.9}, terms) + 0.05, abs=1e-12)


def test_watchdog_health_fails_when_a_poller_dies_or_stops_making_progress() -> None:
    """systemd restarts a daemon that stops pinging: the pings must stop exactly in these cases."""

    class Idle(SensorGroup):
        names, roles, interval_s, timeout_s = ("T1",), {"T1": "temperature"}, 0.5, 1.0

        async def open(self) -> None: ...

        async def read(self) -> dict[str, Reading]:
            return {"T1": Reading(20.0, t=0.0)}

        async def close(self) -> None: ...

    async def check() -> tuple[bool, bool, bool]:
        poller = GroupPoller(Idle(), MonotonicClock(), lambda g, r: None, lambda g, reason, delay, failures: None)
        poller.task = asyncio.get_running_loop().create_task(asyncio.sleep(60))
        healthy = pollers_healthy([poller])
        poller.last_progress = time.monotonic() - GroupPoller.MAX_BACKOFF_S * 2  # stuck for a minute
        stuck = pollers_healthy([poller])
        poller.last_progress = time.monotonic()
        poller.task.cancel()
        await asyncio.sleep(0)
        dead = pollers_healthy([poller])
        return healthy, stuck, dead

    assert asyncio.run(check()) == (True, False, False)

