"""The paper's Table I over seeds: ``python benchmarks/paper_table1.py [--seeds 16] [--cell realistic|ideal]``.

1. Seed ``--seed`` exactly as ``nanodrift demo`` and ``nanodrift validate`` run it, seeded by
   ``nanodrift.commands._cell.scenario_seed`` (test N: seed * 100 + N): the async procedure's calibration (4 s
   ramp, 25 s hold, mean of the last 5 s, 0..480 µm by 30, 24 cycles) of the ``train`` room on a virtual clock,
   fitted as ``nanodrift calibrate`` fits, then tests 1-5 (30 forward sweeps each; test 1 without the model, as
   the paper's). Its Table I is printed as the demo prints it.
2. Seeds 0 .. --seeds - 1 through the vectorised simulator (``drivers/simulated/runs.py``: the same physics,
   plan, step schedule, seeding rule and ``fit``, without asyncio; one process per seed, ``--workers`` at a
   time), each test run twice in the same room with the same noise: through the model, and uncompensated.
   Seed --seed is in both, so how far the two paths agree is printed.
3. Scored against the simulated TRUE position: ISO 9283 accuracy AP (mean over the seven points of
   |mean attained - target|) without and with the model, its ratio, repeatability RP, and per command (every
   step, not a mean per point) the RMS and 95th percentile of |true error|.

Printed: the median and the 90 % interval (5th-95th percentile, interpolated) over the seeds beside the paper's
Table I, and the floors. The interferometer the paper measured with has an uncertainty < 40 nm (III.A): no AP
below that can be verified on a lab's cell, whatever the simulator's truth says. The floors apply to the
WORST seed and the exit code is 1 when one fails. ``--figure DIR`` draws fig. 11 over the seeds. The default
cell is ``realistic`` (physics no candidate term reproduces); ``--cell ideal`` measures the model on its own
form (what the method gives when the model can be exact: an upper bound, not a lab's figure).
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration.iso9283 import TestResult, summarize_runs
from nanodrift.calibration.plans import validation_plan
from nanodrift.commands._cell import scenario_seed
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CELLS, CellPhysics
from nanodrift.drivers.simulated.runs import independent_command, simulate_steps
from nanodrift.model.equation import equation
from nanodrift.model.identify import fit
from nanodrift.model.model import Model
from nanodrift.procedure.recording import fit_recorded, record_calibration
from nanodrift.procedure.validation import run_validation
from nanodrift.reports.validation import PAPER_TABLE1, table1, truth_table

TESTS = ("test1", "test2", "test3", "test4", "test5")
INTERFEROMETER_FLOOR_NM = 40.0
#: floors on the worst seed's improvement against the truth (AP without / AP with), per cell: a regression guard,
#: not the paper's claim. Measured over 16 seeds (README): the realistic cell's worst seed is 1.6-1.8x (its
#: medians 4.1-6.8x; the paper's 7.7-10.8x in range, 3.4x out of it); the ideal cell's worst seed is 7.1-8.0x in
#: range (the paper's 7x floor holds on it) and 1.9x in test 5 (the paper's 2.4x does not).
FLOORS_X: dict[str, dict[str, float]] = {
    "realistic": {"test2": 1.5, "test3": 1.5, "test4": 1.5, "test5": 1.5},
    "ideal": {"test2": 7.0, "test3": 7.0, "test4": 7.0, "test5": 1.5},
}


class _Null:
    def write(self, _: str) -> int:
        return 0

    def flush(self) -> None:
        return None

    def isatty(self) -> bool:
        return False


def procedure_table(seed: int, cycles: int, validation_cycles: int, tests: tuple[str, ...] = TESTS,
                    cell: str = "realistic") -> tuple[list[TestResult], float, float, Model]:
    """Table I through the async procedure: (results, calibration wall s, validation wall s, model)."""
    with tempfile.TemporaryDirectory() as tmp:
        data, model_path = Path(tmp) / "cal.csv", Path(tmp) / "model.json"
        backend = simulated_drivers("train", seed=scenario_seed(seed, "train"), cell=cell)
        t0 = time.perf_counter()
        asyncio.run(record_calibration(backend, data, cycles=cycles, progress_stream=_Null()))
        cal_wall = time.perf_counter() - t0
        model = fit_recorded(data, model_path).models["x"]
    results = []
    t0 = time.perf_counter()
    for name in tests:
        backend = simulated_drivers(name, seed=scenario_seed(seed, name), cell=cell)
        use = None if name == "test1" else model
        results.append(asyncio.run(run_validation(backend, use, name=name, cycles=validation_cycles,
                                                  progress_stream=_Null())))
    return results, cal_wall, time.perf_counter() - t0, model


def true_errors_nm(result: TestResult) -> np.ndarray:
    """Per valid step, the true error (true position - target) of what was commanded: with the model when the
    test ran with it, else the stage as it is."""
    axis = result.axis
    return np.array([1e3 * (x_true - s.step.target(axis))
                     for s, x_true in zip(result.steps, result.x_true_um, strict=True) if s.valid])


def scores(result: TestResult) -> dict[str, float]:
    """One test's figures against the truth (nm; ratio in x)."""
    truth = result.against_truth()
    assert truth is not None, "the simulated cell knows the true position"
    errors = np.abs(true_errors_nm(result))
    with_ = truth.accuracy_nm if result.compensated else truth.accuracy_without_nm
    return {"ap_without": truth.accuracy_without_nm, "ap_with": with_,
            "ratio": truth.accuracy_without_nm / with_ if result.compensated else float("nan"),
            "rp_with": truth.repeatability_nm if result.compensated else truth.repeatability_without_nm,
            "rms": float(np.sqrt(np.mean(errors ** 2))), "p95": float(np.percentile(errors, 95)),
            "ratio_interferometer": result.improvement}


def procedure_seed(seed: int, cell: str, cycles: int, validation_cycles: int) -> dict[str, Any]:
    """One seed as the demo runs it (its own process): its figures per test, its model and Table I text."""
    t0 = time.perf_counter()
    results, _, _, model = procedure_table(seed, cycles, validation_cycles, cell=cell)
    return {"seed": seed, "tests": {r.name: scores(r) for r in results}, "model": f"{model.id}: {equation(model)}",
            "table1": table1(results, PAPER_TABLE1) + "\n\n" + truth_table(results),
            "wall_s": time.perf_counter() - t0}


def vectorised_seed(seed: int, cell: str, cycles: int, validation_cycles: int) -> dict[str, Any]:
    """One seed through the vectorised simulator (its own process): its figures per test, against the truth."""
    t0 = time.perf_counter()
    model = fit(simulate_dataset("train", cycles=cycles, seed=scenario_seed(seed, "train"), cell=cell)).model
    plan = validation_plan(validation_cycles)
    targets = np.array([s.target_um for s in plan])
    cycles_of = [s.cycle for s in plan]
    figures = {}
    for test in TESTS:
        physics = CellPhysics.create(test, seed=scenario_seed(seed, test), cell=cell)
        without = simulate_steps(physics, {"x": targets}, cycles_of)["x_true_um"]
        with_ = (None if test == "test1" else
                 simulate_steps(physics, {"x": targets}, cycles_of, command_for=independent_command({"x": model}))
                 ["x_true_um"])
        truth = summarize_runs(test, {"x": targets}, {"x": without}, None if with_ is None else {"x": with_})
        errors = 1e3 * np.abs((without if with_ is None else with_) - targets)
        compensated = with_ is not None
        figures[test] = {"ap_without": truth.accuracy_without_nm,
                         "ap_with": truth.accuracy_nm if compensated else truth.accuracy_without_nm,
                         "ratio": truth.improvement if compensated else float("nan"),
                         "rp_with": truth.repeatability_nm if compensated else truth.repeatability_without_nm,
                         "rms": float(np.sqrt(np.mean(errors ** 2))), "p95": float(np.percentile(errors, 95))}
    return {"seed": seed, "tests": figures, "wall_s": time.perf_counter() - t0}


def figure_over_seeds(runs: list[dict[str, Any]], directory: Path, provenance: str) -> list[Path]:
    """After the paper's Fig. 11, over seeds: per test the median AP without and with the model against the truth,
    each with its 90 % interval (5th-95th percentile) as an error bar, the paper's figures beside them and the
    interferometer's 40 nm floor; PNG + SVG with a provenance footer (the command that made it)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from nanodrift.reports.validation import STYLE, WITH_COLOR, WITHOUT_COLOR, save_figure, with_footer

    x = np.arange(len(TESTS))
    with plt.rc_context(STYLE):
        fig, ax = plt.subplots(figsize=(9, 5))
        for key, offset, color, label in (("ap_without", -0.2, WITHOUT_COLOR, "without compensation"),
                                          ("ap_with", 0.2, WITH_COLOR, "with compensation")):
            tests = [i for i, t in enumerate(TESTS) if key == "ap_without" or t != "test1"]
            values = np.array([[r["tests"][TESTS[i]][key] for r in runs] for i in tests])
            low, mid, high = np.percentile(values, [5, 50, 95], axis=1)
            ax.bar(x[tests] + offset, mid, 0.4, color=color, label=f"{label}: median over {len(runs)} seeds",
                   gid=f"bars-{key}")
            ax.errorbar(x[tests] + offset, mid, yerr=[mid - low, high - mid], fmt="none", ecolor="0.15", capsize=4,
                        label="90 % of seeds (5th-95th percentile)" if key == "ap_with" else None,
                        gid=f"interval-{key}")
        paper_with = [PAPER_TABLE1[t][1] for t in TESTS]
        ax.plot(x - 0.2, [PAPER_TABLE1[t][0] for t in TESTS], "k_", ms=18, mew=2, label="the paper (Table I)")
        ax.plot([i + 0.2 for i, v in enumerate(paper_with) if v], [v for v in paper_with if v], "k_", ms=18, mew=2)
        ax.axhline(INTERFEROMETER_FLOOR_NM, color="0.4", ls="--", lw=1,
                   label=f"the paper's interferometer: < {INTERFEROMETER_FLOOR_NM:.0f} nm")
        ax.set_yscale("log")
        ax.set_xticks(x, TESTS)
        ax.set_ylabel("ISO 9283 accuracy against the true position (nm)")
        ax.set_title("Table I over seeds (fig. 11): median and 90 % interval")
        ax.legend(loc="upper left", framealpha=0.85)
        fig = with_footer(fig, provenance)
        directory.mkdir(parents=True, exist_ok=True)
        written = save_figure(fig, directory / "fig11_accuracy_over_seeds")
        plt.close(fig)
    return written


def spread(values: list[float], digits: int = 0) -> str:
    """``median [5th, 95th percentile]``."""
    lo, mid, hi = np.percentile(values, [5, 50, 95])
    return f"{mid:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Table I over seeds on the simulated cell, against the paper")
    parser.add_argument("--seeds", type=int, default=16, help="seeds 0..N-1 (default 16)")
    parser.add_argument("--seed", type=int, default=0, help="the seed whose Table I is printed as the demo prints it")
    parser.add_argument("--cell", choices=list(CELLS), default="realistic",
                        help="realistic (default: physics no candidate term reproduces) or ideal (the model's own "
                             "form: what the method gives when the model can be exact)")
    parser.add_argument("--workers", type=int, default=min(2, os.cpu_count() or 1), help="processes (default 2)")
    parser.add_argument("--cycles", type=int, default=24)
    parser.add_argument("--validation-cycles", type=int, default=30)
    parser.add_argument("--figure", metavar="DIR", help="also draw fig. 11 over the seeds (PNG + SVG) into DIR")
    args = parser.parse_args(argv)
    if args.seeds < 1 or args.workers < 1:
        parser.error("--seeds and --workers must be at least 1")
    t0 = time.perf_counter()
    setting = (args.cell, args.cycles, args.validation_cycles)
    with ProcessPoolExecutor(max_workers=args.workers) as pool:
        demo_run = pool.submit(procedure_seed, args.seed, *setting)
        spread_runs = [pool.submit(vectorised_seed, seed, *setting) for seed in sorted({*range(args.seeds), args.seed})]
        shown = demo_run.result()
        runs = [run.result() for run in spread_runs]
    wall = time.perf_counter() - t0
    scored = [r for r in runs if r["seed"] < args.seeds]
    twin = next(r for r in runs if r["seed"] == args.seed)

    print(f"Seed {args.seed} on the {args.cell} cell, as `nanodrift demo --seed {args.seed} --cell {args.cell}` "
          f"prints it (model {shown['model']}):\n{shown['table1']}\n")
    print(f"Seed {args.seed} through the procedure (as the demo) and through the vectorised simulator, improvement "
          "against the truth: " + ", ".join(f"{t} {shown['tests'][t]['ratio']:.1f}x / {twin['tests'][t]['ratio']:.1f}x"
                                            for t in TESTS[1:]) + "\n")
    print(f"Table I over {len(scored)} seeds on the {args.cell} cell (vectorised simulator, {args.cycles} "
          f"calibration and {args.validation_cycles} validation sweeps): median [5th, 95th percentile], nm, scored "
          "against the TRUE position; AP: ISO 9283 accuracy; RMS and p95: per command |true error|")
    print(f"The paper's interferometer has an uncertainty < {INTERFEROMETER_FLOOR_NM:.0f} nm (III.A): on a lab's "
          "cell no figure below it can be verified.")
    head = (f"{'test':<6}| {'paper: without':>14}{'with':>6}{'ratio':>7} | {'AP without':>19}{'AP with':>17}"
            f"{'ratio x':>18}{'RP with':>16}{'RMS/command':>18}{'p95/command':>18}")
    print(head)
    print("-" * len(head))
    for test in TESTS:
        col = {k: [r["tests"][test][k] for r in scored] for k in scored[0]["tests"][test]}
        p0, p1 = PAPER_TABLE1[test]
        paper = f"{p0:>14.0f}{(f'{p1:.0f}' if p1 else '—'):>6}{(f'{p0 / p1:.1f}x' if p1 else '—'):>7}"
        compensated = test != "test1"
        print(f"{test:<6}| {paper} | {spread(col['ap_without']):>19}"
              f"{spread(col['ap_with']) if compensated else '—':>17}"
              f"{spread(col['ratio'], 1) if compensated else '—':>18}{spread(col['rp_with']):>16}"
              f"{spread(col['rms']):>18}{spread(col['p95']):>18}")
    print("(test 1 runs without the model, as the paper's: its RP, RMS and p95 are the stage's as it is)")

    ok = True
    floors = FLOORS_X[args.cell]
    print(f"\nFloors on the worst of {len(scored)} seeds (improvement against the truth):")
    for test, floor in floors.items():
        ratios = {r["seed"]: r["tests"][test]["ratio"] for r in scored}
        worst = min(ratios, key=ratios.__getitem__)
        below = sum(v < floor for v in ratios.values())
        passed = ratios[worst] >= floor
        ok &= passed
        print(f"{'PASS' if passed else 'FAIL'}  {test}: worst seed {worst} {ratios[worst]:.1f}x >= {floor:g}x "
              f"({below}/{len(ratios)} seeds below; median {np.median(list(ratios.values())):.1f}x, the paper "
              f"{PAPER_TABLE1[test][0] / (PAPER_TABLE1[test][1] or np.nan):.1f}x)")
    for test in TESTS[1:]:
        ratios = sorted(r["tests"][test]["ratio"] for r in scored)
        mine = shown["tests"][test]["ratio"]
        low, mid, high = np.percentile(ratios, [5, 50, 95])
        print(f"seed luck: seed {args.seed}'s {test} is {mine:.1f}x against the truth "
              f"({shown['tests'][test]['ratio_interferometer']:.1f}x as the interferometer sees it); over "
              f"{len(ratios)} seeds the median is {mid:.1f}x, 90 % within {low:.1f}-{high:.1f}x "
              f"(demo SEED_SPREAD_X: ({mid:.1f}, {low:.1f}, {high:.1f}))")
    if args.figure:
        command = f"python benchmarks/paper_table1.py --seeds {args.seeds} --cell {args.cell}"
        files = figure_over_seeds(scored, Path(args.figure), f"simulated {args.cell} cell, seeds 0-{args.seeds - 1}: "
                                  f"{command}")
        print(f"figure: {', '.join(str(f) for f in files)}")
    per_seed = [r["wall_s"] for r in runs]
    print(f"\n{wall:.0f} s wall on {args.workers} processes: seed {args.seed} through the procedure "
          f"{shown['wall_s']:.0f} s, {len(runs)} seeds vectorised {np.median(per_seed):.1f} s each (median)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
