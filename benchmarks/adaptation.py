"""Table I over seeds of the simulated cell, static model versus adaptive (the daemon's bias tracker),
scored against the TRUE position as well as the interferometer, and whether ``q_sigma_um`` is calibrated.

    nice python benchmarks/adaptation.py [--seeds 8] [--tau-s 600] [--cycles 30]

Per seed: a 24-cycle ``train`` calibration (vectorised simulator, the same physics and step schedule
as the procedure), fitted by ``fit``; then tests 2-5 (``validate`` on the simulated cell through the
async procedure, scenario ``testN``, seed ``seed * 100 + N``) once with the static model and once
with ``--adapt`` (``BiasTracker(tau_s, max_um)``, the daemon's tracker, fed by each valid step's
residual). Both runs of a test see the same room, sensors and noise. Improvement = without / with
(Table I: "without" is computed from the same run, x - (q - x')).

Two views of accuracy: the interferometer's (what Table I measures, as on the bench) and the truth's
(the simulated cell's true attained position over the same averaging window). The tracker is fed by
the interferometer, so it follows the interferometer's own slow wander (25 nm, ~20 min): its gain
looks larger through the interferometer than it is in truth.

Goals (issue 12): adaptive test 5 median >= 10x and worst >= 5x (interferometer's view, as Table I);
on tests 2-4 the adaptive run is never worse than the static one against the truth on any seed.
Coverage (issue 19): per test and seed, the share of the valid steps whose TRUE error (true position
- target) lies within ±2σ; goal 90-98 % (median over the seeds), no seed below 80 %. σ is the
model's q_sigma in the static runs and the corrected command's q_sigma_adapted (what the tracker
leaves, ``BiasTracker.sigma_um``) in the adaptive ones. With the true errors in hand it also scans
which widths could meet the goal at all (the oracle), for both kinds of run.
"""

from __future__ import annotations

import argparse
import asyncio
import io
import statistics
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from anywhere, never tests/drivers

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration.iso9283 import TestResult
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.model.identify import fit
from nanodrift.procedure.validation import run_validation

TESTS = ("test2", "test3", "test4", "test5")
GOAL_TEST5_MEDIAN, GOAL_TEST5_WORST = 10.0, 5.0


def one_seed(seed: int, cycles: int, tau_s: float, max_um: float) -> dict[str, dict[str, Any]]:
    model = fit(simulate_dataset("train", cycles=24, seed=seed)).model
    out: dict[str, dict[str, Any]] = {}
    for name in TESTS:
        run_seed = seed * 100 + int(name[-1])
        static = asyncio.run(run_validation(simulated_drivers(name, seed=run_seed), model, name=name, cycles=cycles,
                                            progress_stream=io.StringIO()))
        tracker = BiasTracker(tau_s, max_um)
        adaptive = asyncio.run(run_validation(simulated_drivers(name, seed=run_seed), model, name=name,
                                              cycles=cycles, progress_stream=io.StringIO(), adapt=tracker))
        out[name] = {
            "static": static.improvement, "adaptive": adaptive.improvement,
            "static_nm": static.accuracy_nm, "adaptive_nm": adaptive.accuracy_nm,
            "static_true_nm": static.accuracy_true_nm, "adaptive_true_nm": adaptive.accuracy_true_nm,
            "coverage_true": static.coverage_true(), "coverage_measured": static.coverage(),
            "coverage_true_adaptive": adaptive.coverage_true(),
            "sigma_nm": statistics.median(static.q_sigma_um) * 1e3,
            "adaptive_sigma_nm": statistics.median(adaptive.q_sigma_adapted_um) * 1e3,
            **true_errors(static),
            "adaptive_steps": true_errors(adaptive),
        }
    return out


def true_errors(result: TestResult) -> dict[str, Any]:
    """A run's valid steps: true error (true position - target) and the σ of its command, nm."""
    rows = [(x_true - s.step.target(result.axis), sigma) for s, sigma, x_true
            in zip(result.steps, result.command_sigma_um, result.x_true_um, strict=False)
            if s.valid and np.isfinite(sigma)]
    error, sigma = (np.array(v) * 1e3 for v in zip(*rows, strict=True))
    return {"error_nm": error, "q_sigma_nm": sigma}


def coverage_goal_met(per_seed: list[float]) -> bool:
    return 90.0 <= statistics.median(per_seed) <= 98.0 and min(per_seed) >= 80.0


def constant_widths(errors: list[np.ndarray]) -> str:
    """The range of one σ (nm) for every step of every seed that meets the per-seed goal, or none."""
    ok = [w for w in np.geomspace(1.0, 2000.0, 400)
          if coverage_goal_met([100 * float(np.mean(np.abs(e) <= 2 * w))  for e in errors])]
    return f"{min(ok):.3g}-{max(ok):.3g} nm" if ok else "none"


def oracle_scan(runs: list[dict[str, dict[str, Any]]], name: str) -> tuple[str, str, str]:
    """Could ANY σ of the calibration's kind meet the per-seed goal on these very errors?

    σ comes from the calibration alone, so it cannot know the offset a seed's calibration left. Two
    families are scanned with the true errors in hand (an oracle): one σ for every step of every
    seed, and q_sigma scaled by one factor c. Each answer is the range that meets the goal, or none.
    """
    errors = [r[name]["error_nm"] for r in runs]
    sigmas = [r[name]["q_sigma_nm"] for r in runs]

    def meets(c: float) -> bool:
        inside = [100 * float(np.mean(np.abs(e) <= 2 * c * w)) for e, w in zip(errors, sigmas, strict=True)]
        return coverage_goal_met(inside)

    ok = [c for c in np.geomspace(0.05, 5.0, 400) if meets(c)]
    constant = constant_widths(errors)
    scaled = f"{min(ok):.3g}-{max(ok):.3g}x" if ok else "none"
    # the factor at which q_sigma would hold 95 % of the steps pooled over the seeds (the usual calibration)
    ratio = np.abs(np.concatenate(errors)) / (2 * np.concatenate(sigmas))
    return constant, scaled, f"{float(np.quantile(ratio, 0.95)):.2f}x"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--tau-s", type=float, default=600.0, help="the tracker's time constant ([adapt] tau_s)")
    parser.add_argument("--max-um", type=float, default=1.0, help="clamp on the correction ([adapt] max_um)")
    parser.add_argument("--cycles", type=int, default=30, help="validation cycles per test (ISO 9283: 30)")
    args = parser.parse_args()

    print(f"Table I over {args.seeds} seeds of the simulated cell: static model vs adaptive "
          f"(bias tracker tau_s {args.tau_s:g} s, max {args.max_um:g} um)")
    print(f"calibration: 24 train cycles (vectorised simulator) + fit; validation: {args.cycles} cycles per test "
          "through the async procedure, static and adaptive on the same room and noise\n")
    start = time.perf_counter()
    runs = [one_seed(seed, args.cycles, args.tau_s, args.max_um) for seed in range(args.seeds)]
    wall = time.perf_counter() - start

    print("accuracy with compensation (nm), static -> adaptive, against the interferometer | against the TRUE position")
    print("seed  " + "  ".join(f"{name:>27}" for name in TESTS))
    for seed, run in enumerate(runs):
        print(f"{seed:4d}  " + "  ".join(
            f"{run[n]['static_nm']:5.0f}->{run[n]['adaptive_nm']:4.0f} | {run[n]['static_true_nm']:5.0f}->"
            f"{run[n]['adaptive_true_nm']:4.0f}   " for n in TESTS))
    print("\n        improvement (interferometer's view, Table I)     accuracy nm, median over seeds        "
          "adaptive worse than static")
    print("        static (median, worst)  adaptive (median, worst)  interferometer      truth            "
          "(truth)")
    ok = True
    for name in TESTS:
        s = [r[name]["static"] for r in runs]
        a = [r[name]["adaptive"] for r in runs]
        worse = sum(r[name]["adaptive_true_nm"] > r[name]["static_true_nm"] for r in runs)
        nm = {key: statistics.median(r[name][key] for r in runs)
              for key in ("static_nm", "adaptive_nm", "static_true_nm", "adaptive_true_nm")}
        print(f"  {name}  {statistics.median(s):6.1f}x {min(s):6.1f}x      {statistics.median(a):6.1f}x {min(a):6.1f}x"
              f"        {nm['static_nm']:5.0f} -> {nm['adaptive_nm']:4.0f}    {nm['static_true_nm']:5.0f} -> "
              f"{nm['adaptive_true_nm']:4.0f}        {worse}/{len(runs)} seeds")
        if name != "test5":
            ok &= worse == 0
    a5 = [r["test5"]["adaptive"] for r in runs]
    goal5 = statistics.median(a5) >= GOAL_TEST5_MEDIAN and min(a5) >= GOAL_TEST5_WORST
    print(f"\ngoal: adaptive test5 median >= {GOAL_TEST5_MEDIAN:g}x and worst >= {GOAL_TEST5_WORST:g}x "
          f"(interferometer's view): {statistics.median(a5):.1f}x / {min(a5):.1f}x -> {'met' if goal5 else 'NOT met'}")
    print(f"goal: tests 2-4 adaptive never worse than static against the truth on any seed -> "
          f"{'met' if ok else 'NOT met'}")

    print("\nuncertainty: share of the valid steps with |TRUE position - target| <= 2 q_sigma, per seed "
          "(goal 90-98 % median over seeds, no seed below 80 %);")
    print("  static: the model's q_sigma; adaptive: q_sigma_adapted (BiasTracker.sigma_um: what it has not yet "
          "corrected, the interferometer's wander it follows, its recent residuals); 'mean' pools the seeds;")
    print("  'interferometer': the static runs' measured errors within ±2 sqrt(q_sigma² + wander²), median over seeds")
    print("                 " + "".join(f"{seed:>5d}" for seed in range(len(runs)))
          + "  median   mean  worst  q_sigma  interferometer")
    covered = {"static": True, "adaptive": True}
    for mode, key, sigma_key in (("static", "coverage_true", "sigma_nm"),
                                 ("adaptive", "coverage_true_adaptive", "adaptive_sigma_nm")):
        for name in TESTS:
            per_seed = [100 * r[name][key] for r in runs]
            median, worst = statistics.median(per_seed), min(per_seed)
            mean = statistics.fmean(per_seed)
            good = coverage_goal_met(per_seed)
            covered[mode] &= good
            sigma_nm = statistics.median(r[name][sigma_key] for r in runs)
            measured = (f"{statistics.median(100 * r[name]['coverage_measured'] for r in runs):12.1f} %"
                        if mode == "static" else " " * 14)
            print(f"  {mode:>8} {name}" + "".join(f"{c:5.0f}" for c in per_seed)
                  + f"  {median:6.1f} {mean:6.1f}  {worst:5.0f} {sigma_nm:6.0f} nm  {measured}"
                  f"  {'ok' if good else 'OUTSIDE the goal'}")
    for mode, good in covered.items():
        print(f"goal: coverage, {mode} -> {'met' if good else 'NOT met'}")
    covered_all = all(covered.values())

    print("\nwhy: the static runs' true error per seed is one offset (what the calibration's own interferometer "
          "wander left in the bias and the")
    print("temperature coefficients, plus what a linear thermal model misses) and a scatter about it. A seed's "
          "coverage is near 100 % or near 0 %")
    print("unless the scatter is comparable to the offsets. 'offset' = each seed's mean true error, "
          "'scatter' = its SD; 'oracle' = the widths that would meet")
    print("the goal, scanned with the true errors in hand: one σ for all seeds, or q_sigma times one factor "
          "('none': no such width exists);")
    print("'pooled 95 %': the factor at which c·q_sigma would hold 95 % of the steps of all seeds together "
          "(1.00x: q_sigma calibrated pooled)")
    print("'adaptive': the same for the adaptive runs' true errors (the tracker removes the calibration's offset; "
          "what is left is the")
    print("interferometer's wander it followed, again shared by a run's steps): one σ for all seeds, with the truth "
          "in hand")
    print("        offsets by seed (nm)" + " " * 23
          + "RMS  scatter (median)  oracle: one σ      c·q_sigma  pooled 95 %   adaptive: offsets by seed"
          + " " * 26 + "one σ  pooled 95 %")
    for name in TESTS:
        offsets = [float(np.mean(r[name]["error_nm"])) for r in runs]
        scatter = statistics.median(float(np.std(r[name]["error_nm"])) for r in runs)
        rms = float(np.sqrt(np.mean(np.square(offsets))))
        constant, scaled, pooled = oracle_scan(runs, name)
        adaptive_errors = [r[name]["adaptive_steps"]["error_nm"] for r in runs]
        adaptive_ratio = (np.abs(np.concatenate(adaptive_errors))
                          / (2 * np.concatenate([r[name]["adaptive_steps"]["q_sigma_nm"] for r in runs])))
        print(f"  {name}" + "".join(f"{o:6.0f}" for o in offsets)
              + f"  {rms:6.0f}  {scatter:8.0f}          {constant:>12}  {scaled:>12}  {pooled:>10}   "
              + "".join(f"{float(np.mean(e)):5.0f}" for e in adaptive_errors)
              + f"  {constant_widths(adaptive_errors):>14}  {float(np.quantile(adaptive_ratio, 0.95)):10.2f}x")
    print(f"\n{wall:.0f} s wall")
    return 0 if goal5 and ok and covered_all else 1


if __name__ == "__main__":
    sys.exit(main())
