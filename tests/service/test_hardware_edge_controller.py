"""Issue 26 items 2, 3 and 9 (duplicate keys), end to end: what a controller behind a ``serial_line``
template receives.

``nanodrift run`` as a process (the harness' ``file`` plugin for temperatures), a GCS controller on a
real pty (:class:`FakeGcsController`: its ``SVA 1 <number>`` stands in for ``MOV 1 <number>``; only the
lines it receives are asserted), and a client on Zenoh over 127.0.0.1.

- a ``q_um`` field is held to the command range the voltage limits mean, after its rounding;
- an ``x_um`` field carries the ramp's position (never the raw target ahead of the slew), and a target
  the compensation leaves outside the command range is refused, with nothing written;
- a target naming ``x_um`` twice is refused naming the key (``json.loads`` took the last one silently).
"""

from __future__ import annotations

import itertools
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
)
from helpers.serial_helpers import FakeGcsController

from nanodrift.model.model import FittedTerm, Model, Training, save_model
from nanodrift.model.terms import parse_term

VOLTS_PER_UM = 0.02
V_MAX = 9.196  # q_max = 459.8 um
Q_MAX_UM = V_MAX / VOLTS_PER_UM


def write_model(path: Path, offset_um: float) -> Path:
    """q = x + ``offset_um``."""
    terms = [FittedTerm(parse_term("x"), 1.0), FittedTerm(parse_term("1"), offset_um)]
    save_model(Model(terms=terms, training=Training(x_range=(0.0, 480.0), channel_ranges={}, rows=100,
                                                    t_span_s=3600.0),
                     provenance={"source": "tests/service/test_hardware_edge_templates.py"}), path)
    return path


class TemplateCell:
    """A daemon whose one axis is a ``serial_line`` controller on ``controller``'s pty."""

    def __init__(self, root: Path, controller: FakeGcsController, *, offset_um: float, keys: str) -> None:
        self.cell = f"tmpl{free_port()}"
        port = free_port()
        plugins = install_file_plugin(root / "plugins")
        model_path = write_model(root / "model.json", offset_um)
        sensors = SensorFile(root / "sensors.json", dict(TEMPS))
        actuator = (f'kind = "serial_line"\nport = "{controller.port}"\ntimeout_s = 0.3\n'
                    f"volts_per_um = {VOLTS_PER_UM}\nv_min = 0.0\nv_max = {V_MAX}\n{keys}")
        config = root / "nanodrift.toml"
        config.write_text(file_sensor_config(root, cell=self.cell, port=port, model_path=model_path,
                                             sensor_file=sensors.path, channels=("T1",), actuator=actuator))
        self.daemon = Daemon(["--config", str(config)], root / "daemon.log", [plugins])
        self.daemon.wait_log("serving", timeout=30)
        self.bus = Client(port, self.cell)
        self.bus.wait_alive()
        self.bus.wait_ready(("T1",))
        self._ids = itertools.count(1)

    def target(self, x_um: float) -> tuple[bool, dict[str, Any]]:
        return self.bus.query({"x_um": x_um, "id": next(self._ids)})

    def close(self) -> None:
        self.bus.close()
        self.daemon.stop()


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[FakeGcsController]:
    device = FakeGcsController(tmp_path / "ttyPI")
    yield device
    device.close()


def numbers_received(controller: FakeGcsController) -> list[float]:
    """The number of every ``SVA 1 <number>`` line the controller received, in order."""
    return [float(line.split()[2]) for line in controller.lines if line.startswith("SVA 1 ")]


def test_a_rounded_q_um_field_never_reaches_the_controller_beyond_the_voltage_limit(
        tmp_path: Path, controller: FakeGcsController) -> None:
    cell = TemplateCell(tmp_path, controller, offset_um=0.0, keys='command = "SVA 1 {q_um:.0f}\\n"\n')
    try:
        ok, answer = cell.target(459.552)  # q 459.552 um = 9.191 V, inside v_max 9.196 V; '.0f' would write 460
        assert ok, answer
        assert answer["voltage_v"] == pytest.approx(459.552 * VOLTS_PER_UM)
        wait_until(lambda: numbers_received(controller), 10, "the command at the controller")
        assert numbers_received(controller) == [459.0]  # rounded inward, not 460 (9.2 V > v_max)
    finally:
        cell.close()


def test_an_x_um_field_carries_the_ramp_and_a_target_outside_the_command_range_writes_nothing(
        tmp_path: Path, controller: FakeGcsController) -> None:
    rate = 400.0  # um/s: 100 -> 300 um in 0.5 s
    cell = TemplateCell(tmp_path, controller, offset_um=-22.5,
                        keys=f'command = "SVA 1 {{x_um:.4f}}\\n"\nmax_slew_um_per_s = {rate}\n')
    try:
        ok, answer = cell.target(100.0)  # the start is unknown: this first move is not ramped
        assert ok, answer
        wait_until(lambda: numbers_received(controller)[-1:] == [100.0], 10, "x 100 at the controller")
        first = len(numbers_received(controller))
        ok, answer = cell.target(300.0)
        assert ok, answer
        wait_until(lambda: numbers_received(controller)[-1:] == [300.0], 10, "x 300 at the controller")
        ramp = numbers_received(controller)[first:]
        # the ramp's sub-commands carry the ramp's position: rising from 100 to 300 in steps, never the
        # target ahead of the slew (on main every sub-command wrote 300.0000)
        assert len(ramp) >= 4, ramp
        assert all(b > a for a, b in itertools.pairwise([100.0, *ramp])), ramp
        assert ramp[0] < 200.0, ramp

        # q = 470 - 22.5 = 447.5 um is inside the limits, x = 470 um is not: writing it would be 9.4 V's worth
        before = len(controller.lines)
        cell.target(470.0)
        dropped = cell.daemon.wait_log("actuator_goal_dropped", timeout=10)
        # the goal's x_um is beyond what the template may carry: it is dropped whole before anything is written
        # (it used to ramp to the command range's edge and then fault, retrying for ever), the stage holds at 300
        assert dropped["held_v"] == pytest.approx((300.0 - 22.5) * VOLTS_PER_UM, abs=1e-3), dropped
        assert numbers_received(controller)[len(ramp) + first:] == [], controller.lines[before:]
        assert not cell.daemon.log_events("actuator_failed")
    finally:
        cell.close()


def test_check_config_strict_refuses_an_x_um_template(tmp_path: Path) -> None:
    config = tmp_path / "nanodrift.toml"
    model = write_model(tmp_path / "model.json", 0.0)
    config.write_text(f'cell = "c"\n[model]\npath = "{model}"\n'
                      '[actuator]\nkind = "serial_line"\nport = "/dev/ttyUSB9"\n'
                      'command = "MOV 1 {x_um:.4f}\\n"\nv_max = 9.196\n')
    loose = subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(config)],
                           capture_output=True, text=True, timeout=60)
    strict = subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", "--strict", str(config)],
                            capture_output=True, text=True, timeout=60)
    assert loose.returncode == 0, loose.stderr
    assert "{x_um:.4f}" in loose.stdout + loose.stderr
    assert strict.returncode != 0
    assert "actuator.command" in strict.stderr and "{x_um:.4f}" in strict.stderr, strict.stderr


def test_a_target_naming_a_key_twice_is_refused_naming_it_and_nothing_is_written(
        tmp_path: Path, controller: FakeGcsController) -> None:
    cell = TemplateCell(tmp_path, controller, offset_um=0.0, keys="")
    try:
        ok, error = cell.bus.query(b'{"x_um": 10, "id": 1, "x_um": 400}')  # an escape-free order the fast path skips
        assert not ok and error["kind"] == "bad_payload", error
        assert "names 'x_um' twice" in error["error"], error
        ok, error = cell.bus.query(b'{"x_um": 10, "x_um": 400, "id": 2}')
        assert not ok and "names 'x_um' twice" in error["error"], error
        ok, answer = cell.target(20.0)  # the next good target is served: only the bad one was refused
        assert ok, answer
        wait_until(lambda: numbers_received(controller), 10, "the good target at the controller")
        assert numbers_received(controller) == [pytest.approx(20.0 * VOLTS_PER_UM, abs=1e-4)]  # SVA of 0.4 V only
    finally:
        cell.close()
