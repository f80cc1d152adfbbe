"""Model speed: streaming evaluation per target, fit time, predict on a million rows (issue 2).

Run: python benchmarks/model_speed.py   (prints figures; budgets: median < 5 us per target,
fit 408 rows x 10 candidates < 50 ms, predict 1e6 rows < 2 s). Each figure is shown beside a
baseline measured in the same run, so a slow machine shows as a slow baseline, not a bad ratio.
"""

from __future__ import annotations

import resource
import statistics
import subprocess
import sys
import tempfile
import time
import tracemalloc
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from helpers.synthetic import paper_run

from nanodrift.calibration.dataset import Dataset, read_csv, write_csv
from nanodrift.model.identify import candidate_terms, fit, fit_terms
from nanodrift.model.model import save_model


def per_call_us(fn, x_values, repeats: int = 31) -> list[float]:
    """Median-able samples: each is the mean over len(x_values) calls, in microseconds."""
    samples = []
    for _ in range(repeats):
        start = time.perf_counter()
        for x in x_values:
            fn(x)
        samples.append((time.perf_counter() - start) / len(x_values) * 1e6)
    return samples


def bench_streaming() -> None:
    model = fit(paper_run(seed=0), order=3).model
    ev = model.evaluator()
    ev.observe(0.0, {c: 20.0 for c in model.channels})
    xs = list(np.random.default_rng(0).uniform(0, 480, 2000))
    a = [ft.coef for ft in model.terms if ft.term.name in ("x^3", "x^2", "x")]
    static = 20.0 * sum(ft.coef for ft in model.terms if ft.term.channels) + model.terms[-1].coef

    def bare(x: float) -> float:  # the floor: the same cubic and sum, no model object
        return ((a[0] * x + a[1]) * x + a[2]) * x + static

    ours = per_call_us(lambda x: ev.command(x, 1.0), xs)
    base = per_call_us(bare, xs)
    m, b = statistics.median(ours), statistics.median(base)
    print(f"streaming command, paper model ({len(model.terms)} terms: {', '.join(model.term_names())})")
    print(f"  median {m:.2f} us/target (p90 {np.percentile(ours, 90):.2f}); bare inline cubic {b:.2f} us; "
          f"ratio {m / b:.1f}x; budget 5 us -> {'OK' if m < 5 else 'OVER'}")
    obs = per_call_us(lambda x: ev.observe(1.0, {"T1": x}), xs[:500])
    print(f"  observe one temperature sample: median {statistics.median(obs):.2f} us")
    ev.observe(0.0, {c: 20.0 for c in model.channels})
    sig = per_call_us(lambda x: ev.sigma(x, 1.0), xs)
    print(f"  sigma (q_sigma_um) per target: median {statistics.median(sig):.2f} us "
          f"(p90 {np.percentile(sig, 90):.2f}); budget 5 us -> {'OK' if statistics.median(sig) < 5 else 'OVER'}")

    def fresh_sample_then_target(x: float) -> None:  # the first target after a sample pays the refresh
        ev.observe(1.0, {"T1": 20.0})
        ev.sigma(x, 1.0)

    both = per_call_us(fresh_sample_then_target, xs[:500])
    print(f"  observe + the first sigma after it: median {statistics.median(both):.2f} us")


def bench_fit() -> None:
    data = paper_run(seed=1)
    candidates = candidate_terms(list(data.channels), 6)  # x^1..x^6 + T1..T4 = 10 candidates
    X = np.column_stack([t.batch(data.t, data.x, data.channels) for t in candidates])
    times, base = [], []
    for _ in range(21):
        start = time.perf_counter()
        fit_terms(data, candidates)
        times.append(time.perf_counter() - start)
        start = time.perf_counter()
        np.linalg.lstsq(np.column_stack([np.ones(len(data)), X]), data.q, rcond=None)
        base.append(time.perf_counter() - start)
    m = statistics.median(times) * 1e3
    print(f"fit: {len(data)} rows x {len(candidates)} candidates, stepwise + final OLS")
    print(f"  median {m:.2f} ms; one plain lstsq on the same matrix {statistics.median(base) * 1e3:.3f} ms; "
          f"budget 50 ms -> {'OK' if m < 50 else 'OVER'}")
    start = time.perf_counter()
    result = fit(data)
    auto_ms = (time.perf_counter() - start) * 1e3
    print(f"  fit --order auto (5 orders x {result.orders['x'].folds} held-out folds): {auto_ms:.1f} ms")


def bench_predict(rows: int = 1_000_000) -> None:
    base_run = paper_run(seed=2)
    model = fit(base_run, order=3).model
    rng = np.random.default_rng(3)
    data = Dataset(
        t=np.arange(rows) * 0.5,
        x=rng.uniform(0, 480, rows),
        q=None,
        channels={c: 20 + rng.normal(0, 0.2, rows) for c in base_run.channels},
    )
    tracemalloc.start()
    start = time.perf_counter()
    q = model.predict(data)
    elapsed = time.perf_counter() - start
    _, peak = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    input_mb = (2 + len(data.channels)) * rows * 8 / 1e6
    start = time.perf_counter()
    baseline = np.column_stack([data.x**3, data.x**2, data.x, *data.channels.values()]).sum(axis=1)
    base_elapsed = time.perf_counter() - start
    assert q.shape == baseline.shape
    print(f"predict {rows:,} rows (model in memory)")
    print(f"  {elapsed * 1e3:.0f} ms, peak {peak / 1e6:.0f} MB above the {input_mb:.0f} MB of input; "
          f"baseline (stack features + sum) {base_elapsed * 1e3:.0f} ms; "
          f"budget 2 s -> {'OK' if elapsed < 2 else 'OVER'}")
    with tempfile.TemporaryDirectory() as tmp:
        src, out, mpath = Path(tmp) / "d.csv", Path(tmp) / "p.csv", Path(tmp) / "m.json"
        write_csv(data, src)
        save_model(model, mpath)
        start = time.perf_counter()
        read_csv(src)
        t_read = time.perf_counter() - start
        start = time.perf_counter()
        write_csv(data, out, {"q_pred_um": q})
        t_write = time.perf_counter() - start
        # the command as a user runs it: its own process, wall time and peak RSS
        start = time.perf_counter()
        subprocess.run([sys.executable, "-m", "nanodrift.cli", "predict", "--model", str(mpath), str(src),
                        "--out", str(out)], check=True)
        total = time.perf_counter() - start
        peak_rss = resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 1e3
        print(f"  whole `nanodrift predict` file to file ({src.stat().st_size / 1e6:.0f} MB CSV): {total:.2f} s, "
              f"peak RSS {peak_rss:.0f} MB; of that CSV text I/O: read {t_read:.2f} s, write {t_write:.2f} s")


if __name__ == "__main__":
    bench_streaming()
    bench_fit()
    bench_predict()
