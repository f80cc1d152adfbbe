"""Which stepwise selection does better on fresh runs: ``.venv/bin/python benchmarks/selection_modes.py``.

For each seed s: fit the ``train`` calibration of seed s with ``--selection paper`` (MATLAB's iid partial
F-tests) and ``--selection hac`` (Wald tests under the Newey-West covariance), then command the ISO 9283
validation points of scenarios test2..test5 of OTHER seeds (s+1000..) through the vectorised simulator
and score the error of the TRUE position against the target (RMS per command). Also printed: how many
temperature channels each mode kept, and the seed-to-seed SD of the summed thermal coefficient against
the mean standard error the fits print (HAC), so the printed SE can be judged.
"""

from __future__ import annotations

import argparse
import statistics
import sys

import numpy as np

from nanodrift.calibration.plans import validation_plan
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CellPhysics
from nanodrift.drivers.simulated.runs import independent_command, simulate_steps
from nanodrift.model.identify import SELECTIONS, fit, ols
from nanodrift.model.model import Model
from nanodrift.model.terms import Channel

TESTS = ("test2", "test3", "test4", "test5")


def fresh_rms_nm(model: Model, seed: int, cell: str = "ideal") -> dict[str, float]:
    """Per-command RMS of true position - target (nm) on each test scenario of a seed the model never saw."""
    plan = validation_plan(30)
    targets = np.array([s.target_um for s in plan])
    out = {}
    for name in TESTS:
        o = simulate_steps(CellPhysics.create(name, None, seed, cell=cell), {"x": targets}, [s.cycle for s in plan],
                           command_for=independent_command({"x": model}))
        out[name] = float(np.sqrt(np.mean((o["x_true_um"] - targets) ** 2)) * 1000.0)
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--cell", choices=("ideal", "realistic"), default="ideal",
                        help="the simulated cell fitted and scored (ideal: the paper's model form)")
    args = parser.parse_args()
    scores: dict[str, list[dict[str, float]]] = {m: [] for m in SELECTIONS}
    thermal: dict[str, list[tuple[float, float, int]]] = {m: [] for m in SELECTIONS}
    for seed in range(args.seeds):
        data = simulate_dataset("train", seed=seed, cell=args.cell)
        for mode in SELECTIONS:
            model = fit(data, selection=mode).model
            scores[mode].append(fresh_rms_nm(model, 1000 + seed, args.cell))
            # the summed thermal coefficient (the response to a common change) and its HAC SE, covariances included
            thermal_mask = np.array([isinstance(ft.term, Channel) for ft in model.terms])
            final = ols(model.features(data)[:, :-1], np.asarray(data.q))
            summed_se = float(np.sqrt(thermal_mask @ final.cov @ thermal_mask))
            thermal[mode].append((float(final.coef[thermal_mask[:-1]].sum()), summed_se, int(thermal_mask.sum())))
    print(f"fresh-run RMS of the true error per command (nm), fitted on seed s, scored on seed 1000+s, "
          f"{args.seeds} seeds: median [min..max]")
    for mode in SELECTIONS:
        line = "  ".join(
            f"{t} {statistics.median(v):6.1f} [{min(v):5.1f}..{max(v):6.1f}]"
            for t in TESTS for v in [[s[t] for s in scores[mode]]])
        overall = statistics.median(statistics.fmean(s.values()) for s in scores[mode])
        print(f"  {mode:5s}: {line}  | mean of tests, median over seeds {overall:6.1f}")
    for mode in SELECTIONS:
        sums = [t[0] for t in thermal[mode]]
        counts = [t[2] for t in thermal[mode]]
        print(f"  {mode:5s}: channels kept {min(counts)}..{max(counts)}; summed thermal coef SD over seeds "
              f"{statistics.stdev(sums):.3f} µm/°C (HAC SE of the sum, median "
              f"{statistics.median(t[1] for t in thermal[mode]):.3f})")
    wins = sum(statistics.fmean(h.values()) < statistics.fmean(p.values())
               for h, p in zip(scores["hac"], scores["paper"], strict=True))
    print(f"hac better than paper on {wins}/{args.seeds} seeds (mean of the tests)")
    for t in TESTS:
        won = sum(h[t] < p[t] for h, p in zip(scores["hac"], scores["paper"], strict=True))
        print(f"  {t}: hac better on {won}/{args.seeds} seeds")
    return 0


if __name__ == "__main__":
    sys.exit(main())
