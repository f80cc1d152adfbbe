"""Does the model cost repeatability? ``python benchmarks/repeatability.py [--seeds 16] [--jobs 2]``

ISO 9283 pose repeatability RP (l̄ + 3·S_l per point, mean over the seven points) of the TRUE attained
position on the REALISTIC simulated cell, tests 1-4 (in range), each run twice in the same room with the same
noise: commanded through the model (fitted by ``fit`` on the seed's 24-cycle ``train`` calibration) and
uncompensated. A model whose thermal coefficients are large and of opposite signs passes each
thermocouple's noise into every command and makes RP worse than no model at all (issue 27).

Goal: the median over seeds of RP with / RP without (mean of the four tests) <= 1.1. Exits 1 if not.
``--selection`` compares the stepwise modes (``fit --selection``).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from anywhere, never tests/drivers

from nanodrift.calibration.iso9283 import pose_repeatability
from nanodrift.calibration.plans import VALIDATION_POINTS_UM, validation_plan
from nanodrift.commands._cell import scenario_seed
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CellPhysics
from nanodrift.drivers.simulated.runs import independent_command, simulate_steps
from nanodrift.model.identify import DEFAULT_SELECTION, SELECTIONS, fit
from nanodrift.model.terms import Channel

CELL = "realistic"
TESTS = ("test1", "test2", "test3", "test4")
GOAL_RATIO = 1.1


def repeatability_nm(true_um: np.ndarray, targets_um: np.ndarray) -> float:
    """ISO 9283 RP of the true positions, mean over the validation points (nm)."""
    return 1e3 * float(np.mean([pose_repeatability(true_um[targets_um == p][:, None])
                                for p in VALIDATION_POINTS_UM]))


def one_seed(seed: int, selection: str) -> dict[str, float]:
    """Per test RP with and without the model (nm), and the model's thermal coefficients' noise gain."""
    model = fit(simulate_dataset("train", seed=scenario_seed(seed, "train"), cell=CELL), selection=selection).model
    thermal = [ft.coef for ft in model.terms if isinstance(ft.term, Channel)]
    plan = validation_plan(30)
    targets = np.array([s.target_um for s in plan])
    cycles = [s.cycle for s in plan]
    out = {"noise_gain": float(np.linalg.norm(thermal)), "channels": float(len(thermal)),
           "sensitivity": float(sum(thermal))}
    for test in TESTS:
        physics = CellPhysics.create(test, seed=scenario_seed(seed, test), cell=CELL)
        without = simulate_steps(physics, {"x": targets}, cycles)["x_true_um"]
        with_ = simulate_steps(physics, {"x": targets}, cycles,
                               command_for=independent_command({"x": model}))["x_true_um"]
        out[f"{test}_without"] = repeatability_nm(without, targets)
        out[f"{test}_with"] = repeatability_nm(with_, targets)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--first-seed", type=int, default=0)
    parser.add_argument("--jobs", type=int, default=2)
    parser.add_argument("--selection", default=DEFAULT_SELECTION,
                        help=f"stepwise mode(s), comma-separated: {', '.join(SELECTIONS)}; the goal is the first's")
    args = parser.parse_args(argv)
    modes = [m.strip() for m in args.selection.split(",") if m.strip()]
    unknown = [m for m in modes if m not in SELECTIONS]
    if unknown or not modes:
        parser.error(f"--selection: unknown mode(s) {', '.join(unknown) or '(none)'}; valid: {', '.join(SELECTIONS)}")
    seeds = list(range(args.first_seed, args.first_seed + args.seeds))
    start = time.perf_counter()
    results = {}
    with ProcessPoolExecutor(max_workers=args.jobs) as pool:
        for mode in modes:
            results[mode] = list(pool.map(one_seed, seeds, [mode] * len(seeds)))
    wall = time.perf_counter() - start
    print(f"ISO 9283 repeatability RP of the TRUE position, {CELL} cell, tests {', '.join(TESTS)}, seeds "
          f"{seeds[0]}..{seeds[-1]}; median [5th, 95th percentile] over seeds")
    head = (f"{'selection':<11}{'RP without nm':>16}{'RP with nm':>16}{'with/without':>20}"
            f"{'channels':>10}{'|b_T| µm/°C':>16}{'Σb_T µm/°C':>18}")
    print(head)
    print("-" * len(head))
    verdict = True
    for i, mode in enumerate(modes):
        rows = results[mode]
        without = [statistics.fmean(r[f"{t}_without"] for t in TESTS) for r in rows]
        with_ = [statistics.fmean(r[f"{t}_with"] for t in TESTS) for r in rows]
        ratio = [w / o for w, o in zip(with_, without, strict=True)]

        def spread(v: list[float], digits: int = 0) -> str:
            lo, mid, hi = np.percentile(v, [5, 50, 95])
            return f"{mid:.{digits}f} [{lo:.{digits}f}, {hi:.{digits}f}]"

        print(f"{mode:<11}{spread(without):>16}{spread(with_):>16}{spread(ratio, 2):>20}"
              f"{spread([r['channels'] for r in rows]):>10}{spread([r['noise_gain'] for r in rows], 2):>16}"
              f"{spread([r['sensitivity'] for r in rows], 2):>18}")
        if i == 0:
            verdict = statistics.median(ratio) <= GOAL_RATIO
            goal_line = (f"goal ({mode}): median RP with/without {statistics.median(ratio):.2f} <= {GOAL_RATIO} -> "
                         f"{'met' if verdict else 'NOT met'}")
    print("|b_T|: the norm of the thermal coefficients (how much thermocouple noise reaches a command); "
          "Σb_T: the summed sensitivity")
    print(goal_line)
    print(f"{wall:.0f} s wall, {args.jobs} processes")
    return 0 if verdict else 1


if __name__ == "__main__":
    sys.exit(main())
