"""The hardware edge with a PI controller as the output (``[actuator] kind = "pi_gcs"``), end to end: ``nanodrift
run`` as a process driving the GCS emulator on a real pty (``nanodrift.drivers.testing.pi_gcs_emulator``), a
client on Zenoh over 127.0.0.1. What the controller received is asserted, never what the daemon says:

- its servo, on at power-up, is switched off before the first SVA (open loop), and the daemon logs it;
- every SVA it received lies within [v_min, v_max] after formatting, each followed by ERR? and SVA? in
  the same batch; between two SVAs it never moved faster than the slew; a target beyond v_max never
  reaches it;
- SIGTERM ramps it to the safe voltage at the configured rate, and it ends holding it.
"""

from __future__ import annotations

import itertools
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest
from helpers.daemon_harness import Served, wait_until

from nanodrift.config import STOP_TIMEOUT_S
from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice
from nanodrift.motion import RAMP_PERIOD_S

V_MIN, V_MAX = -2.0, 9.0
VOLTS_PER_UM = 0.02
RATE_UM_PER_S = 100.0
RATE_V_PER_S = RATE_UM_PER_S * VOLTS_PER_UM


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[tuple[PiGcsEmulator, PiGcsPtyDevice]]:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(servo=True)})  # an E-727 with its stage: servo on
    device = PiGcsPtyDevice(tmp_path / "ttyPI", emulator)
    yield emulator, device
    device.close()


def sva_values(emulator: PiGcsEmulator) -> list[tuple[float, float]]:
    """(arrival time, volts) of every SVA the controller received."""
    return [(t, float(line.split()[2])) for t, line in emulator.stamped("SVA")]


def assert_within_slew(ramp: list[tuple[float, float]]) -> None:
    # a move from rest covers one ramp period in its first step; 50 ms of pty and scheduling jitter
    slack_v = RATE_V_PER_S * 0.050 + 1e-6
    for (t0, v0), (t1, v1) in itertools.combinations(ramp, 2):
        assert abs(v1 - v0) <= RATE_V_PER_S * (t1 - t0 + RAMP_PERIOD_S) + slack_v, (
            f"{v0} V -> {v1} V in {t1 - t0:.4f} s")


def test_the_controller_gets_the_servo_off_limited_slewed_commands_and_the_safe_ramp_on_stop(
        tmp_path: Path, controller: tuple[PiGcsEmulator, PiGcsPtyDevice]) -> None:
    emulator, device = controller
    keys = (f'kind = "pi_gcs"\ntransport = "serial"\nport = "{device.port}"\ntimeout_s = 0.5\n'
            f"volts_per_um = {VOLTS_PER_UM}\nv_min = {V_MIN}\nv_max = {V_MAX}\n"
            f"max_slew_um_per_s = {RATE_UM_PER_S}\nsafe_voltage_v = 0.0\n")
    served = Served(tmp_path, "gcsedge", actuator=keys).start()
    try:
        ok, command = served.client.query({"x_um": 150.0, "id": 1})
        assert ok, command
        goal_v = round(command["voltage_v"], 6)
        wait_until(lambda: emulator.sva("1") == goal_v, 10, f"the controller at {goal_v} V")
        ok, refused = served.client.query({"x_um": 480.0, "id": 2})  # 9.15 V: beyond v_max = 9.0 V
        assert not ok and refused["kind"] == "voltage_limit", refused
        [switched] = served.daemon.log_events("pi_gcs_servo_switched")
        assert switched["servo"] == "off"
        lines = emulator.received()
        assert lines.index("SVO 1 0") < next(i for i, line in enumerate(lines) if line.startswith("SVA "))
        served.client.close()
        served.daemon.signal(signal.SIGTERM)
        assert served.daemon.proc.wait(STOP_TIMEOUT_S) == 0
    finally:
        served.daemon.stop()

    written = sva_values(emulator)
    assert all(V_MIN <= volts <= V_MAX for _, volts in written), written
    lines = emulator.received()
    for i, line in enumerate(lines):  # each SVA in one batch with its error query and read-back
        if line.startswith("SVA "):
            assert lines[i - 1:i + 3] == ["ERR?", line, "ERR?", "SVA? 1"], lines[i - 1:i + 3]
    peak = next(i for i, (_, v) in enumerate(written) if v == goal_v)
    up = written[:peak + 1]
    assert len(up) > 5 and all(a < b for (_, a), (_, b) in itertools.pairwise(up)), up  # a ramp, not a jump
    assert_within_slew(up)
    down = written[peak:]
    assert down[-1][1] == 0.0 and emulator.sva("1") == 0.0  # the safe voltage, held
    assert all(b <= a for (_, a), (_, b) in itertools.pairwise(down)), "the safe ramp is not monotonic"
    assert_within_slew(down)
