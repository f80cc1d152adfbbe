"""Issue 28's first must-hold: a one-axis and an XY cell calibrate (``nanodrift calibrate --config``), validate
and serve (``nanodrift run`` + :class:`nanodrift.Client`) with ``pi_gcs`` outputs, an ``attocube_ids`` position
sensor per axis and ``dcon`` thermocouples, each emulated behind its real transport and tied together by the
simulated cell's physics (``helpers.instrument_cell``).

What is asserted is what the emulated devices received: every value the PI controller was given lies within
the axis' limits and follows the slew from the one before; its servo is in the state the mode needs before
the first motion command and stays there; the IDS was asked each configured axis' displacement and the DCON
module its ``#AA`` line; the model file names the axes it was calibrated on; each served target ends with the
controller holding the command's value and the IDS seeing the stage at the target.
"""

from __future__ import annotations

import itertools
import json
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.daemon_harness import Daemon, free_port, wait_until
from helpers.instrument_cell import (
    DCON_ADDRESS,
    SLEW_UM_PER_S,
    TRAVEL_UM,
    V_MAX,
    V_MIN,
    VOLTS_PER_UM,
    Case,
    InstrumentCell,
    calibration_cycles,
)

from nanodrift import Client
from nanodrift.calibration.dataset import read_csv
from nanodrift.cli import main
from nanodrift.config import STOP_TIMEOUT_S
from nanodrift.model.cell_model import CellModel, load_any_model
from nanodrift.model.model import Model
from nanodrift.motion import RAMP_PERIOD_S

CASES = [
    Case("x-open-loop-tcp", ("x",), "open_loop", pi_transport="tcp", dcon_transport="serial", dcon_channels=4),
    Case("x-closed-loop-pty", ("x",), "closed_loop", pi_transport="serial", dcon_transport="tcp", dcon_channels=4),
    Case("xy-closed-loop-tcp", ("x", "y"), "closed_loop", pi_transport="tcp", dcon_transport="serial",
         dcon_channels=8),
]
CELL = "inst"
#: served through the daemon: every axis of a target (one-axis cells take the first coordinate)
TARGETS_UM = [(120.0, 300.0), (360.0, 90.0), (200.0, 200.0)]


@pytest.fixture(params=CASES, ids=lambda case: case.name)
def bench(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[InstrumentCell]:
    with InstrumentCell(tmp_path, request.param) as cell:
        yield cell


def received_v(bench: InstrumentCell, pi_axis: str) -> list[tuple[float, float]]:
    """(arrival time, volts) of every SVA the controller received for ``pi_axis``, or of every MOV as the volts
    it stands for (the position times the gain)."""
    word = "SVA" if bench.case.mode == "open_loop" else "MOV"
    out = []
    for t, line in bench.pi.stamped(word):
        _, axis, value = line.split()
        if axis == pi_axis:
            out.append((t, float(value) if word == "SVA" else float(value) * VOLTS_PER_UM))
    return out


def assert_within_slew(written: list[tuple[float, float]], what: str) -> None:
    """Between two consecutive values, never faster than the slew (a ramp's first write covers one ramp period;
    50 ms of scheduling jitter on a shared machine)."""
    rate_v_per_s = SLEW_UM_PER_S * VOLTS_PER_UM
    slack_v = rate_v_per_s * (RAMP_PERIOD_S + 0.050) + 1e-6
    for (t0, v0), (t1, v1) in itertools.pairwise(written):
        assert abs(v1 - v0) <= rate_v_per_s * (t1 - t0) + slack_v, f"{what}: {v0} V -> {v1} V in {t1 - t0:.4f} s"


def target_of(case: Case, point: tuple[float, float]) -> float | dict[str, float]:
    return point[0] if len(case.axes) == 1 else dict(zip(case.axes, point, strict=False))


def target_axis(case: Case, point: tuple[float, float], axis: str) -> float:
    return point[case.axes.index(axis)]


def held(bench: InstrumentCell, axis: str) -> float:
    """What the controller's ``axis`` holds now: volts (open loop) or micrometres (closed loop)."""
    pi_axis = bench.case.pi_axes[axis]
    return bench.pi.sva(pi_axis) if bench.case.mode == "open_loop" else bench.pi.target_um(pi_axis)


def stage_gains(model: Model | CellModel, axes: tuple[str, ...]) -> dict[str, float]:
    """Each axis' coefficient of its own position: the stage's gain as the model identified it."""
    models = {axes[0]: model} if isinstance(model, Model) else model.models
    return {axis: {ft.term.name: ft.coef for ft in models[axis].terms}.get(axis, 0.0) for axis in axes}


def sensors_ok(client: Client, names: list[str]) -> bool:
    sensors = client.status(timeout_s=1.0)["sensors"]
    return all(sensors.get(name, {}).get("state") == "ok" for name in names)


def test_the_cell_calibrates_validates_and_serves_through_its_instruments(
        bench: InstrumentCell, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    case = bench.case
    zenoh_port = free_port()
    model, data = tmp_path / "model.json", tmp_path / "cal.csv"
    config = tmp_path / "inst.toml"
    config.write_text(bench.config_text(cell=CELL, zenoh_port=zenoh_port, model=model))

    assert main(["calibrate", "--config", str(config), "--out", str(model), "--data", str(data)]) == 0
    capsys.readouterr()
    calibrated = load_any_model(model)
    assert (isinstance(calibrated, CellModel) and calibrated.axes == case.axes) or (
        isinstance(calibrated, Model) and case.axes == ("x",))
    # the stage's gain, identified through the PI output and the IDS (pm -> um): 1 um of command per um
    assert stage_gains(calibrated, case.axes) == pytest.approx(dict.fromkeys(case.axes, 1.0), abs=0.02)
    recorded = read_csv(data)
    assert len(recorded) == 17 * calibration_cycles(case.axes) and recorded.extra["valid"].all()

    assert main(["validate", "--config", str(config), "--model", str(model), "--cycles", "1", "--json"]) == 0
    (result,) = json.loads(capsys.readouterr().out)["tests"]
    if len(case.axes) == 1:
        # one short sweep cannot promise an improvement; a wrong gain, sign or axis would be micrometres off. The
        # room runs 3000x wall time, so a busy machine's 20 ms of scheduling is a minute of drift: one point of a
        # loaded run was 598 nm off; the gain above is the precise check of the model
        assert len(result["points"]) == 7 and all(abs(p["accuracy_nm"]) < 1500.0 for p in result["points"]), result
        assert result["invalid_steps"] == 0
    else:
        scores = result["against_interferometer"]
        # the stacked stage's crosstalk (~1 um uncompensated) is what the XY model removes
        assert scores["with"]["accuracy_nm"] < 0.5 * scores["without"]["accuracy_nm"], scores
        assert len(scores["with"]["points"]) == 5

    asked = len(bench.ids.requests), len(bench.dcon.requests) if bench.dcon is not None else 0
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        with Client(f"tcp/127.0.0.1:{zenoh_port}", cell=CELL) as client:
            wait_until(lambda: sensors_ok(client, [*case.thermocouple_channels, *case.position_sensors.values()]),
                       20, "every sensor ok in the daemon's status", interval=0.05)
            for point in TARGETS_UM:
                command = client.move(target_of(case, point), timeout_s=10.0)  # returns on done "reached"
                for axis in case.axes:
                    q_um = command.q_um if len(case.axes) == 1 else command.q_um[axis]
                    voltage_v = command.voltage_v if len(case.axes) == 1 else command.voltage_v[axis]
                    want = voltage_v if case.mode == "open_loop" else q_um
                    assert held(bench, axis) == pytest.approx(want, abs=1e-6), (axis, command)
                    # and the stage went there, as the IDS sees it (the room's drift is ~1 um uncompensated)
                    assert bench.position_um(axis) == pytest.approx(target_axis(case, point, axis), abs=1.0)
        daemon.signal(signal.SIGTERM)
        assert daemon.proc.wait(STOP_TIMEOUT_S) == 0
    finally:
        daemon.stop()

    # -- the PI controller: one kind of motion command, limits, slew, servo, per axis ------------------
    servo_line = {"open_loop": "SVO {} 0", "closed_loop": "SVO {} 1"}[case.mode]
    word = "SVA" if case.mode == "open_loop" else "MOV"
    lines = bench.pi.received()
    assert bench.pi.received("SVA" if case.mode == "closed_loop" else "MOV") == []
    for axis, pi_axis in case.pi_axes.items():
        written = received_v(bench, pi_axis)
        assert len(written) > 17 * calibration_cycles(case.axes), f"axis {axis}: {len(written)} values"
        assert all(V_MIN <= v <= V_MAX for _, v in written), (axis, written)
        if case.mode == "closed_loop":
            assert all(TRAVEL_UM[0] <= v / VOLTS_PER_UM <= TRAVEL_UM[1] for _, v in written), (axis, written)
        assert_within_slew(written, f"axis {axis}")
        first_motion = next(i for i, line in enumerate(lines) if line.startswith(f"{word} {pi_axis} "))
        assert servo_line.format(pi_axis) in lines[:first_motion]  # the servo as the mode needs it, before motion
        assert bench.pi.axes[pi_axis].servo == (case.mode == "closed_loop")
        assert held(bench, axis) == 0.0  # the safe voltage (its position in closed loop), held after SIGTERM
    # -- the IDS and the DCON module were asked, by the procedures and by the daemon -------------------
    for ids_axis in case.ids_axes.values():
        assert ("com.attocube.ids.displacement.getAxisDisplacement", [ids_axis]) in bench.ids.requests
    assert bench.dcon is not None
    assert {line for line in bench.dcon.requests if line.startswith("#")} == {f"#{DCON_ADDRESS:02X}"}
    assert len(bench.ids.requests) > asked[0] and len(bench.dcon.requests) > asked[1]
