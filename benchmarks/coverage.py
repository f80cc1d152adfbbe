"""Is σ calibrated over calibrations? ``python benchmarks/coverage.py [--seeds N] [--cells population|single]``

Per seed s (one independent calibration): 24 ``train`` cycles of the REALISTIC simulated cell (vectorised
simulator) fitted by ``fit``; then ``test2`` (in the training range) and ``test5`` (~1.5 °C above it) through
the async validation procedure (``validate``'s code path, scenario seeds ``s*100 + N``), once with the
static model (σ = the model's ``q_sigma``) and once with the daemon's bias tracker (σ = ``q_sigma_adapted``).

Scored against the simulator's TRUE position (not the interferometer): per valid step e = true position −
target. Pooled over all seeds' steps (one run's steps share one calibration's offset, so only the pool over
calibrations says whether σ is calibrated, issue 27): the share of |e| <= 2σ and RMS(e/σ).
Goals: coverage 90-98 %, RMS(e/σ) 0.8-1.25, in and out of range, static and adaptive. Exits 1 if any
misses. Out of range the coverage is judged over RUNS, not steps: there a run's e/σ is nearly one value
(its cell's bending times g: within a run e/σ spreads 0.1, between runs 1), so N calibrations are N
samples, and a σ that is exactly calibrated (e/σ one N(0, 1) value per run) would meet "90-98 % of the
steps" on 16 runs with probability 0.36 only. The rule there: RMS(e/σ) 0.8-1.25 and the runs beyond 2σ
(median step) within the 95 % binomial interval of the 4.55 % a calibrated σ leaves beyond 2σ.
The noise model (daemon/model/uncertainty.py) was tuned on seeds 1000-1015; the default scored seeds
are 0..N-1 (disjoint). Both are printed.

``--cells single``: every seed calibrates and validates the ONE realistic cell, so test 5's true errors
carry that cell's own bending on every seed, which one calibration cannot see: σ must cover every
bending it cannot exclude and so errs wide there. ``--cells population`` (the default, 48 seeds) judges
σ over the cells one calibration cannot tell apart: per scored seed s a realistic cell whose bracket
bending k2 is drawn from N(-0.40, sd²) (``nanodrift.drivers.simulated.population``, numpy
default_rng(s)), sd = the median curvature allowance κ of the tuning seeds' calibrations (or
``--bending-sd``); that seed's training data, test 2 and test 5 all come from its cell. It prints the
single-cell table beside and exits 1 if the POPULATION misses.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from anywhere, never tests/drivers

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration.iso9283 import TestResult
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.commands._cell import scenario_seed
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import cell_variant
from nanodrift.drivers.simulated.population import BENDING_FIELD, drawn_cell
from nanodrift.model.identify import fit
from nanodrift.procedure.validation import run_validation

CELL = "realistic"
TESTS = {"test2": "in range", "test5": "out of range"}
MODES = ("static", "adaptive")
#: the seeds the noise model was tuned on (never scored by default)
TUNING_SEEDS = range(1000, 1016)
GOAL_COVERAGE = (0.90, 0.98)
GOAL_RMS_Z = (0.80, 1.25)
#: the tests judged over runs (a run is one sample there: see the module docstring)
JUDGED_BY_RUN = {"test5"}
#: the share of a calibrated σ's samples beyond 2σ, P(|N(0, 1)| > 2)
BEYOND_2SIGMA = float(2.0 * stats.norm.sf(2.0))
#: seeds per table: 16 steps-judged (the issue's minimum); 48 for the population, whose out-of-range rows are judged
#: over runs (RMS(e/σ) of 16 calibrated samples misses 0.8-1.25 with probability 0.22, of 48 with 0.03)
DEFAULT_SEEDS = {"single": 16, "population": 48}
#: the daemon's default tracker ([adapt] tau_s, max_um)
TRACKER_TAU_S, TRACKER_MAX_UM = 600.0, 1.0
#: the one realistic cell's bracket bending, µm/°C² (the population's mean)
OWN_K2 = getattr(cell_variant(CELL).params, BENDING_FIELD)


def true_errors(result: TestResult) -> tuple[np.ndarray, np.ndarray]:
    """The valid steps' true error (true position − target) and the σ of their command, µm."""
    rows = [(x_true - s.step.target(result.axis), sigma) for s, sigma, x_true
            in zip(result.steps, result.command_sigma_um, result.x_true_um, strict=True)
            if s.valid and np.isfinite(sigma)]
    error, sigma = (np.array(v) for v in zip(*rows, strict=True))
    return error, sigma


Run = dict[tuple[str, str], tuple[np.ndarray, np.ndarray]]


def calibration_kappa(seed: int) -> float:
    """κ (µm/°C²), the curvature allowance of seed ``seed``'s calibration of the one realistic cell."""
    curvature = fit(simulate_dataset("train", seed=scenario_seed(seed, "train"), cell=CELL)).model.covariance.curvature
    if curvature is None:
        raise RuntimeError(f"seed {seed}: the calibration's model has no curvature allowance to take κ from")
    return curvature.sd_um_per_c2


def one_seed(seed: int, cycles: int, cell: dict[str, float] | None = None) -> Run:
    """(test, mode) -> (true errors, σ) of one independent calibration and its validation runs; ``cell``: the
    magnitudes of this seed's cell (population), over the realistic cell's own (None: the one cell)."""
    overrides = cell or {}
    model = fit(simulate_dataset("train", seed=scenario_seed(seed, "train"), cell=CELL, **overrides)).model
    out = {}
    for test in TESTS:
        for mode in MODES:
            drivers = simulated_drivers(test, seed=scenario_seed(seed, test), cell=CELL, params=overrides or None)
            tracker = BiasTracker(TRACKER_TAU_S, TRACKER_MAX_UM) if mode == "adaptive" else None
            result = asyncio.run(run_validation(drivers, model, name=test, cycles=cycles,
                                                progress_stream=io.StringIO(), adapt=tracker))
            out[test, mode] = true_errors(result)
    return out


def score(errors: list[np.ndarray], sigmas: list[np.ndarray]) -> dict[str, Any]:
    e, s = np.concatenate(errors), np.concatenate(sigmas)
    z = e / s
    return {"coverage": float(np.mean(np.abs(z) <= 2.0)), "rms_z": float(np.sqrt(np.mean(z * z))),
            "steps": int(e.size), "rms_e_nm": 1e3 * float(np.sqrt(np.mean(e * e))),
            "sigma_nm": 1e3 * float(np.median(s)),
            "offset_sd_nm": 1e3 * float(np.std([err.mean() for err in errors])),
            # a run whose typical step lies beyond 2σ: out of range a run's e/σ is nearly one value (its cell's
            # bending), so the pool holds about one sample per calibration and the coverage moves in 1/N steps
            "runs_beyond": sum(int(np.median(np.abs(err / sig)) > 2.0)
                               for err, sig in zip(errors, sigmas, strict=True))}


def judge(test: str, s: dict[str, Any], runs: int) -> tuple[bool, str]:
    """Whether a row meets its goal, and the rule it was judged by (module docstring)."""
    rms_ok = GOAL_RMS_Z[0] <= s["rms_z"] <= GOAL_RMS_Z[1]
    if test in JUDGED_BY_RUN:
        lo, hi = (int(v) for v in stats.binom.interval(0.95, runs, BEYOND_2SIGMA))
        return rms_ok and lo <= s["runs_beyond"] <= hi, f"runs >2σ in {lo}..{hi}"
    return rms_ok and GOAL_COVERAGE[0] <= s["coverage"] <= GOAL_COVERAGE[1], "steps"


def table(runs: list[Run], seeds: list[int], saved: dict[str, np.ndarray], key: str) -> bool:
    """Print one pooled table (test x mode); True if every row meets the goals. Steps go into ``saved``."""
    head = (f"{'test':<7}{'range':<14}{'mode':<10}{'steps':>6}{'±2σ coverage':>14}{'RMS(e/σ)':>10}"
            f"{'RMS e nm':>10}{'median σ nm':>13}{'SD of run offsets nm':>22}{'runs >2σ':>10}  goal")
    print(head)
    print("-" * len(head))
    ok = True
    for test, where in TESTS.items():
        for mode in MODES:
            errors = [r[test, mode][0] for r in runs]
            sigmas = [r[test, mode][1] for r in runs]
            s = score(errors, sigmas)
            good, rule = judge(test, s, len(errors))
            ok &= good
            print(f"{test:<7}{where:<14}{mode:<10}{s['steps']:>6}{100 * s['coverage']:>13.1f}%{s['rms_z']:>10.2f}"
                  f"{s['rms_e_nm']:>10.0f}{s['sigma_nm']:>13.0f}{s['offset_sd_nm']:>22.0f}"
                  f"{str(s['runs_beyond']) + '/' + str(len(errors)):>10}  "
                  f"{'ok' if good else 'OUTSIDE'} ({rule})")
            for seed, err, sig in zip(seeds, errors, sigmas, strict=True):
                saved[f"{key}_{test}_{mode}_{seed}_e"], saved[f"{key}_{test}_{mode}_{seed}_s"] = err, sig
    return ok


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, help="independent calibrations (default: 16; 48 with --cells "
                                                  "population, whose out-of-range rows are judged over runs)")
    parser.add_argument("--first-seed", type=int, default=0, help="scored seeds: first-seed .. first-seed+seeds-1")
    parser.add_argument("--jobs", type=int, default=2, help="parallel processes")
    parser.add_argument("--cycles", type=int, default=30, help="validation cycles per test (ISO 9283: 30)")
    parser.add_argument("--cells", choices=("single", "population"), default="population",
                        help="single: every seed the one realistic cell; population: per seed a cell whose bending "
                             "is drawn (prints the single-cell table beside; exits 1 if the population misses)")
    parser.add_argument("--bending-sd", type=float,
                        help="population: the SD of the drawn bending k2, µm/°C² (default: the median κ of the "
                             f"tuning seeds' calibrations, {TUNING_SEEDS.start}..{TUNING_SEEDS.stop - 1})")
    parser.add_argument("--save", type=Path, help="write every step's error and σ to this .npz "
                                                  "(keys <single|population>_<test>_<mode>_<seed>_<e|s>)")
    args = parser.parse_args(argv)
    if args.bending_sd is not None and not (np.isfinite(args.bending_sd) and args.bending_sd >= 0):
        parser.error(f"--bending-sd: expected a finite number >= 0 (µm/°C²), got {args.bending_sd:g}")
    count = args.seeds if args.seeds is not None else DEFAULT_SEEDS[args.cells]
    seeds = list(range(args.first_seed, args.first_seed + count))
    tuned = set(TUNING_SEEDS) & set(seeds)
    population = args.cells == "population"
    start = time.perf_counter()
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        bending_sd, sd_source = args.bending_sd, "given (--bending-sd)"
        if population and bending_sd is None:
            kappas = list(pool.map(calibration_kappa, TUNING_SEEDS))
            bending_sd = float(np.median(kappas))
            sd_source = (f"the median κ of the tuning seeds' calibrations {TUNING_SEEDS.start}..{TUNING_SEEDS.stop - 1}"
                         f" (one realistic cell; κ {min(kappas):.2f}..{max(kappas):.2f})")
        cells = [drawn_cell(seed, bending_sd) for seed in seeds] if bending_sd is not None and population else []
        single = pool.map(one_seed, seeds, [args.cycles] * len(seeds))
        drawn = pool.map(one_seed, seeds, [args.cycles] * len(seeds), cells) if cells else iter(())
        single_runs, drawn_runs = list(single), list(drawn)
    wall = time.perf_counter() - start
    print(f"σ over independent calibrations, {CELL} cell, {len(seeds)} seeds {seeds[0]}..{seeds[-1]} scored; "
          f"noise model tuned on seeds {TUNING_SEEDS.start}..{TUNING_SEEDS.stop - 1}"
          + (f" (WARNING: {len(tuned)} scored seeds were tuning seeds)" if tuned else " (disjoint)"))
    print("scored against the TRUE position; pooled over all seeds' valid steps; "
          f"adaptive: bias tracker tau_s {TRACKER_TAU_S:g} s, max {TRACKER_MAX_UM:g} µm")
    print(f"goals: ±2σ coverage {GOAL_COVERAGE[0]:.0%}-{GOAL_COVERAGE[1]:.0%} of the steps, RMS(e/σ) "
          f"{GOAL_RMS_Z[0]:g}-{GOAL_RMS_Z[1]:g}; out of range over runs (one sample per calibration): RMS(e/σ) "
          f"and the runs beyond 2σ within the 95 % binomial interval of {BEYOND_2SIGMA:.2%}\n")
    saved: dict[str, np.ndarray] = {}
    print(f"ONE cell: every seed the realistic cell itself ({BENDING_FIELD} "
          f"{OWN_K2:g} µm/°C²)" + (" (beside; not judged)" if population else ""))
    ok = table(single_runs, seeds, saved, "single")
    if population:
        k2 = [c[BENDING_FIELD] for c in cells]
        print(f"\nPOPULATION of cells: per seed s a realistic cell with {BENDING_FIELD} ~ N("
              f"{OWN_K2:g}, {bending_sd:.3f}²) drawn with numpy default_rng(s); "
              f"sd = {sd_source}")
        print("drawn k2 µm/°C² per seed: " + ", ".join(f"{s}: {v:+.2f}" for s, v in zip(seeds, k2, strict=True)))
        ok = table(drawn_runs, seeds, saved, "population")
    if args.save:
        np.savez(args.save, **saved)
    judged = "the population's" if population else "the one cell's"
    print(f"\n{'all goals met' if ok else 'GOALS NOT MET'} ({judged} table); {wall:.0f} s wall, {args.jobs} processes")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
