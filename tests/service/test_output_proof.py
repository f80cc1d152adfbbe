"""Issue 26 items 4, 5, 8 and 9: outputs the daemon can prove, recoveries that keep the slew, safe stops per axis.

End to end, judged on the device side: ``nanodrift run`` as a process, pymodbus' own TCP server on 127.0.0.1 as
each output module (stamping every write as it lands), a Zenoh client over 127.0.0.1.

4. a read-back mismatch (``verify = true``) mid-ramp, and a reopen that still reads back a lie, recover by
   ramping from what the daemon wrote: the register never moves faster than the slew;
5. after ``kill -9`` a restart believes the register only as far as the state file confirms it: 8 V resumes
   from 8 V; a claim of 10 V where 0 V was written is refused (nothing is written, ``status`` says why and what to
   do) until ``nanodrift confirm-output`` says where it is, and the move then ramps from there; without the state
   file, the axis' position sensor proves 8 V when it reads where 8 V puts the stage, and a reading far from it
   or a stale one proves nothing;
8. SIGTERM on an XY cell whose y module is dead: x reaches its safe voltage while y still retries;
9. a module answering each write 60 ms late: the ramp's steps cover the pause the daemon makes for it (9x the
   write time), not 0.1 s at most, and still never move faster than the slew.

Every wait polls a condition with a deadline.
"""

from __future__ import annotations

import contextlib
import itertools
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.cell_helpers import write_cell_model
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    free_port,
    install_file_plugin,
    wait_until,
)
from helpers.edge_cell import ADDRESS, UM_PER_COUNT, Cell, OutputModule, confirm_output, raw_for, state_dir_keys
from helpers.modbus_helpers import FC_READ_HOLDING

from nanodrift.motion import LATENCY_PAUSES, RAMP_PERIOD_S

#: the module's thread stamps writes as they land: a loaded machine delays one against the next (as in
#: test_hardware_edge.py's slew checks), plus one count of rounding
STAMP_SLACK_S = 0.100


def assert_slewed(writes: list[tuple[float, int]], rate_um_per_s: float, *, from_raw: int | None = None) -> None:
    """Between any two values the register received (and from ``from_raw``, what it held before, to the first),
    it never moved faster than the rate; a move from rest may cover one ramp period more."""
    points = [(t, raw * UM_PER_COUNT) for t, raw in writes]
    if from_raw is not None:
        assert abs(points[0][1] - from_raw * UM_PER_COUNT) <= rate_um_per_s * RAMP_PERIOD_S + UM_PER_COUNT, \
            f"first write {points[0][1]:.2f} um, the register held {from_raw * UM_PER_COUNT:.2f} um"
    slack_um = UM_PER_COUNT + rate_um_per_s * STAMP_SLACK_S
    for (t0, q0), (t1, q1) in itertools.pairwise(points):
        assert abs(q1 - q0) <= rate_um_per_s * (t1 - t0 + RAMP_PERIOD_S) + slack_um, \
            f"{q1 - q0:.3f} um in {t1 - t0:.4f} s at {rate_um_per_s} um/s"


# --- 4. a recovery ramps from what was written ---------------------------------------------------------


def test_a_read_back_mismatch_mid_ramp_recovers_ramped_from_the_value_written(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 200.0  # 0 -> 480 um (9.6 V) in 2.4 s
    cell = Cell(tmp_path, terms={"x": 1.0}, hub_port=module.server.port,
                actuator=f"max_slew_um_per_s = {rate}\nverify = true")
    cells.append(cell)
    lies = {"left": 0}

    def lie(function_code: int, start: int, registers: list[int]) -> None:  # the verify read, then the reopen's
        if function_code == FC_READ_HOLDING and lies["left"] > 0 and start <= ADDRESS < start + len(registers):
            lies["left"] -= 1
            registers[ADDRESS - start] = raw_for(0.035)

    module.device.on_read = lie
    cell.target(480.0)
    wait_until(lambda: module.register() > raw_for(3.0), 10, "the ramp past 3 V", interval=0.005)
    lies["left"] = 2
    wait_until(lambda: module.register() == raw_for(9.6), 15, "the register at the goal, 9.6 V")
    assert lies["left"] == 0, "the module was never asked to read back while it lied"
    assert cell.daemon.log_events("actuator_failed"), "the mismatch was not a fault"
    assert_slewed(module.written(), rate, from_raw=0)  # issue 26.4: 9.96 V then 0.035 V, 0.2 s apart
    untrusted = cell.daemon.wait_log("actuator_readback_untrusted")
    assert untrusted["known_from"] == "last written" and "0.0350 V" in untrusted["reason"], untrusted


# --- 5. a read-back the daemon can prove -----------------------------------------------------------------


def test_a_restart_after_kill_9_resumes_from_the_8_v_the_state_file_proves_without_a_jump(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 400.0
    cell = Cell(tmp_path, terms={"x": 1.0}, hub_port=module.server.port, extra=state_dir_keys(tmp_path),
                actuator=f"max_slew_um_per_s = {rate}\nverify = true")
    cells.append(cell)
    cell.target(400.0)
    wait_until(lambda: module.register() == raw_for(8.0), 10, "the register at 8 V")
    wait_until(lambda: cell.bus.status()["actuator"]["last_voltage_v"] == pytest.approx(8.0), 5, "8 V confirmed")
    cell.restart_after_kill()
    opened = cell.daemon.wait_log("actuator_open")
    assert opened["known_from"] == "read back" and opened["voltage_v"] == pytest.approx(8.0), opened
    assert cell.daemon.wait_log("output_proved")["by"] == "state"
    assert cell.bus.status()["actuator"]["proved_by"] == "state"
    since = len(module.stamps)
    cell.target(420.0)  # 8.4 V
    wait_until(lambda: module.register() == raw_for(8.4), 10, "the register at 8.4 V")
    writes = module.written(since)
    assert all(raw >= raw_for(8.0) for _, raw in writes), writes  # never back to 0 V, or anywhere below 8 V
    assert_slewed(writes, rate, from_raw=raw_for(8.0))


def test_a_read_back_the_state_file_contradicts_is_refused_until_an_operator_confirms_it(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 400.0
    cell = Cell(tmp_path, terms={"x": 1.0}, hub_port=module.server.port, extra=state_dir_keys(tmp_path),
                actuator=f"max_slew_um_per_s = {rate}\nverify = true")
    cells.append(cell)
    cell.target(0.0)  # 0 V written: the state file says so
    wait_until(lambda: cell.bus.status()["actuator"]["writes"] >= 1, 5, "0 V written")
    cell.daemon.proc.kill()
    module.hold(raw_for(10.0))  # meanwhile the module claims 10 V (another program, or a read-back that lies)
    cell.restart_after_kill()
    ok, answer = cell.bus.query({"x_um": 100.0, "id": 7})
    assert not ok and answer["kind"] == "actuator_fault", answer
    assert "read back 10.0000 V, but 0.0000 V was the last value written (state file)" in answer["error"], answer
    assert "nanodrift confirm-output --config <the config> --axis x --voltage" in answer["error"], answer
    actuator = cell.bus.status()["actuator"]
    assert actuator["state"] == "fault" and str(tmp_path / "state") in actuator["reason"], actuator
    assert module.written() == [] and module.register() == raw_for(10.0)  # nothing written

    confirmed = confirm_output(cell.config_path, [tmp_path / "plugins"], "--axis", "x", "--voltage", "10.0")
    assert confirmed.returncode == 0 and "confirmed at 10 V" in confirmed.stdout, confirmed.stderr
    # the daemon's own retry (seconds apart) believes it: a status query every 50 ms, not every 10 ms, sees it
    wait_until(lambda: cell.bus.status()["actuator"]["state"] == "ok", 15, "the daemon believes the confirmed 10 V",
               interval=0.05)
    assert module.written() == []  # believing moves nothing
    proved = cell.daemon.wait_log("output_proved")
    assert proved["by"] == "operator" and proved["voltage_v"] == pytest.approx(10.0), proved
    cell.target(480.0)  # 9.6 V, ramped down from the confirmed 10 V
    wait_until(lambda: module.register() == raw_for(9.6), 10, "the register at 9.6 V")
    assert_slewed(module.written(), rate, from_raw=raw_for(10.0))


#: the stated tolerance of a position sensor's proof: the model's worst correction (none: q = x) and the sensor's
#: uncertainty
PROOF_TOLERANCE_UM = 5.0


def restarted_at_8_v_without_the_state_file(root: Path, module: OutputModule, cells: list[Cell], rate: float, *,
                                            sensor_um: float, sensor_age_s: float = 0.0) -> tuple[Cell, int]:
    """A cell with a position sensor whose output an earlier run left at 8 V and whose state file is lost (the
    module holds 8 V; the state directory has no record of the axis), its sensor reading ``sensor_um``
    (``sensor_age_s`` old), started: the cell and the module's stamp count at its start.

    The earlier run is not a daemon of its own: a run killed at 8 V leaves exactly the register at 8 V, and its
    state file, which this scenario deletes; what the daemon starting here reads (the register, no record, the
    sensor) is the same, and its start (the proof, the first writes) is a fresh daemon's, as it was."""
    module.hold(raw_for(8.0))  # what the killed run left in the register (the stamps start afresh: none yet)
    cell = Cell(root, terms={"x": 1.0}, hub_port=module.server.port, extra=state_dir_keys(root), position=True,
                actuator=f"max_slew_um_per_s = {rate}\nverify = true\n"
                         f"position_proof_tolerance_um = {PROOF_TOLERANCE_UM}",
                sensor_values={"P": sensor_um}, sensor_age={"P": sensor_age_s},
                ready=("T1", "T2", *(("P",) if sensor_age_s == 0.0 else ())))  # a stale P is never ok
    cells.append(cell)
    return cell, 0


def test_without_the_state_file_a_position_sensor_reading_where_8_v_puts_the_stage_resumes_from_8_v(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate = 400.0
    cell, since = restarted_at_8_v_without_the_state_file(tmp_path, module, cells, rate, sensor_um=401.5)
    opened = cell.daemon.wait_log("actuator_open")
    assert opened["known_from"] == "position sensor" and opened["voltage_v"] == pytest.approx(8.0), opened
    proved = cell.daemon.wait_log("output_proved")
    assert proved["by"] == "position_sensor" and proved["sensor"] == "P", proved
    assert proved["measured_um"] == pytest.approx(401.5) and proved["implied_um"] == pytest.approx(400.0), proved
    assert proved["tolerance_um"] == PROOF_TOLERANCE_UM and "on a first start" in proved["unconfirmed"], proved
    actuator = cell.bus.status()["actuator"]
    assert actuator["state"] == "ok" and actuator["proved_by"] == "position_sensor", actuator
    assert module.written(since) == []  # believing moves nothing
    cell.target(420.0)  # 8.4 V
    wait_until(lambda: module.register() == raw_for(8.4), 10, "the register at 8.4 V")
    writes = module.written(since)
    assert all(raw >= raw_for(8.0) for _, raw in writes), writes  # no jump back to 0 V, or anywhere below 8 V
    assert_slewed(writes, rate, from_raw=raw_for(8.0))  # the first write within the slew of 8 V


def test_without_the_state_file_a_position_sensor_reading_far_from_8_v_proves_nothing_and_nothing_is_written(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    cell, since = restarted_at_8_v_without_the_state_file(tmp_path, module, cells, 400.0, sensor_um=100.0)
    ok, answer = cell.bus.query({"x_um": 420.0, "id": 7})
    assert not ok and answer["kind"] == "actuator_fault", answer
    assert ("read back 8.0000 V means q 400.000 µm, but the position sensor measures 100.000 µm (300.000 µm apart; "
            f"position_proof_tolerance_um = {PROOF_TOLERANCE_UM:g} µm) (sensor P)") in answer["error"], answer
    assert "nanodrift confirm-output --config <the config> --axis x --voltage" in answer["error"], answer
    # the daemon retries the proof on its own: still refused after more attempts, and nothing is ever written
    wait_until(lambda: cell.bus.status()["actuator"]["failures"] >= 3, 15, "three attempts to prove the output",
               interval=0.05)  # attempts seconds apart: a status query every 50 ms, not every 10 ms
    actuator = cell.bus.status()["actuator"]
    assert actuator["state"] == "fault" and actuator["proved_by"] is None, actuator
    assert module.written(since) == [] and module.register() == raw_for(8.0)
    assert cell.daemon.log_events("output_proved") == []


def test_a_stale_position_reading_proves_nothing_until_a_fresh_one_agrees(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    cell, since = restarted_at_8_v_without_the_state_file(tmp_path, module, cells, 400.0, sensor_um=400.0,
                                                          sensor_age_s=30.0)
    ok, answer = cell.bus.query({"x_um": 420.0, "id": 7})
    assert not ok and answer["kind"] == "actuator_fault", answer
    assert "not proved by a position sensor: its position sensor P is stale (last reading" in answer["error"], answer
    assert module.written(since) == [] and cell.daemon.log_events("output_proved") == []
    # the sensor reads again, fresh (a new value: the same one since the stale stamp would be frozen): the daemon's
    # retry proves 8 V
    cell.sensors.write(values={**cell.sensors.doc["values"], "P": 400.3}, age={"P": 0.0})
    wait_until(lambda: cell.bus.status()["actuator"]["state"] == "ok", 15, "8 V proved by a fresh reading",
               interval=0.05)  # the daemon's retry: a status query every 50 ms, not every 10 ms
    assert cell.daemon.wait_log("output_proved")["by"] == "position_sensor"
    assert module.written(since) == [] and module.register() == raw_for(8.0)


def test_confirm_output_refuses_a_voltage_outside_the_limits_and_an_unknown_axis(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    # confirm-output reads the config and writes a state file; it never talks to a daemon (nor opens the device):
    # the cell's config and files, no daemon started
    cell = Cell(tmp_path, terms={"x": 1.0}, hub_port=module.server.port, extra=state_dir_keys(tmp_path),
                actuator="verify = true", start=False)
    cells.append(cell)
    outside = confirm_output(cell.config_path, [tmp_path / "plugins"], "--voltage", "40")
    assert outside.returncode == 2 and "--voltage 40: outside axis x's [v_min, v_max] = [-2, 12] V" in outside.stderr
    unknown = confirm_output(cell.config_path, [tmp_path / "plugins"], "--axis", "y", "--voltage", "1")
    assert unknown.returncode == 2 and "--axis y: the cell's axes are x" in unknown.stderr, unknown.stderr
    assert not (tmp_path / "state" / f"output-{cell.cell}-x.json").exists()  # a refused confirmation writes nothing


# --- 8. a safe stop per axis ------------------------------------------------------------------------------


def xy_on_two_modules(root: Path, x_port: int, y_port: int, zenoh_port: int, cell: str,
                      positions_um: dict[str, float] | None = None) -> Path:
    """An XY cell, each axis on its own module; ``positions_um``: each axis' position sensor (``P<axis>``) reads
    it, and proves a read-back within :data:`PROOF_TOLERANCE_UM`."""
    model = root / "model.json"
    write_cell_model(model, ("x", "y"))
    positions = {f"P{axis}": um for axis, um in (positions_um or {}).items()}
    readings = SensorFile(root / "sensors.json", {**TEMPS, **positions}).path
    proof = f"position_proof_tolerance_um = {PROOF_TOLERANCE_UM}\n" if positions_um else ""
    axes = "".join(
        f'[[axes]]\nname = "{axis}"\nmin_um = 0.0\nmax_um = 480.0\n[axes.actuator]\nkind = "modbus"\nhub = "{hub}"\n'
        f"address = {ADDRESS}\nscale = 0.001\nvolts_per_um = 0.02\nmax_slew_um_per_s = 400.0\nsafe_voltage_v = 0.0\n"
        + proof for axis, hub in (("x", "mx"), ("y", "my")))
    hubs = "".join(f'[[hubs]]\nname = "{hub}"\nhost = "127.0.0.1"\nport = {port}\ntimeout_s = 0.3\n'
                   for hub, port in (("mx", x_port), ("my", y_port)))
    sensors = "".join(f'[[sensors]]\nname = "{ch}"\nkind = "file"\npath = "{readings}"\ninterval_s = 0.05\n'
                      "max_age_s = 2.0\ntimeout_s = 0.5\n" for ch in TEMPS)
    sensors += "".join(f'[[sensors]]\nname = "{ch}"\nrole = "position"\naxis = "{ch[1]}"\nkind = "file"\n'
                       f'path = "{readings}"\ninterval_s = 0.05\nmax_age_s = 2.0\ntimeout_s = 0.5\n'
                       for ch in positions)
    config = root / "xy.toml"
    config.write_text(f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zenoh_port}"]\n'
                      f'multicast_scouting = false\n[model]\npath = "{model}"\n{axes}{hubs}{sensors}')
    return config


@contextlib.contextmanager
def serving_xy(root: Path, config: Path, zenoh_port: int, cell: str,
               channels: tuple[str, ...]) -> Iterator[tuple[Daemon, Client]]:
    """The daemon of ``config`` serving, and a client that has seen ``channels`` ready; both ended on the way out."""
    daemon = Daemon(["--config", str(config)], root / "daemon.log", [install_file_plugin(root / "plugins")])
    client: Client | None = None
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(zenoh_port, cell)
        client.wait_alive()
        client.wait_ready(channels)
        yield daemon, client
    finally:
        if client is not None:
            client.close()
        daemon.stop()


def test_sigterm_with_a_dead_y_module_still_takes_x_to_its_safe_voltage(tmp_path: Path) -> None:
    x_module, y_module = OutputModule(), OutputModule()
    zenoh_port, cell = free_port(), f"xy{free_port()}"
    config = xy_on_two_modules(tmp_path, x_module.server.port, y_module.server.port, zenoh_port, cell)
    try:
        with serving_xy(tmp_path, config, zenoh_port, cell, tuple(TEMPS)) as (daemon, client):
            ok, answer = client.query({"x_um": 300.0, "y_um": 300.0, "id": 1})
            assert ok, answer
            wait_until(lambda: client.status()["axes"]["y"]["actuator"]["writes"] >= 1
                       and x_module.register() == raw_for(answer["voltage_v"]["x"]), 10, "both axes written")
            assert x_module.register() > raw_for(5.0)
            y_module.close()  # y's module dies
            daemon.signal(signal.SIGTERM)
            # x reaches its safe voltage (6 V at 8 V/s: under a second) while y is still retrying within its own
            # 20 s budget: one axis never waits for another (before: x stayed at 7.84 V for good)
            wait_until(lambda: x_module.register() == 0, 10, "x at its safe voltage, 0 V")
            assert daemon.proc.poll() is None, "the daemon gave up on y before the test could see x alone"
            assert_slewed(x_module.written(), 400.0)
            daemon.proc.kill()  # (y's budget is not this test's subject)
    finally:
        x_module.close()


def test_an_xy_cell_proves_each_axis_by_its_own_way_and_resumes_y_from_where_its_own_sensor_puts_it(
        tmp_path: Path) -> None:
    """No state file: x's module holds its power-up 0 V; y's holds 6 V, which y's own sensor (300 µm) proves, while
    x's sensor reads 0 µm: each axis is proved by its own witness, and y's first writes start from 6 V."""
    x_module, y_module = OutputModule(), OutputModule()
    y_module.hold(raw_for(6.0))
    zenoh_port, cell = free_port(), f"xy{free_port()}"
    config = xy_on_two_modules(tmp_path, x_module.server.port, y_module.server.port, zenoh_port, cell,
                               positions_um={"x": 0.0, "y": 300.0})
    try:
        with serving_xy(tmp_path, config, zenoh_port, cell, (*TEMPS, "Px", "Py")) as (daemon, client):
            proved = {line["axis"]: line for line in daemon.log_events("output_proved")}
            assert proved["x"]["by"] == "power_up" and proved["y"]["by"] == "position_sensor", proved
            assert proved["y"]["sensor"] == "Py" and proved["y"]["implied_um"] == pytest.approx(300.0), proved
            axes = client.status()["axes"]
            assert [axes[a]["actuator"]["proved_by"] for a in ("x", "y")] == ["power_up", "position_sensor"], axes
            ok, answer = client.query({"x_um": 20.0, "y_um": 320.0, "id": 1})  # y: 6 V -> 6.4 V
            assert ok, answer
            wait_until(lambda: y_module.register() == raw_for(answer["voltage_v"]["y"]), 10, "y at its goal")
            assert_slewed(y_module.written(), 400.0, from_raw=raw_for(6.0))  # no jump through 0 V
            assert all(raw >= raw_for(6.0) for _, raw in y_module.written()), y_module.written()
    finally:
        x_module.close()
        y_module.close()


# --- 9. ramps keep their rate on slow devices ---------------------------------------------------------------


def test_a_module_answering_in_60_ms_ramps_in_steps_that_cover_the_pause_and_never_faster(
        tmp_path: Path, module: OutputModule, cells: list[Cell]) -> None:
    rate, latency_s = 100.0, 0.060
    cell = Cell(tmp_path, terms={"x": 1.0}, hub_port=module.server.port,
                actuator=f"max_slew_um_per_s = {rate}\nverify = true")
    cells.append(cell)
    module.device.write_delay_s = latency_s
    cell.target(300.0)  # 0 -> 6 V at 2 V/s
    wait_until(lambda: module.register() == raw_for(6.0), 20, "the register at 6 V")
    writes = module.written()
    assert_slewed(writes, rate, from_raw=0)
    steps_um = [abs(b - a) * UM_PER_COUNT for (_, a), (_, b) in itertools.pairwise(writes)][:-1]  # not the last
    # each step covers at least the pause the daemon makes after a 60 ms write: 9 x 60 ms; before, a step could
    # cover 0.1 s at most, and a 60 ms module ramped at a quarter of the rate
    assert steps_um and min(steps_um) >= rate * LATENCY_PAUSES * latency_s - UM_PER_COUNT, steps_um
