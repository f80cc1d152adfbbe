"""Discovery on 1e4, 1e5 and 1e6 rows: wall time, peak memory, and how time grows with rows.

    .venv/bin/python benchmarks/discovery.py [--sizes 10000,100000,1000000]

Data: a synthetic stepped run (the paper's forward sweeps, 29 s per step) whose room temperature
cycles over days, four thermocouples that lag the air like the simulated cell's, and a hidden
thermal lag (2 h) that the given model (eq. 3, fitted by the paper's identification) lacks, so
every candidate family is searched and one step is taken. Each size runs in its own process (peak
memory is that process's growth during discovery, by tracemalloc, which numpy reports to); the
baseline is one least-squares fit of the given model on the same rows, timed in the same process.
Budget: 1e6 rows in under 30 s and 2 GB.
"""

from __future__ import annotations

import argparse
import itertools
import json
import subprocess
import sys
import time
import tracemalloc

import numpy as np

from nanodrift.calibration.dataset import Dataset

BUDGET_S, BUDGET_BYTES = 30.0, 2 * 1024**3


def synthetic_run(n: int, seed: int = 0) -> Dataset:
    from nanodrift.model.terms import lag_filter

    rng = np.random.default_rng(seed)
    t = np.arange(n) * 29.0
    steps = np.arange(0.0, 481.0, 30.0)
    x = np.tile(steps, n // steps.size + 1)[:n] + rng.normal(0, 0.003, n)
    day = 86400.0
    air = 22.0 + 0.3 * np.sin(2 * np.pi * t / day) + 0.15 * np.sin(2 * np.pi * t / (0.37 * day))
    air += np.cumsum(rng.normal(0, 0.002, n)) * 0.05
    channels = {}
    for name, tau, offset in (("T1", 900.0, 0.04), ("T2", 2400.0, -0.03), ("T3", 60.0, 0.06), ("T4", 150.0, -0.02)):
        true = lag_filter(t, air, tau) + offset
        channels[name] = np.round((true + rng.normal(0, 0.005, n)) / 0.01) * 0.01
    drift = -0.4 * (lag_filter(t, air, 900.0) - 22) - 0.5 * (lag_filter(t, air, 2400.0) - 22)
    drift += -3.0 * (lag_filter(t, air, 7200.0) - 22)  # the hidden effect
    u = x / 480.0
    q = x - u * (-0.25 + u * (1.2 - 0.75 * u)) - drift + rng.normal(0, 0.02, n)
    cycle = np.arange(n) // steps.size
    return Dataset(t=t, x=x, q=q, channels=channels, extra={"cycle": cycle.astype(float)}, source=f"synthetic:{n}")


def measure(n: int) -> dict[str, float]:
    """One size, in this process: data, given model, baseline fit time, discovery time and memory."""
    from nanodrift.calibration.discovery import discover
    from nanodrift.model.identify import fit, ols

    data = synthetic_run(n)
    given = fit(data, order=3).model
    start = time.perf_counter()
    ols(given.features(data)[:, :-1], data.q)
    baseline_s = time.perf_counter() - start
    start = time.perf_counter()
    result = discover(data, given)
    discover_s = time.perf_counter() - start
    tracemalloc.start()
    discover(data, given)
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    return {
        "rows": n, "discover_s": discover_s, "baseline_fit_s": baseline_s, "peak_bytes": float(peak),
        "steps": [f"{s.effect} {s.params.get('tau_behind_fastest_s', '')}" for s in result.steps],
        "candidates": sum(len(r.candidates) for r in result.rounds),
    }


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--sizes", default="10000,100000,1000000")
    parser.add_argument("--one", type=int, help=argparse.SUPPRESS)  # internal: measure one size, print JSON
    args = parser.parse_args()
    if args.one:
        print(json.dumps(measure(args.one)))
        return 0
    sizes = [int(s) for s in args.sizes.split(",")]
    rows = []
    for n in sizes:
        out = subprocess.run([sys.executable, __file__, "--one", str(n)], capture_output=True, text=True, check=True)
        rows.append(json.loads(out.stdout.strip().splitlines()[-1]))
    print(f"{'rows':>9} {'discover':>10} {'1 OLS fit':>10} {'ratio':>7} {'peak mem':>10} {'candidates':>10}  named")
    for r in rows:
        print(f"{r['rows']:>9d} {r['discover_s']:>9.2f}s {r['baseline_fit_s']:>9.3f}s "
              f"{r['discover_s'] / r['baseline_fit_s']:>7.0f} {r['peak_bytes'] / 2**20:>8.0f}MB "
              f"{r['candidates']:>10d}  {', '.join(r['steps']) or '-'}")
    if len(rows) >= 2:
        slope, _ = np.polyfit(np.log([r["rows"] for r in rows]), np.log([r["discover_s"] for r in rows]), 1)
        print(f"time grows as rows^{slope:.2f} (least-squares over all sizes)")
        for a, b in itertools.pairwise(rows):
            local = np.log(b["discover_s"] / a["discover_s"]) / np.log(b["rows"] / a["rows"])
            print(f"  {a['rows']:>9d} -> {b['rows']:>9d} rows: x{b['discover_s'] / a['discover_s']:.1f} time, "
                  f"exponent {local:.2f}")
    big = [r for r in rows if r["rows"] >= 1_000_000]
    for r in big:
        ok = r["discover_s"] < BUDGET_S and r["peak_bytes"] < BUDGET_BYTES
        print(f"budget (1e6 rows < {BUDGET_S:.0f} s and < {BUDGET_BYTES / 2**30:.0f} GB): "
              f"{'met' if ok else 'MISSED'} ({r['discover_s']:.1f} s, {r['peak_bytes'] / 2**30:.2f} GB)")
    return 0 if all(r["discover_s"] < BUDGET_S and r["peak_bytes"] < BUDGET_BYTES for r in big) else 1


if __name__ == "__main__":
    sys.exit(main())
