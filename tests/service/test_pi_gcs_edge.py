"""The hardware edge with a PI controller as the output (``[actuator] kind = "pi_gcs"``), end to end: ``nanodrift
run`` as a process driving the GCS emulator on a real pty (``nanodrift.drivers.testing.pi_gcs_emulator``), a
client on Zenoh over 127.0.0.1. What the controller received is asserted, never what the daemon says:

- open loop: its servo, on at power-up, is switched off before the first SVA, and the daemon logs it;
  closed loop: off at power-up, switched on before the first MOV;
- every SVA (MOV) it received lies within the limits after formatting, each in one batch with ERR? and
  the read-back; between two of them it never moved faster than the slew; a target beyond v_max never
  reaches it;
- SIGTERM ramps it to the safe voltage (its position, in closed loop) at the configured rate, and it
  ends holding it;
- closed loop: a move's ``done`` says ``reached`` only once the controller answers ``ONT?`` with 1 (asked
  after the last MOV), and ``failed``, naming the axis, when it never does within the budget.
"""

from __future__ import annotations

import itertools
import signal
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.daemon_harness import Served, wait_until

from nanodrift import Client, MoveEnded
from nanodrift.config import STOP_TIMEOUT_S
from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice
from nanodrift.motion import RAMP_PERIOD_S
from nanodrift.service.actuation import ON_TARGET_BUDGET_S

V_MIN, V_MAX = -2.0, 9.0
VOLTS_PER_UM = 0.02
RATE_UM_PER_S = 100.0  # 150 um ramp up (and the safe ramp down) in 1.5 s: a loaded machine still writes several steps
RATE_V_PER_S = RATE_UM_PER_S * VOLTS_PER_UM


@pytest.fixture(params=["open_loop", "closed_loop"])
def controller(tmp_path: Path, request: pytest.FixtureRequest) -> Iterator[tuple[PiGcsEmulator, PiGcsPtyDevice, str]]:
    mode = request.param
    # open loop: an E-727 left with its servo on; closed loop: a controller that powers up in open loop
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(servo=mode == "open_loop")})
    device = PiGcsPtyDevice(tmp_path / "ttyPI", emulator)
    yield emulator, device, mode
    device.close()


def written_v(emulator: PiGcsEmulator, mode: str) -> list[tuple[float, float]]:
    """(arrival time, volts) of every SVA the controller received, or of every MOV as the volts it stands for."""
    if mode == "open_loop":
        return [(t, float(line.split()[2])) for t, line in emulator.stamped("SVA")]
    return [(t, float(line.split()[2]) * VOLTS_PER_UM) for t, line in emulator.stamped("MOV")]


def assert_within_slew(ramp: list[tuple[float, float]]) -> None:
    # a move from rest covers one ramp period in its first step; 50 ms of pty and scheduling jitter
    slack_v = RATE_V_PER_S * 0.050 + 1e-6
    for (t0, v0), (t1, v1) in itertools.combinations(ramp, 2):
        assert abs(v1 - v0) <= RATE_V_PER_S * (t1 - t0 + RAMP_PERIOD_S) + slack_v, (
            f"{v0} V -> {v1} V in {t1 - t0:.4f} s")


def test_the_controller_gets_the_servo_off_limited_slewed_commands_and_the_safe_ramp_on_stop(
        tmp_path: Path, controller: tuple[PiGcsEmulator, PiGcsPtyDevice, str]) -> None:
    emulator, device, mode = controller
    word, readback = ("SVA", ["SVA? 1"]) if mode == "open_loop" else ("MOV", ["MOV? 1", "OVF? 1"])
    keys = (f'kind = "pi_gcs"\ntransport = "serial"\nport = "{device.port}"\ntimeout_s = 0.5\nmode = "{mode}"\n'
            f"volts_per_um = {VOLTS_PER_UM}\nv_min = {V_MIN}\nv_max = {V_MAX}\n"
            f"max_slew_um_per_s = {RATE_UM_PER_S}\nsafe_voltage_v = 0.0\n")
    served = Served(tmp_path, "gcsedge", actuator=keys).start()
    try:
        ok, command = served.client.query({"x_um": 150.0, "id": 1})
        assert ok, command
        goal_v = round(command["voltage_v"], 6)
        goal_um = round(command["q_um"], 6)

        def held() -> float:
            return emulator.sva("1") if mode == "open_loop" else emulator.target_um("1") * VOLTS_PER_UM

        def arrived() -> bool:
            return (emulator.sva("1") == goal_v) if mode == "open_loop" else (emulator.target_um("1") == goal_um)

        wait_until(arrived, 10, f"the controller at the command ({goal_v} V, {goal_um} um)")
        goal_v = held()
        ok, refused = served.client.query({"x_um": 480.0, "id": 2})  # 9.15 V: beyond v_max = 9.0 V
        assert not ok and refused["kind"] == "voltage_limit", refused
        [switched] = served.daemon.log_events("pi_gcs_servo_switched")
        assert switched["servo"] == ("off" if mode == "open_loop" else "on")
        lines = emulator.received()
        servo_line = "SVO 1 0" if mode == "open_loop" else "SVO 1 1"
        assert lines.index(servo_line) < next(i for i, line in enumerate(lines) if line.startswith(f"{word} "))
        served.client.close()
        served.daemon.signal(signal.SIGTERM)
        assert served.daemon.proc.wait(STOP_TIMEOUT_S) == 0
    finally:
        served.close()

    written = written_v(emulator, mode)
    assert all(V_MIN <= volts <= V_MAX + 1e-9 for _, volts in written), written
    assert emulator.received("SVA" if mode == "closed_loop" else "MOV") == []  # one kind of motion command only
    lines = emulator.received()
    batch = 3 + len(readback)
    for i, line in enumerate(lines):  # each command in one batch with its error queries and read-back
        if line.startswith(f"{word} "):
            assert lines[i - 1:i - 1 + batch] == ["ERR?", line, "ERR?", *readback], lines[i - 1:i - 1 + batch]
    peak = next(i for i, (_, v) in enumerate(written) if v == pytest.approx(goal_v, abs=1e-9))
    up = written[:peak + 1]
    # a ramp, not a jump: intermediate values, each step within the slew of the time it took (a loaded machine
    # writes fewer, longer steps)
    assert len(up) >= 4 and all(a < b for (_, a), (_, b) in itertools.pairwise(up)), up
    assert_within_slew(up)
    down = written[peak:]
    assert down[-1][1] == 0.0 and held() == 0.0  # the safe voltage, held
    assert all(b <= a for (_, a), (_, b) in itertools.pairwise(down)), "the safe ramp is not monotonic"
    assert_within_slew(down)


def closed_loop_keys(port: str) -> str:
    return (f'kind = "pi_gcs"\ntransport = "serial"\nport = "{port}"\ntimeout_s = 0.5\nmode = "closed_loop"\n'
            f"volts_per_um = {VOLTS_PER_UM}\nv_min = {V_MIN}\nv_max = {V_MAX}\nmax_slew_um_per_s = 0\n"
            "safe_voltage_v = 0.0\n")


@pytest.mark.parametrize("settle_s", [0.4, 30.0])
def test_a_closed_loop_move_is_reached_only_once_the_controller_says_it_is_on_target(
        tmp_path: Path, settle_s: float) -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(servo=False)}, settle_s=settle_s)
    device = PiGcsPtyDevice(tmp_path / "ttyPI", emulator)
    served = Served(tmp_path, "gcsont", actuator=closed_loop_keys(device.port)).start()
    try:
        with Client(f"tcp/127.0.0.1:{served.port}", cell="gcsont") as client:
            if settle_s < ON_TARGET_BUDGET_S:
                command = client.move(150.0, timeout_s=20.0)
                ended_s = time.monotonic()
                [(mov_s, mov)] = [(t, line) for t, line in emulator.stamped("MOV") if line.startswith("MOV 1 ")][-1:]
                assert float(mov.split()[2]) == pytest.approx(command.q_um, abs=1e-6)
                asked = [t for t, _ in emulator.stamped("ONT?") if t > mov_s]
                assert asked, "done came without asking the controller whether it is on target"
                assert ended_s - mov_s >= settle_s  # not before the controller settled (a busy machine: later)
            else:
                with pytest.raises(MoveEnded) as ended:
                    client.move(150.0, timeout_s=20.0)
                assert ended.value.state == "failed" and "axis x" in str(ended.value), ended.value
                assert "on target" in str(ended.value)
                assert served.daemon.log_events("actuator_not_on_target")
    finally:
        served.close()  # its client's session too: a session left open keeps zenoh's threads (and the run) alive
        device.close()
