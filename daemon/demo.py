"""``nanodrift demo``: the whole story on the simulated cell in about a minute.

1. calibrate: the paper's procedure (24 forward sweeps of the ``train`` room) on a virtual clock, then
   stepwise identification -> a model file;
2. serve: for each validation test, ``nanodrift run`` in its own process on 127.0.0.1, the simulated
   room of that test running ``--speed`` times faster than real time;
3. as a client would: send each validation target over Zenoh (the ``compensate`` queryable), let the
   stage hold, average what the interferometer publishes over the last seconds of the hold;
4. Table I: accuracy with and without compensation, computed by ``daemon.calibration.validation``
   (ISO 9283, "without" = the same period's drift, x_measured - (q' - x')).
"""

from __future__ import annotations

import argparse
import asyncio
import io
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

from daemon.errors import UserError

HOLD_S = 25.0  # paper III.B: each step is held 25 s, the last 5 s averaged
WINDOW_S = 5.0
DEFAULT_TESTS = ("test2", "test4", "test5")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def demo_config(cell: str, listen: str, model_path: Path, scenario: str, speed: float, seed: int) -> str:
    """A simulated cell whose polls are spaced in simulated time so the sped-up daemon stays light."""
    sensors = "".join(
        f'[[sensors]]\nname = "{name}"\nkind = "simulated"\ninterval_s = 5.0\nmax_age_s = 30.0\n'
        for name in ("T1", "T2", "T3", "T4")
    )
    return (
        f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["{listen}"]\nmulticast_scouting = false\n'
        f'[model]\npath = "{model_path}"\n'
        f'[simulation]\nscenario = "{scenario}"\nspeed = {speed}\nseed = {seed}\n'
        f"{sensors}"
        '[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "simulated"\ninterval_s = 1.0\n'
        "max_age_s = 5.0\n"
    )


class CellClient:
    """A client session: targets through ``compensate``, positions from ``sensors/position``."""

    def __init__(self, connect: str, cell: str) -> None:
        import zenoh

        from daemon.bus import Keys, session_config

        self.keys = Keys(cell)
        conf = session_config(mode="client", connect=[connect], multicast_scouting=False)
        deadline = time.monotonic() + 30
        while True:
            try:
                self.session = zenoh.open(conf)
                break
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise UserError(f"the demo daemon never listened on {connect}") from None
                time.sleep(0.1)
        self._cond = threading.Condition()
        self.positions: list[tuple[float, float]] = []  # (cell clock t, um)
        self._sub = self.session.declare_subscriber(f"{self.keys.prefix}/sensors/position", self._position)

    def _position(self, sample: Any) -> None:
        doc = json.loads(sample.payload.to_bytes())
        if doc.get("state") == "ok" and doc.get("value") is not None:
            with self._cond:
                self.positions.append((float(doc["t"]), float(doc["value"])))
                self._cond.notify_all()

    def status(self) -> dict[str, Any] | None:
        for reply in self.session.get(self.keys.status, timeout=1.0):
            if reply.ok is not None:
                return json.loads(reply.ok.payload.to_bytes())
        return None

    def wait_ready(self, timeout: float = 30.0) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            status = self.status()
            if status and all(s["state"] == "ok" for s in status["sensors"].values()):
                return
            time.sleep(0.1)
        raise UserError("the demo daemon's sensors never became ready")

    def compensate(self, x_um: float, target_id: int) -> tuple[bool, dict[str, Any]]:
        payload = json.dumps({"x_um": x_um, "id": target_id})
        for reply in self.session.get(self.keys.compensate, payload=payload, timeout=5.0):
            if reply.ok is not None:
                return True, json.loads(reply.ok.payload.to_bytes())
            return False, json.loads(reply.err.payload.to_bytes())
        raise UserError(f"no answer from {self.keys.compensate}")

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
        self.session.close()


def calibrate(workdir: Path, cycles: int, seed: int) -> Any:
    from daemon.calibration.procedure import fit_recorded, record_calibration, simulated_backend

    backend = simulated_backend("train", seed=seed)
    data = workdir / "calibration.csv"
    asyncio.run(record_calibration(backend, data, cycles=cycles, progress_stream=io.StringIO()))
    return fit_recorded(data, workdir / "model.json")


def validate_through_daemon(workdir: Path, model_path: Path, test: str, args: argparse.Namespace) -> Any:
    from daemon.calibration.procedure import StepResult
    from daemon.calibration.validation import summarize, validation_plan

    listen = args.listen[0] if args.listen else f"tcp/127.0.0.1:{_free_port()}"
    connect = args.connect[0] if args.connect else listen
    config = workdir / f"{test}.toml"
    config.write_text(demo_config("demo", listen, model_path, test, args.speed, args.seed))
    log_path = workdir / f"{test}.log"
    with open(log_path, "wb") as log:
        daemon = subprocess.Popen([sys.executable, "-m", "daemon.cli", "run", "--config", str(config)],
                                  stdout=subprocess.DEVNULL, stderr=log, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    client: CellClient | None = None
    try:
        client = CellClient(connect, "demo")
        client.wait_ready()
        steps: list[StepResult] = []
        extrapolating = 0
        wall_timeout = 10.0 + 2 * HOLD_S / args.speed
        for step in validation_plan(args.cycles):
            ok, answer = client.compensate(step.target_um, step.index)
            t_command = client.latest_t(wall_timeout)
            if not ok:
                raise UserError(f"{test}: target {step.target_um} refused: {answer['error']}")
            extrapolating += bool(answer.get("extrapolating"))
            x = client.hold_and_measure(t_command, wall_timeout)
            steps.append(StepResult(step, t_command + HOLD_S, answer["q_um"], x, answer["temperatures_c"], True))
        return summarize(test, steps, compensated=True, extrapolating=extrapolating)
    except UserError as error:
        raise UserError(f"{error}\n(daemon log: {log_path})") from None
    finally:
        if client is not None:
            client.close()
        daemon.terminate()
        try:
            daemon.wait(10)
        except subprocess.TimeoutExpired:
            daemon.kill()


def run_demo(args: argparse.Namespace) -> int:
    from daemon.calibration.report import PAPER_TABLE1, table1

    started = time.monotonic()
    keep = getattr(args, "keep", None)
    with tempfile.TemporaryDirectory(prefix="nanodrift-demo-") as tmp:
        workdir = Path(keep) if keep else Path(tmp)
        workdir.mkdir(parents=True, exist_ok=True)
        print(f"1. calibration: {args.calibration_cycles} sweeps of the 'train' room (~3.3 h of simulated time)")
        fitted = calibrate(workdir, args.calibration_cycles, args.seed)
        model = fitted.model
        print(f"   model {model.id}: q = " + " + ".join(f"{ft.coef:.4g}*{ft.term.name}" for ft in model.terms))
        results = []
        for test in args.tests:
            print(f"2. {test}: serving the cell over Zenoh (nanodrift run, {args.speed:g}x real time); "
                  f"{args.cycles} validation sweeps sent as targets by a client ...", flush=True)
            result = validate_through_daemon(workdir, workdir / "model.json", test, args)
            results.append(result)
            print(f"   {len(result.steps)} targets, accuracy {result.accuracy_without_nm:.0f} nm without "
                  f"-> {result.accuracy_nm:.0f} nm with compensation", flush=True)
        print()
        print(table1(results, paper=PAPER_TABLE1))
        print(f"\n(demo took {time.monotonic() - started:.0f} s; files in {workdir if keep else 'a temporary dir'})")
    return 0
