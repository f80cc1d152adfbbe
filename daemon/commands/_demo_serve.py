"""``nanodrift demo``, its serving step (step 4 of :mod:`nanodrift.commands.demo`): the daemon on the calibrated
model and a client over Zenoh; the position the interferometer reads after each target is averaged over the
end of the hold, as the paper's procedure does.
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from nanodrift.calibration.plans import PAPER_TIMING
from nanodrift.cell_view import measured_of
from nanodrift.client import Client, Refused, json_object
from nanodrift.commands._cell import scenario_seed
from nanodrift.drivers.local_port import free_port
from nanodrift.errors import UserError

HOLD_S = PAPER_TIMING.hold_s  # paper III.B: each step is held 25 s, the last 5 s averaged
WINDOW_S = PAPER_TIMING.window_s
#: the room and the targets of the serving step (a room inside the training range)
SERVE_SCENARIO = "test2"
SERVE_TARGETS_UM = (0.0, 240.0, 480.0, 360.0, 120.0)  # five held targets: enough for the health unit to judge
SERVE_CELL = "demo"
LOG_TAIL_LINES = 20


def demo_config(cell: str, listen: str, model_path: Path, scenario: str, speed: float, seed: int,
                simulated_cell: str = "ideal") -> str:
    """A simulated cell whose polls are spaced in simulated time so the sped-up daemon stays light."""
    sensors = "".join(
        f'[[sensors]]\nname = "{name}"\nkind = "simulated"\ninterval_s = 5.0\nmax_age_s = 30.0\n'
        for name in ("T1", "T2", "T3", "T4")
    )
    return (
        f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["{listen}"]\nmulticast_scouting = false\n'
        f'[model]\npath = "{model_path}"\n'
        f'[simulation]\nscenario = "{scenario}"\nspeed = {speed}\nseed = {seed}\n'
        + ("" if simulated_cell == "ideal" else f'cell = "{simulated_cell}"\n')
        + f"{sensors}"
        '[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "simulated"\ninterval_s = 1.0\n'
        "max_age_s = 5.0\n"
    )


class CellClient:
    """A :class:`nanodrift.Client` of the demo's cell (targets through ``compensate``, not waiting for ``done``:
    the demo times its holds on the cell clock itself), and positions from ``sensors/position``."""

    def __init__(self, connect: str, cell: str, alive: Callable[[], bool] | None = None,
                 timeout_s: float = 30.0) -> None:
        deadline = time.monotonic() + timeout_s
        while True:  # the daemon starts in its own process: a client-mode session opens once it listens
            if alive is not None and not alive():
                raise UserError("the demo's daemon exited before it listened")
            try:
                self.client = Client(connect, cell)
                break
            except ConnectionError as error:
                if time.monotonic() > deadline:
                    raise UserError(f"the demo's daemon never listened: {error}") from None
                time.sleep(0.1)
        self.keys = self.client.keys
        self._alive = alive
        self._cond = threading.Condition()
        self.positions: list[tuple[float, float]] = []  # (cell clock t, µm)
        self._sub = self.client.session.declare_subscriber(f"{self.keys.prefix}/sensors/position", self._position)

    def _position(self, sample: Any) -> None:
        measured = measured_of(json_object(sample.payload.to_bytes()) or {})
        if measured is not None:
            with self._cond:
                self.positions.append((measured.t, measured.value_um))
                self._cond.notify_all()

    def status(self) -> dict[str, Any] | None:
        try:
            return self.client.status(timeout_s=1.0)
        except TimeoutError:
            return None

    def wait_ready(self, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            if self._alive is not None and not self._alive():
                raise UserError("the demo's daemon exited while starting")
            status = self.status()
            if status and all(s["state"] == "ok" for s in status["sensors"].values()):
                return
            time.sleep(0.1)
        raise UserError("the demo daemon's sensors never became ready")

    def compensate(self, x_um: float, target_id: int) -> tuple[bool, dict[str, Any]]:
        try:
            return True, dict(self.client.move(x_um, wait=False, timeout_s=5.0, id=target_id).payload)
        except Refused as refused:
            return False, refused.payload
        except TimeoutError:
            raise UserError(f"no answer from {self.keys.compensate}") from None

    def latest_t(self, timeout: float) -> float:
        with self._cond:
            if not self._cond.wait_for(lambda: bool(self.positions), timeout):
                raise UserError("no interferometer readings from the demo daemon")
            return self.positions[-1][0]

    def hold_and_measure(self, t_command: float, timeout: float) -> float:
        """Mean position over [t_command + HOLD_S - WINDOW_S, t_command + HOLD_S] (cell clock)."""
        end = t_command + HOLD_S
        with self._cond:
            if not self._cond.wait_for(lambda: self.positions[-1][0] >= end, timeout):
                raise UserError("the demo daemon stopped publishing positions")
            window = [v for t, v in self.positions if end - WINDOW_S < t <= end]
            self.positions = self.positions[-1:]
        if not window:
            raise UserError("no position sample inside the averaging window; lower --speed")
        return sum(window) / len(window)

    def close(self) -> None:
        self._sub.undeclare()
        self.client.close()


def log_tail(path: Path, lines: int = LOG_TAIL_LINES) -> str:
    try:
        text = path.read_text(errors="replace").splitlines()
    except OSError:
        return "   (no daemon output)"
    return "\n".join(f"   | {line}" for line in text[-lines:]) or "   (no daemon output)"


def answer_line(answer: dict[str, Any], measured_um: float) -> str:
    temps = ", ".join(f"{c} {v:.2f} °C" for c, v in (answer.get("temperatures_c") or {}).items())
    flag = f"  EXTRAPOLATING {', '.join(answer['extrapolating'])}" if answer.get("extrapolating") else ""
    return (f"   x' {answer['x_um']:5.0f} µm -> q' {answer['q_um']:9.4f} µm, {answer['voltage_v']:.4f} V ({temps}); "
            f"the interferometer then reads {measured_um:9.4f} µm ({(measured_um - answer['x_um']) * 1000:+.0f} nm)"
            f"{flag}")


def serve(args: argparse.Namespace, workdir: Path, model_path: Path, kept: bool) -> list[dict[str, Any]]:
    """``nanodrift run`` on the calibrated model in its own process, and a client sending targets: the answers,
    each with the position the interferometer then read."""
    served: list[dict[str, Any]] = []
    workdir = workdir.resolve()  # the daemon runs with cwd=workdir: a relative --config would miss it
    listen = args.listen[0] if args.listen else f"tcp/127.0.0.1:{free_port()}"
    connect = args.connect[0] if args.connect else listen
    config = workdir / "serve.toml"
    config.write_text(demo_config(SERVE_CELL, listen, model_path.resolve(), SERVE_SCENARIO, args.speed,
                                  scenario_seed(args.seed, SERVE_SCENARIO), getattr(args, "cell", "ideal")))
    shown = config if kept else Path(config.name)
    targets = " ".join(f"{x:g}" for x in SERVE_TARGETS_UM)
    print(f"   $ nanodrift run --config {shown}        # the model above; the {SERVE_SCENARIO} room at "
          f"{args.speed:g}× real time; listens on {listen}", flush=True)
    print(f"   $ nanodrift target {targets} -e {connect} --cell {SERVE_CELL}   # a client, over Zenoh", flush=True)
    log_path = workdir / "serve.log"
    with open(log_path, "wb") as log:
        daemon = subprocess.Popen([sys.executable, "-m", "nanodrift.cli", "run", "--config", str(config)],
                                  stdout=subprocess.DEVNULL, stderr=log, cwd=workdir,
                                  env={**os.environ, "PYTHONUNBUFFERED": "1"})
    client: CellClient | None = None
    try:
        client = CellClient(connect, SERVE_CELL, alive=lambda: daemon.poll() is None)
        client.wait_ready()
        wall_timeout = 10.0 + 2 * HOLD_S / args.speed
        for i, x in enumerate(SERVE_TARGETS_UM):
            ok, answer = client.compensate(x, i)
            t_command = client.latest_t(wall_timeout)
            if not ok:
                raise UserError(f"target {x:g} µm refused: {answer.get('error')}")
            measured = client.hold_and_measure(t_command, wall_timeout)
            # the daemon's own health unit, as `nanodrift status` reads it, after this held target
            served.append({**answer, "measured_um": measured, "health": (client.status() or {}).get("health")})
            print(answer_line(answer, measured), flush=True)
        return served
    except UserError as error:
        _stop(daemon)
        where = (f"the daemon's log: {log_path}" if kept
                 else f"the daemon's last log lines (keep them with --keep DIR):\n{log_tail(log_path)}")
        raise UserError(f"{error}\n{where}") from None
    finally:
        if client is not None:
            client.close()
        _stop(daemon)


def _stop(daemon: subprocess.Popen[bytes]) -> None:
    if daemon.poll() is not None:
        return
    daemon.terminate()
    try:
        daemon.wait(10)
    except subprocess.TimeoutExpired:
        daemon.kill()
        daemon.wait()
