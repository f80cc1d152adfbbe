"""A season of records on a lab PC: ``fit``, ``discover`` and ``predict`` on 100k and 1M rows (issue 27, item 6).

    python benchmarks/fit_scale.py            # budgets on the 1M rows: <= 20 s wall and <= 1 GB peak RSS each

A fast synthetic generator writes a season's recording per the CSV contract (``t_s``, ``x_um``, ``q_um``,
``T1``..``T4``; one row every 8 s, so 1M rows are 93 days) into a temporary directory with
``nanodrift.write_csv``: the paper's forward sweeps 0..480 µm, four thermocouples following a seasonal
swing, the day and their own offsets, and a command from eq. 3 plus a bracket's curvature in T2, white
noise and a 25 nm, 20 min interferometer wander. Each command runs as a real ``python -m nanodrift.cli``
subprocess; its wall time, CPU time (user + system) and peak RSS come from ``os.wait4``'s resource
usage of that very child. The 100k rows beside the 1M show how the cost grows (a ratio near 10 is
linear). The machine's load average is printed: the budgets are for the 2-core machine, and CPU time
says what a loaded machine's wall time hides. Exits 1 when a 1M-row command fails, takes over 20 s or
peaks over 1 GB.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from scipy.signal import lfilter

from nanodrift.calibration.dataset import Dataset, write_csv

ROWS = (100_000, 1_000_000)
BUDGET_WALL_S = 20.0
BUDGET_RSS_BYTES = 1_000_000_000
SAMPLE_S = 8.0
STEPS_UM = np.arange(0.0, 481.0, 30.0)


def season(rows: int, seed: int = 0) -> Dataset:
    """A season's recording whose inverse model eq. 3 (plus T2's curvature) can fit, with a wander it cannot."""
    rng = np.random.default_rng(seed)
    t = np.arange(rows) * SAMPLE_S
    x = np.resize(STEPS_UM, rows) + rng.normal(0.0, 0.01, rows)
    day = 2 * np.pi * t / 86400.0
    air = 21.0 + 1.5 * np.sin(2 * np.pi * t / (120 * 86400.0)) + 0.4 * np.sin(day)
    channels = {f"T{i}": air + 0.1 * i * np.sin(day * (1 + 0.1 * i) + i) + rng.normal(0.0, 0.005, rows)
                for i in range(1, 5)}
    decay = np.exp(-SAMPLE_S / 1200.0)
    wander = lfilter([0.025 * np.sqrt(1 - decay**2)], [1.0, -decay], rng.normal(0.0, 1.0, rows))
    q = (22.0 + 1.0012 * x - 4e-6 * x**2 + 3e-9 * x**3 - 0.6 * channels["T1"] - 0.5 * channels["T2"]
         + 0.2 * channels["T4"] - 0.3 * (channels["T2"] - 21.0) ** 2 + rng.normal(0.0, 0.02, rows) + wander)
    return Dataset(t=t, x=x, q=q, channels=channels, source=f"season of {rows} rows")


@dataclass(frozen=True)
class Run:
    wall_s: float
    cpu_s: float
    peak_rss_bytes: int
    ok: bool
    message: str


def run(args: list[str]) -> Run:
    """One ``nanodrift`` command as a child process; its own resource usage (``os.wait4``)."""
    start = time.perf_counter()
    child = subprocess.Popen([sys.executable, "-m", "nanodrift.cli", *args], stdout=subprocess.PIPE,
                             stderr=subprocess.STDOUT, text=True)
    assert child.stdout is not None
    output = child.stdout.read()  # read before waiting: a full pipe would block the child
    _, status, usage = os.wait4(child.pid, 0)
    wall = time.perf_counter() - start
    child.returncode = os.waitstatus_to_exitcode(status)
    last = output.strip().splitlines()[-1] if output.strip() else ""
    return Run(wall, usage.ru_utime + usage.ru_stime, usage.ru_maxrss * 1024, child.returncode == 0, last)


def main() -> int:
    print(f"load average at start: {' '.join(f'{v:.2f}' for v in os.getloadavg())} (2 cores: {os.cpu_count()} CPUs)")
    results: dict[tuple[str, int], Run] = {}
    with tempfile.TemporaryDirectory(prefix="nanodrift-fit-scale-") as tmp:
        for rows in ROWS:
            data = Path(tmp, f"season_{rows}.csv")
            start = time.perf_counter()
            write_csv(season(rows), data)
            written_s = time.perf_counter() - start
            print(f"{rows} rows: {data.stat().st_size / 1e6:.0f} MB of CSV written in {written_s:.1f} s")
            model, extended, predicted = (Path(tmp, f"{name}_{rows}{ext}") for name, ext in
                                          (("model", ".json"), ("extended", ".json"), ("predicted", ".csv")))
            commands = {
                "fit": ["fit", str(data), "--out", str(model)],
                "discover": ["discover", str(data), "--model", str(model), "--out", str(extended)],
                "predict": ["predict", "--model", str(model), str(data), "--out", str(predicted)],
            }
            for name, args in commands.items():
                results[name, rows] = outcome = run(args)
                if not outcome.ok:
                    print(f"  {name} FAILED: {outcome.message}")
    print(f"load average at end: {' '.join(f'{v:.2f}' for v in os.getloadavg())}")
    small, large = ROWS
    print(f"\n{'command':<9} | {'100k rows: wall  CPU   peak RSS':>32} | {'1M rows: wall  CPU   peak RSS':>32} | "
          f"{'1M/100k wall':>12} | {'RSS/row':>8} | budget")
    failed = False
    for name in ("fit", "discover", "predict"):
        a, b = results[name, small], results[name, large]
        within = b.ok and b.wall_s <= BUDGET_WALL_S and b.peak_rss_bytes <= BUDGET_RSS_BYTES
        failed |= not within
        print(f"{name:<9} | {a.wall_s:8.1f} s {a.cpu_s:5.1f} s {a.peak_rss_bytes / 1e6:6.0f} MB    | "
              f"{b.wall_s:8.1f} s {b.cpu_s:5.1f} s {b.peak_rss_bytes / 1e6:6.0f} MB    | "
              f"{b.wall_s / a.wall_s:11.1f}x | {b.peak_rss_bytes / large:5.0f} B  | "
              f"{'OK' if within else 'OVER'} (<= {BUDGET_WALL_S:g} s, <= {BUDGET_RSS_BYTES / 1e9:g} GB)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
