"""Safety at the hardware edge (issue 16), end to end: what the device receives, not what the daemon says.

Real peers only: ``nanodrift run`` as a process (the harness' ``file`` plugin for temperatures and, where
a test needs one, a position sensor), pymodbus' own TCP server on 127.0.0.1 as the output module (on an
asyncio loop in a thread of this process, stamping every write as it lands, optionally answering each
write late or refusing one), a PI controller speaking GCS on a pty, and a client on Zenoh over 127.0.0.1.
A wall-clock step is made in the daemon's process only (:class:`helpers.wall_clock.WallShift`).

1. a wall-clock step (−600 s, +1 day, −1 day) changes no command, faults no sensor, is logged once;
2. a reload in the middle of a ramp keeps the goal: the register ends at the served command, and a
   target answered just after the SIGHUP is written too;
3. a read-back that lies (outside the limits) is never a ramp start: at start nothing proves it, so the output
   is not moved and targets are refused (issue 26.5), for a Modbus module and a GCS controller;
5. settled residuals only after the ramp (the position sensor reads where the register puts the stage);
6. shutdown: the safe ramp at the configured rate whatever the device latency, retried after a refused
   write, and targets during the stop window answered once, with ``shutting_down``.

Every wait polls a condition with a deadline.
"""

from __future__ import annotations

import itertools
import json
import signal
import threading
import time
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    MODEL_TERMS,
    TEMPS,
    expected_q,
    wait_until,
)
from helpers.edge_cell import (
    UM_PER_COUNT,
    VOLTS_PER_UM,
    Cell,
    OutputModule,
    raw_for,
)
from helpers.serial_helpers import FakeGcsController
from helpers.wall_clock import WallShift

from nanodrift.config import STOP_TIMEOUT_S
from nanodrift.motion import RAMP_PERIOD_S


def holds_for(module: OutputModule, raw: int, seconds: float) -> None:
    """The register holds ``raw`` for ``seconds`` (polled): nothing moves it afterwards."""
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        assert module.register() == raw, f"the register left {raw}: now {module.register()}"
        time.sleep(0.02)


# --- 1. a wall-clock step ------------------------------------------------------------------------


@pytest.mark.parametrize("steps_s", [(-600.0,), (-86400.0, 86400.0)], ids=["minus_600s", "minus_plus_1day"])
def test_a_wall_clock_step_changes_no_command_faults_no_sensor_and_is_logged_once(
        tmp_path: Path, cells: list[Cell], steps_s: tuple[float, ...]) -> None:
    shift = WallShift(tmp_path / "wall_offset")
    terms = {"x": 1.0, "lag(T1, 100 s)": -2.0, "1": 0.0}
    cell = Cell(tmp_path, terms=terms, actuator="", channels=("T1",), shift=shift)
    cells.append(cell)
    baseline = cell.target(100.0)
    assert baseline["q_um"] == pytest.approx(100.0 - 2.0 * TEMPS["T1"], abs=1e-9)  # constant T1: the lag is T1

    def t1_sample_t() -> float | None:
        sample = cell.bus.telemetry.get("temperature/T1")
        return None if sample is None else sample.get("t")

    for count, step_s in enumerate(steps_s, start=1):
        before = wait_until(t1_sample_t, 5, "a T1 sample")
        shift.step(step_s)
        # a reading taken well after the step reached the daemon's model (readings come every 50 ms), or
        # the daemon failed to take it in (then the checks below say how)
        wait_until(lambda b=before: ((t := t1_sample_t()) is not None and abs(t - b) > 0.2)
                   or cell.daemon.log_events("sensor_group_failed"), 10,
                   f"a T1 reading after the {step_s:+g} s step", interval=0.02)
        command = cell.target(100.0)
        assert command["q_um"] == pytest.approx(baseline["q_um"], abs=1e-9), (step_s, command, baseline)
        assert command["voltage_v"] == pytest.approx(baseline["voltage_v"], abs=1e-9)
        status = cell.bus.status()
        assert status["sensors"]["T1"]["state"] == "ok", (step_s, status["sensors"])
        assert status["healthy"] is True
        # told within a supervision round (0.25 s), before the next step
        wait_until(lambda n=count: len(cell.daemon.log_events("clock_step")) >= n, 5, f"clock_step x{count}")
    steps = [e["step_s"] for e in cell.daemon.log_events("clock_step")]
    assert steps == [pytest.approx(s, abs=2.0) for s in steps_s]  # one line per step
    assert [e for e in cell.daemon.log_events("sensor_state") if e.get("state") != "ok"] == []
    assert not [d for d in cell.daemon.logs() if d.get("level") in ("error", "critical")]


# --- 2. a reload in the middle of a ramp ---------------------------------------------------------


def test_a_reload_mid_ramp_keeps_the_goal_and_a_target_answered_just_after_sighup_is_written(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 300.0  # 0 -> 480 um in 1.6 s
    start_raw = raw_for(VOLTS_PER_UM * expected_q(0.0, TEMPS))
    module.hold(start_raw)  # the stage is at 0 um, as confirmed; verify = true: the daemon reads it back, ramps from it
    cell = Cell(tmp_path, terms=MODEL_TERMS, actuator=f"max_slew_um_per_s = {rate}\nv_max = 12.0",
                hub_port=module.server.port, confirmed_v=start_raw * 0.001)
    cells.append(cell)

    def mid_ramp(goal_raw: int, from_raw: int) -> None:
        """Until the register is between a fifth and half of the way from ``from_raw`` to ``goal_raw``."""
        wait_until(lambda: 0.2 <= (module.register() - from_raw) / (goal_raw - from_raw) <= 0.5, 10,
                   "the ramp under way", interval=0.005)

    # a reload mid-ramp: the register ends at the served command, ramped on from where it was
    jump = cell.target(480.0)
    jump_raw = raw_for(jump["voltage_v"])
    mid_ramp(jump_raw, start_raw)
    cell.write_config(f"max_slew_um_per_s = {rate}\nv_max = 11.5")  # [actuator] edited; the goal still allowed
    since = len(module.stamps)
    cell.daemon.signal(signal.SIGHUP)
    applied = cell.daemon.wait_log("reload_applied", timeout=15)
    assert applied["drivers_restarted"] is True
    wait_until(lambda: module.register() == jump_raw, 10, "the register at the served command", interval=0.02)
    holds_for(module, jump_raw, 0.3)
    after = [raw for _, raw in module.written(since)]
    assert after and after[-1] == jump_raw
    assert all(b >= a for a, b in itertools.pairwise(after)), "the ramp went back after the reload"

    # a target answered just after a SIGHUP (while the drivers are swapped) is written to the new output
    back = cell.target(100.0)
    back_raw = raw_for(back["voltage_v"])
    mid_ramp(back_raw, jump_raw)
    cell.write_config(f"max_slew_um_per_s = {rate}\nv_max = 11.0")
    cell.daemon.signal(signal.SIGHUP)
    sent = time.monotonic()
    late = cell.target(300.0)
    assert time.monotonic() - sent < 0.5  # answered right after the SIGHUP
    late_raw = raw_for(late["voltage_v"])
    cell.daemon.wait_log("reload_applied", timeout=15, count=2)
    wait_until(lambda: module.register() == late_raw, 10, "the register at the target answered after SIGHUP",
               interval=0.02)
    holds_for(module, late_raw, 0.3)
    assert cell.bus.status()["actuator"]["state"] == "ok"


# --- 3. a read-back that lies ------------------------------------------------------------------------

# q = x - 22.5 um: the target 0 um is commanded at -0.45 V
LYING_TERMS = {"x": 1.0, "1": -22.5}


def refused_as_unproven(cell: Cell, claim: str) -> dict[str, Any]:
    """A target is refused because the output's read-back is unproven, saying what to do; status says it too."""
    ok, answer = cell.bus.query({"x_um": 0.0, "id": 1})
    assert not ok and answer["kind"] == "actuator_fault", answer
    assert claim in answer["error"] and "nanodrift confirm-output" in answer["error"], answer
    actuator = cell.bus.status()["actuator"]
    assert actuator["state"] == "fault" and "cannot be proven" in actuator["reason"], actuator
    return answer


def test_a_modbus_output_reading_back_outside_the_limits_is_never_moved(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    module.hold(raw_for(10.0))  # the register reads back 10 V; the limits are [-2, 9.5] V
    cell = Cell(tmp_path, terms=LYING_TERMS, hub_port=module.server.port,
                actuator="v_min = -2.0\nv_max = 9.5\nmax_slew_um_per_s = 100.0\nverify = true")
    cells.append(cell)
    refused_as_unproven(cell, "read back 10.0000 V, outside [-2, 9.5] V")
    assert module.written() == [] and module.register() == raw_for(10.0)  # the module received nothing


def test_a_gcs_controller_reading_back_outside_the_limits_is_never_moved(
        tmp_path: Path, cells: list[Cell]) -> None:
    controller = FakeGcsController(tmp_path / "ttyPI")
    controller.voltage = 50.0  # SVA? 1 answers 50 V; the limits are [-2, 12] V
    try:
        keys = (f'kind = "serial_line"\nport = "{controller.port}"\nreadback = "SVA? 1\\n"\nerror_query = "ERR?\\n"\n'
                "timeout_s = 2.0\nmax_slew_um_per_s = 100.0\n")  # answered from a thread here: late when loaded
        cell = Cell(tmp_path, terms=LYING_TERMS, actuator=keys)
        cells.append(cell)
        refused_as_unproven(cell, "read back 50.0000 V, outside [-2, 12] V")
        assert not [line for line in controller.lines if line.startswith("SVA 1 ")], controller.lines
    finally:
        for cell in cells:
            cell.close()
        cells.clear()
        controller.close()


# --- 5. settled residuals only after the ramp ------------------------------------------------------


def test_settled_residuals_are_taken_only_after_the_ramp_has_reached_the_command(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 40.0  # 80 um in 2 s: longer than settle_s + window_s
    settle_s, window_s = 1.0, 0.5
    module.hold(0)
    cell = Cell(tmp_path, terms={"x": 1.0}, hub_port=module.server.port, position=True,
                actuator=f"max_slew_um_per_s = {rate}",
                extra=f"[health]\nsettle_s = {settle_s}\nwindow_s = {window_s}\n")
    cells.append(cell)

    # the stage is where the register puts it, and the position sensor reads it (q = x: no drift)
    def moved(raw: int) -> None:
        cell.sensors.set(P=raw * UM_PER_COUNT)

    module.on_output = moved
    assert cell.bus.status()["health"]["n"] == 0
    sent = time.monotonic()
    command = cell.target(80.0)
    goal_raw = raw_for(command["voltage_v"])
    seen_mid_ramp = 0
    while module.register() != goal_raw:  # mid-ramp: no residual
        assert time.monotonic() - sent < 10, "the ramp did not end"
        assert cell.bus.status()["health"]["n"] == 0, "a residual was taken mid-ramp"
        seen_mid_ramp += 1
        time.sleep(0.02)  # a poll period (not a wait for anything): status queries back to back cost both CPUs
    reached = next(t for t, raw in module.written() if raw == goal_raw)
    assert reached - sent >= 80.0 / rate - 0.3 and seen_mid_ramp >= 2  # checked mid-ramp (a loaded machine polls less)

    def first_residual() -> dict[str, Any] | None:
        health = cell.bus.status()["health"]
        return health if health["n"] > 0 else None

    health = wait_until(first_residual, reached + settle_s + window_s + 5 - time.monotonic(), "the first residual",
                        interval=0.05)
    assert time.monotonic() >= reached + settle_s + window_s - 0.1
    assert health["n"] == 1
    assert abs(health["residual_mean_nm"]) < 100.0 and health["residual_rms_nm"] < 100.0, health  # not tens of um


# --- 6. shutdown -------------------------------------------------------------------------------------


def shutdown_cell(tmp_path: Path, module: OutputModule, cells: list[Cell], rate: float) -> Cell:
    """A daemon holding 200 um (4 V) on a register that answers each write 10 ms late; safe_voltage_v = 0."""
    module.device.write_delay_s = 0.010
    module.hold(raw_for(4.0))
    cell = Cell(tmp_path, terms={"x": 1.0}, hub_port=module.server.port, confirmed_v=4.0,
                actuator=f"max_slew_um_per_s = {rate}\nsafe_voltage_v = 0.0")
    cells.append(cell)
    cell.target(200.0)
    wait_until(lambda: cell.bus.status()["actuator"]["writes"] >= 1, 5, "the command written")
    assert module.register() == raw_for(4.0)
    return cell


def test_sigterm_ramps_to_the_safe_voltage_at_the_configured_rate_and_refuses_targets_meanwhile(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 100.0  # 200 um -> 0 in 2 s
    cell = shutdown_cell(tmp_path, module, cells, rate)
    client = cell.bus
    ids = itertools.count(1000)
    sent: list[int] = []
    stop_sending = threading.Event()

    def send() -> None:  # a stream of targets through the stop window, until the daemon is gone
        while not stop_sending.is_set() and cell.daemon.proc.poll() is None:
            target_id = next(ids)
            client.put(json.dumps({"x_um": 200.0, "id": target_id}))
            sent.append(target_id)
            time.sleep(0.02)

    sender = threading.Thread(target=send, daemon=True)
    sender.start()
    try:
        client.wait(lambda: len(client.commands) >= 3, 5, "targets served before the stop")
        since = len(module.stamps)
        asked = time.monotonic()
        cell.daemon.signal(signal.SIGTERM)
        code = cell.daemon.proc.wait(STOP_TIMEOUT_S)
        stopped_in = time.monotonic() - asked
    finally:
        stop_sending.set()
        sender.join(5)
    assert code == 0 and stopped_in < STOP_TIMEOUT_S
    assert module.register() == 0  # the safe count

    ramp = [(t, raw * UM_PER_COUNT) for t, raw in module.written(since)]
    assert ramp[-1][1] == 0.0 and len(ramp) > 5, ramp  # a ramp (~100 steps idle; fewer on a loaded machine)
    assert all(b < a for (_, a), (_, b) in itertools.pairwise(ramp)), f"the safe ramp is not monotonic {ramp}"
    # ramp[0]: the last write before the stop (200 um) or the ramp's first step; a move from rest covers one
    # ramp period in its first step, on top of the time between the two
    # a count, and 100 ms of stamping jitter: the module's thread stamps arrivals, and a loaded machine delays one
    # write against the next (10 ms failed under load); a ramp 10 % too fast still fails over its 2 s
    slack_um = UM_PER_COUNT + rate * 0.100
    (t0, q0), (t1, q1) = ramp[:2]
    assert q0 - q1 <= rate * (t1 - t0 + RAMP_PERIOD_S) + slack_um, f"{q0 - q1:.3f} um in {t1 - t0:.4f} s"
    for (t0, q0), (t1, q1) in itertools.combinations(ramp[1:], 2):
        assert q0 - q1 <= rate * (t1 - t0) + slack_um, f"{q0 - q1:.3f} um in {t1 - t0:.4f} s"
    achieved = (ramp[1][1] - ramp[-1][1]) / (ramp[-1][0] - ramp[1][0])
    # not crawling (the unit's stop timeout counts on the rate). A step covers the time since the previous write
    # returned (the bound that holds on the device whatever the loop does) and a ramp pauses 9x the write time,
    # so a device answering in 10 ms ramps at about 90 % of the rate idle, less when a loaded machine writes late:
    # a floor, not a speed
    assert achieved >= 0.3 * rate, f"{achieved:.1f} um/s with a device answering in 10 ms, configured {rate}"
    assert cell.daemon.log_events("actuator_safe")[0]["voltage_v"] == 0.0

    # every target sent got one answer at most; once refused for the stop, never served again
    def answered() -> dict[int, list[tuple[str, dict[str, Any]]]]:
        return {i: client.answers_for(i) for i in sent if client.answers_for(i)}

    answers = answered()
    last = max(answers)
    wait_until(lambda: all(client.answers_for(i) for i in sent if i <= last), 2, "an answer for every target")
    answers = answered()
    assert all(len(a) == 1 for a in answers.values()), {i: a for i, a in answers.items() if len(a) != 1}
    refused = [i for i, [(kind, doc)] in answers.items() if kind == "error"]
    assert len(refused) >= 10, answers  # the stop window is ~2 s of 50 targets a second
    for i in refused:
        [(_, doc)] = answers[i]
        assert doc["kind"] == "shutting_down" and doc["error"] == "the daemon is stopping: target not served", doc
    assert not [i for i, [(kind, _)] in answers.items() if kind == "command" and i > min(refused)]


def test_a_write_refused_mid_safe_ramp_is_retried_and_the_safe_voltage_reached(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 100.0
    cell = shutdown_cell(tmp_path, module, cells, rate)
    since = len(module.stamps)
    cell.daemon.signal(signal.SIGTERM)
    wait_until(lambda: module.register() < raw_for(3.0), 5, "the safe ramp half way", interval=0.005)
    refused_from = len(module.device.writes)
    module.device.refuse_writes = 1  # the module refuses the next write (DEVICE_FAILURE)
    assert cell.daemon.proc.wait(STOP_TIMEOUT_S) == 0
    assert module.device.refuse_writes == 0, "no write was refused: the ramp ended first"
    assert len(module.device.writes) > refused_from + 1
    assert module.register() == 0
    [safe] = cell.daemon.log_events("actuator_safe")
    assert safe["attempts"] >= 2 and safe["voltage_v"] == 0.0
    ramp = [raw for _, raw in module.written(since)]
    assert ramp[-1] == 0 and all(b < a for a, b in itertools.pairwise(ramp)), ramp
    assert not cell.daemon.log_events("actuator_safe_failed")
