"""Two simulated weeks served by ``nanodrift run``, as a lab runs them: serve, record, refit, serve again.

    nice python benchmarks/week.py [--cell realistic|ideal] [--seeds 1] [--workers 2] [--speed 10000] [--seed 1]

What a lab does with the paper's calibration, which saw T4 21.55-22.0 °C while a week's air spans
20.3-23.0 °C (day/night, HVAC, the weekend setback), on the ``realistic`` cell by default (physics no candidate
term reproduces; ``--cell ideal``: the model's own form, where a refit with a square can be nearly exact):

1. ``train``: ``nanodrift fit calibration.csv``, the calibration being 24 ``train`` cycles of the vectorised
   simulator (``simulate_dataset``, seed k for pair k), as ``benchmarks/adaptation.py`` calibrates.
2. Week 1 (cell seed ``--seed`` + 2k): ``train`` served statically (``[adapt] mode = "off"``), recording every
   settled target with every polled channel (``[health] record_dir``). This is also the "paper's
   calibration only" line, printed beside the follow-up paper's 400 nm static over days (no bar).
3. ``refit``: ``nanodrift fit calibration.csv records/*.csv`` (week 1's seven day files, each a run of its
   own), in a subprocess as the lab runs it; its terms and training ranges are printed.
4. Week 2 (seed + 1: the same weekly pattern, new noise, fluctuations and door dips), three runs, ``--workers``
   at a time (each its own daemon process): ``refit`` static, ``train`` with the bias tracker (``mode =
   "bias"``: the follow-up's case, the paper's method plus the tracker, which its 100 nm anchor measured) and
   ``refit`` with the tracker (what the lab would run after refitting).

Scored per command, against the truth: every settled target of the full days 1-6 (not a daily mean per point)
gives e_true = true position - target, which splits as e_true = e_read - e_interf: e_read = interferometer -
target (what the interferometer reads: the error the bias tracker sees and zeroes) and e_interf = interferometer
- truth over the very same readings (the interferometer's own error: wander and the refraction its
compensation misses). Each has its RMS, 95th percentile and maximum. The bars (``BARS_NM``) apply to the
worst of the ``--seeds`` pairs, so a model or tracker that fails one stretch of the week fails the run:

- static (the refit served without adaptation): e_true, a model's error against the truth;
- adaptive (the bias tracker): e_read, the part of the truth error that is the tracker's. The tracker's
  reference is the interferometer, so no setting of it can remove e_interf: on the realistic cell the
  refraction walk the compensation misses (15 nm/sqrt(h), drivers/simulated/README.md) is 58-203 nm RMS
  over a week (the cell's seeds 1-16), far above the paper's < 40 nm (III.A), and an adaptive run's e_true follows it
  (measured: the adaptive runs' daily mean e_true is minus the interferometer's daily mean error to a
  few nm). e_true and e_interf are printed beside, never hidden.

The bars must fail a broken tracker: each pair replays week 1 (the calibration's model served statically, a
week of residuals the interferometer read, with the truth beside) through :class:`BiasTracker` as the daemon
runs it (``[adapt]`` tau_s and the clamp of this benchmark) and through two broken ones: off (clamp 0) and
the correction's sign reversed. The working replay must pass the adaptive bars and each broken one fail them,
on every pair; a mis-set tracker (a time constant 100 times too long, which still takes out the week's trend)
is printed beside. The replay leaves out what a correction changes in the stage's own path (hysteresis and
creep of a command a few hundred nm away: nm); it reproduces the daemon's runs to ~10 nm RMS.
The interferometer's uncertainty is < 40 nm (the paper's III.A): e_true below it is the simulator's truth, not
what a lab could verify. RSS growth (< 10 MB), the seven day files with every polled channel and
no refused target are checked on every run. The ISO 9283 accuracy per day (truth and interferometer) is
printed per pair as before, without a bar.

Each run is a real ``python -m nanodrift.cli run`` subprocess serving the simulated cell (``[simulation]
scenario = "week"``: ±1 °C day/night, HVAC steps, a weekend setback, door openings) on a clock ``--speed``
times faster than the wall clock, with T1..T4, the interferometer (the ``role = "position"`` sensor: the
health unit, the bias tracker and the recorder read it) and ``[health] record_dir``. A client-mode Zenoh
session on 127.0.0.1 sends the ISO 9283 points (0..480 µm by 80, up and down sweeps) one every
``--period-s`` of cell time all week, and counts the answers and refusals.

A "day" is the simulated lab's: the scaled clock starts at the last UTC midnight together with the
scenario (Monday 00:00), and the recorder labels its rows with that clock, so day k of the scenario is
the k-th record file. Day 0 starts when the daemon first serves (its start-up takes a few wall seconds:
hours of cell time), so it is shorter than the others; it holds the bias tracker's cold start (its first
residual weighs one 30 s step, ``BiasTracker.first_dt_s``) in the weekend setback, and is printed beside.

The truth: the simulated cell writes every interferometer reading beside the true position at that instant
(``[simulation] truth_log``); each recorded row's window is found in that log as the run of readings whose
mean is exactly the row's ``x_um`` (so the truth is averaged over the very readings the daemon averaged).
The runs are paced by the wall clock (the start-up's length, the machine's load), so two runs of one seed
differ in their rows, and so in the linear channels the refit selects (T1..T4 are nearly collinear over a
week). Daemon RSS is read from /proc/<pid>/status at the end of each day.
"""

from __future__ import annotations

import argparse
import csv
import datetime as dt
import json
import math
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import TypeVar

import numpy as np
import zenoh

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from anywhere, never tests/drivers

from nanodrift.calibration.dataset import write_csv
from nanodrift.calibration.plans import VALIDATION_POINTS_UM
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.client import Client
from nanodrift.drivers.local_port import free_port
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CELLS
from nanodrift.service.recorder import RECORD_COLUMNS

REPO = Path(__file__).resolve().parent.parent
T = TypeVar("T")
DAYS = 7
DAY_S = 86400.0
CHANNELS = ("T1", "T2", "T3", "T4")
INTERVAL_S = 20.0  # every sensor, in cell seconds: 2 ms of wall time at speed 10000
MAX_AGE_S = 1000.0  # what the daemon keeps fresh at speed 10000 (drivers/simulated/config.py WALL_LATENCY_S)
SETTLE_S, WINDOW_S = 300.0, 600.0  # a target's residual: the mean over 600 s from 300 s after it was reached
#: the tracker's clamp: the static model's error reaches -1.4 um at the weekend setback (1.7 degC below
#: the training range), beyond the default 1 um clamp
ADAPT_MAX_UM = 2.0
GOAL_RSS_MB = 10.0
#: the tracker's time constant, the daemon's default ([adapt] tau_s), written into every config and replayed
ADAPT_TAU_S = 600.0
#: bars per command over the full days 1-6 (nm), on the worst pair of weeks, whatever the cell: static on e_true
#: (the refit's error against the truth), adaptive on e_read (the truth error less the interferometer's own, which
#: no tracker referenced to it can remove); the follow-up paper's figures over days, 400 nm static and 100 nm
#: adaptive, are printed beside as anchors. Measured on the realistic cell (README, --seeds 4: week seeds 1-8,
#: median/worst): static e_true RMS 102/139, p95 194/253, max 324/368; adaptive e_read RMS 123/124 (train) and
#: 82/82 (refit), p95 <= 288, max <= 441; week 1 replayed: the daemon's tracker 109-124 nm RMS, off 258-374,
#: reversed > 2000 nm.
BARS_NM: dict[str, dict[str, float]] = {
    "static": {"RMS": 150.0, "p95": 300.0, "max": 600.0},
    "adaptive train": {"RMS": 200.0, "p95": 400.0, "max": 1000.0},
    "adaptive refit": {"RMS": 200.0, "p95": 400.0, "max": 1000.0},
}
ANCHOR_STATIC_NM, ANCHOR_ADAPTIVE_NM = 400.0, 100.0


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    return float("nan")


def write_config(path: Path, *, port: int, model: Path, mode: str, speed: float, seed: int, run_dir: Path,
                 cell: str) -> None:
    sensors = "".join(
        f'[[sensors]]\nname = "{c}"\nkind = "simulated"\ninterval_s = {INTERVAL_S}\nmax_age_s = {MAX_AGE_S}\n'
        for c in CHANNELS)
    sensors += (f'[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "simulated"\n'
                f"interval_s = {INTERVAL_S}\nmax_age_s = {MAX_AGE_S}\n")
    path.write_text(
        f'cell = "week"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
        f'[model]\npath = "{model}"\n'
        f"[health]\nsettle_s = {SETTLE_S}\nwindow_s = {WINDOW_S}\n"
        f'record_dir = "{run_dir / "records"}"\nrecord_keep_days = 0\n'
        f'[adapt]\nmode = "{mode}"\ntau_s = {ADAPT_TAU_S}\nmax_um = {ADAPT_MAX_UM}\n'
        f'[simulation]\nscenario = "week"\ncell = "{cell}"\nspeed = {speed}\nseed = {seed}\n'
        f'truth_log = "{run_dir / "truth.csv"}"\n'
        + sensors)


class WeekClient:
    """Sends targets, counts commands and refusals (by kind), reads ``status``: a :class:`nanodrift.Client`'s
    session and status, with its own subscribers and a ``target`` publisher. The week's targets are puts, not
    ``Client.move``: the pacing loop sends one every period of cell time and never waits for an answer, and
    the answers (every client's ``command`` and ``error``) are counted as they arrive."""

    def __init__(self, port: int, cell: str) -> None:
        self.client = Client(f"tcp/127.0.0.1:{port}", cell)
        self.session = self.client.session
        self.prefix = self.client.keys.prefix
        self.commands = 0
        self.refusals: dict[str, int] = {}
        self.first_refusal = ""
        self._lock = threading.Lock()
        self._subs = [self.session.declare_subscriber(f"{self.prefix}/command", self._command),
                      self.session.declare_subscriber(f"{self.prefix}/error", self._error)]
        self.publisher = self.session.declare_publisher(f"{self.prefix}/target",
                                                        congestion_control=zenoh.CongestionControl.BLOCK)

    def _command(self, _sample: zenoh.Sample) -> None:
        with self._lock:
            self.commands += 1

    def _error(self, sample: zenoh.Sample) -> None:
        doc = json.loads(sample.payload.to_bytes())
        with self._lock:
            kind = str(doc.get("kind"))
            self.refusals[kind] = self.refusals.get(kind, 0) + 1
            self.first_refusal = self.first_refusal or str(doc.get("error"))

    def status(self) -> dict[str, object] | None:
        try:
            return self.client.status(timeout_s=2.0)
        except TimeoutError:
            return None

    def cell_time(self) -> float | None:
        """The newest reading's stamp in ``status`` (cell clock), once every channel is ok."""
        status = self.status()
        if status is None:
            return None
        sensors = status["sensors"]
        assert isinstance(sensors, dict)
        if not all(s.get("state") == "ok" for s in sensors.values()):
            return None
        return max(float(s["t"]) for s in sensors.values())

    def close(self) -> None:
        for sub in self._subs:
            sub.undeclare()
        self.publisher.undeclare()
        self.client.close()


@dataclass
class Run:
    name: str
    mode: str  # [adapt] mode: off (static) or bias
    model: Path
    seed: int
    run_dir: Path
    rows: list[dict[str, float]] = field(default_factory=list)  # valid rows, with "true_x_um" added
    invalid_rows: int = 0
    unmatched_rows: int = 0
    files: list[tuple[str, list[str]]] = field(default_factory=list)  # (name, header)
    rss_mb: list[float] = field(default_factory=list)  # at the end of each day
    sent: int = 0
    commands: int = 0
    refusals: dict[str, int] = field(default_factory=dict)
    first_refusal: str = ""
    day0_hours: float = 0.0
    week_start: float = 0.0  # Monday 00:00 on the cell's clock (unix s)
    wall_s: float = 0.0


def wait_for(predicate: Callable[[], T | None], timeout_s: float, what: str) -> T:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(0.05)
    raise SystemExit(f"timed out after {timeout_s:g} s waiting for {what}")


def serve_week(name: str, mode: str, model: Path, root: Path, *, speed: float, period_s: float, seed: int,
               cell: str) -> Run:
    """One week of ``nanodrift run`` (``[adapt] mode``) with ``model`` on the ``week`` cell of ``seed``, scored."""
    run_dir = root / name
    run_dir.mkdir()
    port = free_port()
    config = run_dir / "week.toml"
    write_config(config, port=port, model=model, mode=mode, speed=speed, seed=seed, run_dir=run_dir, cell=cell)
    log = run_dir / "daemon.log"
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    started = time.monotonic()
    with open(log, "wb") as log_file:
        daemon = subprocess.Popen([sys.executable, "-m", "nanodrift.cli", "run", "--config", str(config)],
                                  stdout=subprocess.DEVNULL, stderr=log_file, cwd=REPO, env=env)
    run = Run(name, mode, model, seed, run_dir)
    client: WeekClient | None = None
    try:
        wait_for(lambda: daemon.poll() is not None or '"serving"' in log.read_text(errors="replace"), 60,
                 "the daemon to serve")
        if daemon.poll() is not None:
            raise SystemExit(f"the daemon exited ({daemon.returncode}):\n{log.read_text()[-2000:]}")
        client = WeekClient(port, "week")
        first_t = wait_for(client.cell_time, 30, "every channel ok")
        week_start = first_t - first_t % DAY_S  # the scaled clock starts at a UTC midnight: Monday 00:00
        # the cell's clock from the wall clock (one status round trip of error: tens of cell seconds)
        offset = first_t - speed * time.monotonic()

        def cell_now() -> float:
            return offset + speed * time.monotonic()

        run.week_start = week_start
        run.day0_hours = (week_start + DAY_S - first_t) / 3600.0
        week_end = week_start + DAYS * DAY_S
        points = list(VALIDATION_POINTS_UM)
        sweep = points + points[::-1]  # ISO 9283: up and down, the end points twice at each turn
        next_day = week_start + DAY_S
        k = 0
        while True:
            due = first_t + k * period_s
            if due > week_end - SETTLE_S - WINDOW_S - 2 * INTERVAL_S:  # the last target settles inside the week
                break
            while (now := cell_now()) < due:
                if now >= next_day:
                    run.rss_mb.append(rss_mb(daemon.pid))
                    next_day += DAY_S
                time.sleep(min(0.01, (due - now) / speed))
            client.publisher.put(json.dumps({"x_um": sweep[k % len(sweep)], "id": k}))
            k += 1
        run.sent = k
        while (now := cell_now()) < week_end:
            if now >= next_day:
                run.rss_mb.append(rss_mb(daemon.pid))
                next_day += DAY_S
            time.sleep(0.005)
        run.rss_mb.append(rss_mb(daemon.pid))
        wait_for(lambda: client.commands + sum(client.refusals.values()) >= run.sent, 10, "every answer")
        run.commands, run.refusals, run.first_refusal = client.commands, dict(client.refusals), client.first_refusal
    finally:
        if client is not None:
            client.close()
        daemon.send_signal(signal.SIGTERM)
        try:
            daemon.wait(20)
        except subprocess.TimeoutExpired:
            daemon.kill()
            daemon.wait(5)
    run.wall_s = time.monotonic() - started
    score(run, run_dir)
    return run


def score(run: Run, run_dir: Path) -> None:
    """Each valid recorded row with the truth averaged over exactly the readings the daemon averaged."""
    truth = np.loadtxt(run_dir / "truth.csv", delimiter=",", skiprows=1, ndmin=2)
    truth = truth[np.argsort(truth[:, 0], kind="stable")]
    t, true_x, measured = truth[:, 0], truth[:, 2], truth[:, 3]
    for path in sorted((run_dir / "records").glob("records-*.csv")):
        with open(path, newline="") as handle:
            reader = csv.DictReader(handle)
            run.files.append((path.name, list(reader.fieldnames or [])))
            for raw in reader:
                row = {key: float(value) for key, value in raw.items()}
                if row["valid"] != 1.0:
                    run.invalid_rows += 1
                    continue
                true_mean = window_truth(row, t, true_x, measured)
                if true_mean is None:
                    run.unmatched_rows += 1
                    continue
                run.rows.append({**row, "true_x_um": true_mean})


def window_truth(row: dict[str, float], t: np.ndarray, true_x: np.ndarray, measured: np.ndarray) -> float | None:
    """The truth's mean over the run of readings (ending at most three polls before the row's label) whose
    measured mean is the row's ``x_um`` (summed in the daemon's order: the same float); None when none is."""
    last = int(np.searchsorted(t, row["t_s"], side="right"))  # readings [.., last) are at or before the label
    most = 2 * round(WINDOW_S / INTERVAL_S)  # a poll takes time too: fewer readings than window / interval
    for end in range(last, max(0, last - 4), -1):
        for n in range(1, most + 1):
            start = end - n
            if start < 0:
                break
            total = 0.0
            for value in measured[start:end].tolist():
                total += value
            if abs(total / n - row["x_um"]) < 1e-9:
                return float(np.mean(true_x[start:end]))
    return None


def day_accuracy_nm(rows: list[dict[str, float]], key: str) -> float:
    """ISO 9283 accuracy (Table I): per point |mean(position - target)|, averaged over the points."""
    by_point: dict[float, list[float]] = {}
    for row in rows:
        by_point.setdefault(row["target_um"], []).append(row[key] - row["target_um"])
    return 1e3 * statistics.fmean(abs(statistics.fmean(errors)) for errors in by_point.values())


def per_day(run: Run) -> dict[int, list[dict[str, float]]]:
    days: dict[int, list[dict[str, float]]] = {}
    first = dt.datetime.fromtimestamp(run.week_start, dt.UTC).date()
    for row in run.rows:
        index = (dt.datetime.fromtimestamp(row["t_s"], dt.UTC).date() - first).days
        days.setdefault(index, []).append(row)
    return days


def nanodrift_fit(data: list[Path], out: Path, *options: str) -> str:
    """``nanodrift fit DATA... --out OUT`` in a subprocess, as the lab runs it; its summary (terms, ranges)."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-m", "nanodrift.cli", "fit", *map(str, data), "--out", str(out), *options],
                          capture_output=True, text=True, cwd=REPO, env=env, check=False)
    if done.returncode != 0:
        raise SystemExit(f"nanodrift fit failed ({done.returncode}):\n{done.stderr}")
    return done.stdout.strip()


def record_files(run: Run) -> list[Path]:
    return sorted((run.run_dir / "records").glob("records-*.csv"))


def indent(text: str) -> str:
    return "\n".join("    " + line for line in text.splitlines())


@dataclass(frozen=True)
class Spread:
    """|error| per command over the full days 1-6 (nm): RMS, 95th percentile, maximum."""

    rms_nm: float
    p95_nm: float
    max_nm: float

    @classmethod
    def of(cls, errors_nm: np.ndarray) -> Spread:
        if errors_nm.size == 0:
            return cls(math.inf, math.inf, math.inf)  # no row on a full day fails every bar
        magnitudes = np.abs(errors_nm)
        return cls(float(np.sqrt(np.mean(magnitudes ** 2))), float(np.percentile(magnitudes, 95)),
                   float(magnitudes.max()))

    def figure(self, name: str) -> float:
        return {"RMS": self.rms_nm, "p95": self.p95_nm, "max": self.max_nm}[name]

    def text(self) -> str:
        return f"RMS {self.rms_nm:.0f}, p95 {self.p95_nm:.0f}, max {self.max_nm:.0f} nm"


@dataclass(frozen=True)
class CommandErrors:
    """Per command over the full days 1-6: e_true = e_read - e_interf (see the module's docstring)."""

    true: Spread  # true position - target
    read: Spread  # interferometer - target: what the bias tracker sees
    interferometer: Spread  # interferometer - truth over the same readings: no tracker can remove it

    @classmethod
    def of(cls, rows: list[dict[str, float]]) -> CommandErrors:
        target = np.array([row["target_um"] for row in rows])
        read = 1e3 * (np.array([row["x_um"] for row in rows]) - target)
        true = 1e3 * (np.array([row["true_x_um"] for row in rows]) - target)
        return cls(Spread.of(true), Spread.of(read), Spread.of(read - true))


@dataclass
class Scores:
    """A run's per-day accuracy against the truth and the interferometer, and per command over the full days."""

    by_day: dict[int, tuple[float, float, int]]  # day -> (truth nm, interferometer nm, rows)
    worst_full_day_nm: float  # ISO accuracy of the worst full day (1-6) against the truth
    day0_nm: float
    commands: CommandErrors


def full_days(rows: list[dict[str, float]], week_start: float) -> list[dict[str, float]] | None:
    """The rows of days 1-6; None when one of those days has none (which fails every bar)."""
    first = dt.datetime.fromtimestamp(week_start, dt.UTC).date()
    by_day: dict[int, list[dict[str, float]]] = {}
    for row in rows:
        by_day.setdefault((dt.datetime.fromtimestamp(row["t_s"], dt.UTC).date() - first).days, []).append(row)
    if any(day not in by_day for day in range(1, DAYS)):
        return None
    return [row for day in range(1, DAYS) for row in by_day[day]]


def scores(run: Run) -> Scores:
    by_day: dict[int, tuple[float, float, int]] = {}
    for day, rows in per_day(run).items():
        by_day[day] = (day_accuracy_nm(rows, "true_x_um"), day_accuracy_nm(rows, "x_um"), len(rows))
    full = full_days(run.rows, run.week_start)
    if full is None:
        missing = Spread(math.inf, math.inf, math.inf)
        return Scores(by_day, math.inf, math.nan, CommandErrors(missing, missing, missing))
    worst = max(by_day[d][0] for d in range(1, DAYS))
    return Scores(by_day, worst, by_day[0][0] if 0 in by_day else float("nan"), CommandErrors.of(full))


@dataclass(frozen=True)
class TrackerReplay:
    """A bias tracker replayed on a static run's week: how the benchmark proves its adaptive bars fail a broken one."""

    name: str
    tau_s: float
    max_um: float
    sign: float = 1.0  # -1: the correction moves the wrong way

    def replay(self, run: Run) -> CommandErrors:
        """The static run's settled targets as if each command had carried the tracker's correction then: its
        residual and true error both shift by that correction (the stage's own path, hysteresis and creep of a
        command a few hundred nm away, is left out: nm)."""
        tracker = BiasTracker(self.tau_s, self.max_um)
        correction_um = 0.0
        corrected = []
        for row in sorted(run.rows, key=lambda r: r["t_s"]):
            shifted = {**row, "x_um": row["x_um"] + correction_um, "true_x_um": row["true_x_um"] + correction_um}
            corrected.append(shifted)
            correction_um = tracker.update(row["t_s"], self.sign * (shifted["x_um"] - row["target_um"]))
        full = full_days(corrected, run.week_start)
        if full is None:
            missing = Spread(math.inf, math.inf, math.inf)
            return CommandErrors(missing, missing, missing)
        return CommandErrors.of(full)


#: the replay of the tracker as the daemon runs it: it must pass the adaptive bars, and a broken one (off,
#: reversed) fail them; a mis-set one (a time constant 100x too long) is printed beside, without a check
WORKING_REPLAY = "the daemon's tracker"
MIS_SET_REPLAY = "a tracker 100x too slow"


def tracker_replays() -> tuple[TrackerReplay, ...]:
    return (TrackerReplay(WORKING_REPLAY, ADAPT_TAU_S, ADAPT_MAX_UM),
            TrackerReplay("a tracker off (clamp 0)", ADAPT_TAU_S, 0.0),
            TrackerReplay("a tracker with its sign reversed", ADAPT_TAU_S, ADAPT_MAX_UM, sign=-1.0),
            TrackerReplay(MIS_SET_REPLAY, 100 * ADAPT_TAU_S, ADAPT_MAX_UM))


@dataclass
class SeedWeeks:
    """One seed's two weeks: the calibration and week 1 (seed), the refit, week 2 (seed + 1) three ways."""

    seed: int
    week1: Run
    week2: list[Run]
    train_summary: str
    refit_summary: str
    replays: dict[str, CommandErrors] = field(default_factory=dict)  # week 1 through each of tracker_replays()

    @property
    def runs(self) -> list[Run]:
        return [self.week1, *self.week2]


def two_weeks(root: Path, seed: int, calibration_seed: int, args: argparse.Namespace) -> SeedWeeks:
    """Calibrate (seed ``calibration_seed``), serve week 1 statically, refit, serve week 2 three ways (the three
    runs of week 2 ``--workers`` at a time: each is its own daemon process)."""
    root = root / f"seed{seed}"
    root.mkdir()
    calibration = root / "calibration.csv"
    write_csv(simulate_dataset("train", cycles=24, seed=calibration_seed, cell=args.cell), calibration)
    train_model, refit_model = root / "train.json", root / "refit.json"
    train_summary = nanodrift_fit([calibration], train_model)
    serve = {"speed": args.speed, "period_s": args.period_s, "cell": args.cell}
    week1 = serve_week("week1-static-train", "off", train_model, root, seed=seed, **serve)
    refit_summary = nanodrift_fit([calibration, *record_files(week1)], refit_model)
    plans = [("week2-static-refit", "off", refit_model), ("week2-adaptive-train", "bias", train_model),
             ("week2-adaptive-refit", "bias", refit_model)]
    with ThreadPoolExecutor(max_workers=args.workers) as pool:
        week2 = list(pool.map(lambda plan: serve_week(*plan, root, seed=seed + 1, **serve), plans))
    return SeedWeeks(seed, week1, week2, train_summary, refit_summary)


def print_days(weeks: SeedWeeks, results: dict[str, Scores]) -> None:
    """The per-day table of one seed's four runs (ISO accuracy per day, truth and interferometer)."""
    runs = weeks.runs
    titles = [f"wk1 static {weeks.week1.model.stem}",
              *(f"wk2 {'static' if r.mode == 'off' else 'adaptive'} {r.model.stem}" for r in weeks.week2)]
    print("ISO 9283 accuracy per day, nm (mean over the 7 points of |the day's mean error|) against the TRUE position "
          "(truth) and the interferometer (interf.); rows = settled targets scored")
    print("day  weekday " + "".join(f"| {t:^21}" for t in titles) + "| RSS MB, week 2 runs in this order")
    print("             " + "|  truth interf. rows  " * len(runs) + "|")
    weekdays = ("Mon", "Tue", "Wed", "Thu", "Fri", "Sat", "Sun")
    for day in range(DAYS):
        cells = []
        for run in runs:
            if day in results[run.name].by_day:
                truth_nm, interf_nm, rows = results[run.name].by_day[day]
                cells.append(f"| {truth_nm:6.1f} {interf_nm:7.1f} {rows:4d}  ")
            else:
                cells.append(f"| {'-':>6} {'-':>7} {0:4d}  ")
        rss = " / ".join(f"{r.rss_mb[day]:.1f}" if day < len(r.rss_mb) else "-" for r in weeks.week2)
        label = f"{day}{'*' if day == 0 else ' '}"
        print(f"{label:4} {weekdays[day]:8}" + "".join(cells) + f"| {rss}")
    day0_hours = " / ".join(f"{run.day0_hours:.1f}" for run in runs)
    print(f"* day 0 from the first served target: {day0_hours} h of the day in these runs (the daemon's "
          "start-up is hours of cell time), with the bias tracker's cold start: it gives its first residual the "
          "weight of one 30 s step (BiasTracker first_dt_s), so the first targets, in the weekend setback, carry "
          "the static error; the figures below are over the full days 1-6, day 0 beside them\n")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--speed", type=float, default=10_000.0, help="cell seconds per wall second")
    parser.add_argument("--period-s", type=float, default=1200.0, help="a target every this many cell seconds")
    parser.add_argument("--seed", type=int, default=1,
                        help="week 1's cell seed; week 2's is seed + 1 (the calibration's: 0)")
    parser.add_argument("--seeds", type=int, default=1,
                        help="independent pairs of weeks: pair k has week 1 seed + 2k, week 2 seed + 2k + 1 and "
                             "its calibration seed k; the bars apply to the worst pair")
    parser.add_argument("--cell", choices=list(CELLS), default="realistic",
                        help="realistic (default: physics no candidate term reproduces) or ideal (the model's own "
                             "form, where a refit can be nearly exact)")
    parser.add_argument("--workers", type=int, default=2, help="week 2's runs served at once (each its own daemon)")
    args = parser.parse_args()
    if args.seeds < 1 or args.workers < 1:
        parser.error("--seeds and --workers must be at least 1")
    wall0 = time.perf_counter()
    root = Path(tempfile.mkdtemp(prefix="nanodrift-week-"))
    print(f"Two simulated weeks (scenario week, the {args.cell} cell) served by `nanodrift run` at speed "
          f"{args.speed:g}: a target every {args.period_s:g} cell s (ISO 9283 points 0..480 by 80), settle "
          f"{SETTLE_S:g} s + window {WINDOW_S:g} s, sensors every {INTERVAL_S:g} s (max_age_s {MAX_AGE_S:g}); "
          f"files in {root}\n")
    all_weeks = []
    for k in range(args.seeds):
        weeks = two_weeks(root, args.seed + 2 * k, k, args)
        all_weeks.append(weeks)
        results = {run.name: scores(run) for run in weeks.runs}
        week1 = weeks.week1
        recorded = len(week1.rows) + week1.invalid_rows + week1.unmatched_rows
        print(f"=== pair {k}: calibration seed {k}, week 1 seed {weeks.seed}, week 2 seed {weeks.seed + 1}")
        print(f"Model 'train': `nanodrift fit calibration.csv` (24 train cycles of the simulator, seed {k}):\n"
              f"{indent(weeks.train_summary)}\n")
        print(f"Model 'refit': `nanodrift fit calibration.csv <week 1's {len(record_files(week1))} record files>` "
              f"(week 1 served statically with 'train'; {recorded} rows recorded, {week1.invalid_rows} with "
              f"valid = 0 that fit leaves out):\n{indent(weeks.refit_summary)}\n")
        print_days(weeks, results)
        for run in weeks.runs:
            c = results[run.name].commands
            print(f"      {run.name}: per command over days 1-6, e_true {c.true.text()}; e_read {c.read.text()}; "
                  f"e_interf {c.interferometer.text()}; worst day's ISO accuracy "
                  f"{results[run.name].worst_full_day_nm:.1f} nm")
        replays = {replay.name: replay.replay(week1) for replay in tracker_replays()}
        weeks.replays = replays
        print(f"      week 1 replayed through bias trackers (the 'train' model's residuals, seed {weeks.seed}):")
        for name, replayed in replays.items():
            print(f"        {name:<34} e_true {replayed.true.text()}; e_read {replayed.read.text()}")
        print()
    ok = True

    def check(passed: bool, text: str) -> None:
        nonlocal ok
        ok &= passed
        print(f"{'PASS' if passed else 'FAIL'}  {text}")

    def passes(name: str, spread: Spread) -> bool:
        return all(spread.figure(figure) <= bar for figure, bar in BARS_NM[name].items())

    def median_worst(spreads: list[Spread]) -> str:
        return ", ".join(f"{figure} {statistics.median(s.figure(figure) for s in spreads):.0f}/"
                         f"{max(s.figure(figure) for s in spreads):.0f}" for figure in ("RMS", "p95", "max"))

    seeds = ", ".join(f"{w.seed}+{w.seed + 1}" for w in all_weeks)
    print(f"Per command over the full days 1-6 (every settled target, not a daily mean), nm, median/worst of "
          f"{args.seeds} pair(s) (week seeds {seeds}); the bars apply to the worst. e_true = true position - target "
          "= e_read - e_interf; the interferometer's uncertainty is < 40 nm (the paper's III.A): e_true below it "
          "cannot be verified on a lab's cell, and an adaptive run's e_true cannot be better than e_interf")
    week1_true = [scores(w.week1).commands.true for w in all_weeks]
    print(f"INFO  week 1 static, the paper's calibration only ('train'): e_true {median_worst(week1_true)}   anchor: "
          f"the follow-up's {ANCHOR_STATIC_NM:g} nm static over days (no bar: the model has not seen the room's range)")
    for index, name in enumerate(("static", "adaptive train", "adaptive refit")):
        commands = [scores(w.week2[index]).commands for w in all_weeks]
        scored = [c.true if name == "static" else c.read for c in commands]
        worst = Spread(*(max(s.figure(figure) for s in scored) for figure in ("RMS", "p95", "max")))
        anchor = ANCHOR_STATIC_NM if name == "static" else ANCHOR_ADAPTIVE_NM
        check(passes(name, worst),
              f"week 2 {name} ('{all_weeks[0].week2[index].model.stem}', "
              f"{'[adapt] mode = bias' if 'adaptive' in name else 'static'}): "
              f"{'e_true' if name == 'static' else 'e_read'} "
              + ", ".join(f"{figure} {worst.figure(figure):.0f} <= {bar:g}" for figure, bar in BARS_NM[name].items())
              + f"   anchor: the follow-up's {anchor:g} nm {'static' if name == 'static' else 'adaptive'} over days"
              + ("" if name == "static" else " (read by its interferometer)"))
        if name != "static":
            print(f"      beside it: e_true {median_worst([c.true for c in commands])}; the interferometer's own "
                  f"e_interf {median_worst([c.interferometer for c in commands])}")
    for weeks in all_weeks:
        for replay in tracker_replays():
            replayed = weeks.replays[replay.name]
            text = (f"pair seed {weeks.seed}: week 1 replayed through {replay.name}: e_read {replayed.read.text()} "
                    f"{{}} the adaptive bars (e_true {replayed.true.text()})")
            if replay.name == MIS_SET_REPLAY:  # mis-set, not broken: it still takes out the week's trend
                print("INFO  " + text.format("passes" if passes("adaptive train", replayed.read) else "fails"))
                continue
            working = replay.name == WORKING_REPLAY
            check(passes("adaptive train", replayed.read) == working, text.format("passes" if working else "fails"))
    for weeks in all_weeks:
        for run in weeks.week2:
            growth = run.rss_mb[-1] - run.rss_mb[0] if len(run.rss_mb) >= 2 else float("nan")
            check(growth < GOAL_RSS_MB, f"{run.name} (seed {run.seed}): daemon RSS growth from the end of day 0 "
                  f"to the end of the week {growth:+.1f} MB < {GOAL_RSS_MB:g} MB ({run.rss_mb[0]:.1f} -> "
                  f"{run.rss_mb[-1]:.1f} MB)")
            expected = [*RECORD_COLUMNS, *CHANNELS]
            week_days = {(dt.datetime.fromtimestamp(run.week_start, dt.UTC).date()
                          + dt.timedelta(days=d)).isoformat() for d in range(DAYS)}
            in_week = [(name, header) for name, header in run.files if name[len("records-"):][:10] in week_days]
            after = [name for name, header in run.files if (name, header) not in in_week]
            complete = [name for name, header in in_week if all(c in header for c in expected)]
            check(len(in_week) == DAYS and len(complete) == DAYS,
                  f"{run.name}: {len(in_week)} record files for the week's {DAYS} days, {len(complete)} with every "
                  f"polled channel ({', '.join(CHANNELS)})"
                  + (f" (and {', '.join(after)}: the last target, sent in the week, settled after its end: the "
                     "client's pacing is wall-clock, 0.1 s of which is 1000 cell s)" if after else ""))
        for run in weeks.runs:
            refused = sum(run.refusals.values())
            check(refused == 0 and run.commands == run.sent,
                  f"{run.name} (seed {run.seed}): {run.sent} targets sent, {run.commands} commands, {refused} "
                  f"refused {run.refusals or ''} {run.first_refusal}")
            print(f"      {len(run.rows)} valid rows scored, {run.invalid_rows} invalid (valid = 0), "
                  f"{run.unmatched_rows} whose readings were not found in the truth log; run {run.wall_s:.0f} s wall")
    print(f"\n{time.perf_counter() - wall0:.0f} s wall")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
