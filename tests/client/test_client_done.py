"""``nanodrift.Client`` on the daemon's ``done`` and ``stop``: ``move()`` returns once its ``done`` says
``reached``, ``stop()`` from another thread ends a ramp in flight (``MoveEnded``, state ``stopped``), and the
README's *Python API* script moves the simulated cell, one axis and XY, through five targets.

Real daemons (``nanodrift run`` subprocesses), real Zenoh over 127.0.0.1, free ports; every wait is on an
event (a sample, a reply, a thread's end), bounded.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh
from helpers.daemon_harness import REPO, TEMPS, Daemon, Served, expected_q, free_port, wait_until

from nanodrift import Client, Command, MoveEnded

README = REPO / "README.md"
SLEW_UM_PER_S = 20.0  # a 0 -> 480 µm move ramps for 24 s: long enough to be stopped midway


def endpoint(port: int) -> str:
    return f"tcp/127.0.0.1:{port}"


def simulated_config(port: int, cell: str, *, axes: str = "", actuator: str = "") -> str:
    """The simulated cell (its default sensors and model) on a free port; ``actuator``: ``[actuator]`` keys."""
    return (f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            + (f"[actuator]\n{actuator}\n" if actuator else "")
            + '[simulation]\nscenario = "room"\nspeed = 1.0\nseed = 0\n' + (f'axes = "{axes}"\n' if axes else ""))


class SimulatedCell:
    def __init__(self, root: Path, cell: str, *, axes: str = "", actuator: str = "") -> None:
        self.cell = cell
        self.port = free_port()
        config = root / f"{cell}.toml"
        config.write_text(simulated_config(self.port, cell, axes=axes, actuator=actuator))
        self.daemon = Daemon(["--config", str(config)], root / f"{cell}.log")
        self.daemon.wait_log("serving", timeout=30)
        with Client(endpoint(self.port), cell=cell) as client:
            def ready() -> bool:
                try:
                    sensors = client.status(timeout_s=1.0)["sensors"]
                except TimeoutError:
                    return False
                return all(s["state"] == "ok" for s in sensors.values() if s["role"] == "temperature")

            wait_until(ready, 30, f"cell {cell}'s temperatures ok", interval=0.1)

    def close(self) -> int:
        return self.daemon.stop()


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    s = Served(tmp_path_factory.mktemp("done"), "donecell").start()
    yield s
    s.close()


def test_move_returns_the_command_once_its_done_says_reached(served: Served) -> None:
    with Client(endpoint(served.port), cell=served.cell) as cell:
        for x in (100.0, 240.0):
            command = cell.move(x, timeout_s=10.0)
            assert isinstance(command, Command) and command.q_um == pytest.approx(expected_q(x, TEMPS), abs=1e-9)
            assert command.done is not None and command.done["state"] == "reached"
            assert command.done["id"] == command.id and command.done["error"] is None
            assert command.done["voltage_v"] == pytest.approx(command.voltage_v)


@pytest.fixture(scope="module")
def ramping(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimulatedCell]:
    cell = SimulatedCell(tmp_path_factory.mktemp("ramp"), "ramp",
                         actuator=f'kind = "simulated"\nmax_slew_um_per_s = {SLEW_UM_PER_S}')
    yield cell
    cell.close()


def test_stop_from_another_thread_ends_a_move_in_flight(ramping: SimulatedCell) -> None:
    with Client(endpoint(ramping.port), cell=ramping.cell) as cell:
        start = cell.move(0.0, timeout_s=60.0)  # where the ramp starts (reached: the output holds it)
        assert start.done is not None and start.done["state"] == "reached"
        ended: list[BaseException] = []
        answered = threading.Event()
        moving = threading.Thread(target=lambda: _move(cell, 480.0, ended, answered))

        def on_command(sample: zenoh.Sample) -> None:
            if json.loads(sample.payload.to_bytes()).get("x_um") == 480.0:
                answered.set()

        subscriber = cell.session.declare_subscriber(f"{cell.keys.prefix}/command", on_command)
        try:
            moving.start()
            assert answered.wait(10), "the 480 µm target was never answered"
            held = cell.stop()  # returns once the daemon answered; every output holds where it is
            moving.join(10)
            assert not moving.is_alive(), "stop() did not end the move waiting in the other thread"
        finally:
            subscriber.undeclare()
        assert len(ended) == 1 and isinstance(ended[0], MoveEnded), ended
        error = ended[0]
        assert error.state == "stopped" and error.error is None and error.command.target == 480.0
        assert held["held"] is True and held["voltage_v"] < error.command.voltage_v  # the 24 s ramp never got there
        assert error.command.done is not None and error.command.done["voltage_v"] < error.command.voltage_v
        assert cell.status()["actuator"]["last_voltage_v"] < error.command.voltage_v
        again = cell.move(10.0, timeout_s=60.0)  # the next target moves again
        assert again.done is not None and again.done["state"] == "reached"


def _move(cell: Client, x: float, ended: list[BaseException], answered: threading.Event) -> None:
    try:
        cell.move(x, timeout_s=60.0)
    except BaseException as error:  # the test asserts which
        ended.append(error)
    finally:
        answered.set()


def readme_script() -> str:
    """The README's *Python API* script (the block after the ``<!-- python-api-script -->`` marker)."""
    text = README.read_text()
    match = re.search(r"<!-- python-api-script -->\n```python\n(.*?)```", text, re.S)
    assert match, "README: no python block after <!-- python-api-script -->"
    return match.group(1)


def run_script(script: str, port: int) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", script.replace("tcp/127.0.0.1:7447", endpoint(port))],
                          capture_output=True, text=True, cwd=REPO, timeout=300)


def test_the_readme_script_moves_the_simulated_cell_through_five_targets(tmp_path: Path) -> None:
    script = readme_script()
    assert len(script.strip().splitlines()) <= 12 and 'cell="cell0"' in script
    cell = SimulatedCell(tmp_path, "cell0")
    try:
        result = run_script(script, cell.port)
    finally:
        assert cell.close() == 0
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len([line for line in lines if " µm -> q " in line]) == 5, result.stdout
    assert lines[-1] == "cell0", result.stdout


XY_SCRIPT = """\
from nanodrift import Client, MoveEnded, Refused

with Client("tcp/127.0.0.1:7447", cell="xy0") as cell:
    for x, y in ((0.0, 0.0), (120.0, 400.0), (240.0, 100.0), (360.0, 300.0), (480.0, 480.0)):
        try:
            cmd = cell.move({"x": x, "y": y})
        except (Refused, MoveEnded) as error:
            print(f"{x:g},{y:g} µm: {error}")
            continue
        print(f"{x:g},{y:g} µm -> q x {cmd.q_um['x']:.4f} y {cmd.q_um['y']:.4f} µm, {cmd.done['state']}")
    print(cell.status()["cell"])
"""


def test_a_ten_line_script_moves_the_simulated_xy_cell_through_five_targets(tmp_path: Path) -> None:
    cell = SimulatedCell(tmp_path, "xy0", axes="xy")
    try:
        result = run_script(XY_SCRIPT, cell.port)
    finally:
        assert cell.close() == 0
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert len([line for line in lines if line.endswith(" µm, reached")]) == 5, result.stdout
    assert lines[-1] == "xy0", result.stdout
