"""Discovery that never hurts: does a named effect improve a fresh run, not just held-out blocks?

    nice .venv/bin/python benchmarks/discovery_fresh.py [--seeds 16]

For nothing hidden and for each effect of the simulator's catalogue hidden (its default
parameters), over ``--seeds`` seeds: a calibration run of the simulated cell (the runs of
``tests/calibration/test_discovery.py``: 24 ``train`` cycles; 48 for ``thermal_lag`` and
``unmonitored_drift``; up-and-down sweeps for ``hysteresis``), the paper's model fitted on it
(``fit --order 3``), ``discover`` on it; then both models predict a fresh run of the same scenario
(seed + 1000, never seen) and the ratio of their RMS errors (after / before) is the figure: < 1
helps, > 1.05 hurts by more than 5 %. When nothing is named the model is unchanged (ratio 1).

Printed per scenario: how often something is named, how often the hidden effect is named first,
the fresh-run ratio (median, worst) and the seeds where it is worse by more than 5 %.
Each named effect is judged by what it promises. An applied effect (a term the daemon computes)
must improve the fresh run of the same scenario. ``unmonitored_drift`` is named but never applied
online: the written model keeps the thermal coefficients cleaned of the drift and the bias of the
run's start (where the interferometer was zeroed), and the operator is told to find the source; a
seed where it is named is judged on a fresh run of the same cell with the source fixed (the
acceptance test's criterion). The ratio on a fresh run that still drifts is printed beside it:
there the given model, whose bias absorbed the run's mean drift, is better by construction (a ramp
from 0 has twice the RMS of the same ramp centred).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from anywhere, never tests/drivers

from daemon.calibration.dataset import Dataset
from daemon.calibration.discovery import discover
from daemon.model.identify import fit
from daemon.model.model import Model
from drivers.simulated.datasets import simulate_dataset
from drivers.simulated.effects import EFFECTS

HURT = 1.05


@dataclass(frozen=True)
class Run:
    cycles: int = 24
    bidirectional: bool = False


RUNS = {"": Run(), "thermal_lag": Run(48), "unmonitored_drift": Run(48), "hysteresis": Run(bidirectional=True),
        # the user's default story (`nanodrift simulate` makes 24 cycles): the room falls and rises once,
        # so a lag of hours and a drift in time look alike and the lag's time constant is not pinned
        "thermal_lag@24": Run(24), "unmonitored_drift@24": Run(24)}
DEFAULT = ",".join(["", *EFFECTS, "thermal_lag@24", "unmonitored_drift@24"])


def cell_run(effect: str, seed: int, source_fixed: bool = False) -> Dataset:
    """A run with ``effect`` hidden; ``source_fixed``: without an unmonitored drift (other effects stay)."""
    run = RUNS.get(effect, Run())
    effect = effect.split("@")[0]
    hidden = None if not effect or (source_fixed and effect == "unmonitored_drift") else effect
    return simulate_dataset("train", hidden, cycles=run.cycles, seed=seed, bidirectional=run.bidirectional)


def rms(data: Dataset, model: Model) -> float:
    assert data.q is not None
    return float(np.sqrt(np.mean((data.q - model.predict(data)) ** 2)))


def one(effect: str, seed: int) -> tuple[list[str], float, str, float]:
    """(effects named, the judged fresh-run ratio, the steps in words, the same-scenario ratio)."""
    data = cell_run(effect, seed)
    given = fit(data, order=3).model
    result = discover(data, given)
    named = [s.effect for s in result.steps]
    if not named:
        return named, 1.0, "", 1.0
    fresh = cell_run(effect, seed + 1000)
    same = rms(fresh, result.model) / rms(fresh, given)
    ratio = same
    if "unmonitored_drift" in named:
        fixed = cell_run(effect, seed + 1000, source_fixed=True)
        ratio = rms(fixed, result.model) / rms(fixed, given)
    detail = ", ".join(f"{s.effect}({_param(s.params)})" for s in result.steps)
    return named, ratio, detail, same


def _param(params: dict) -> str:
    for key in ("tau_s", "channel", "order", "rate_um_per_h", "deadband_um"):
        if key in params:
            return f"{key}={params[key]}"
    return ""


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=16)
    parser.add_argument("--effects", default=DEFAULT,
                        help="comma-separated effects to hide (empty name: nothing hidden; name@24: a 24-cycle run)")
    parser.add_argument("--verbose", action="store_true", help="every seed's named steps and ratio")
    args = parser.parse_args()
    effects = args.effects.split(",")
    print(f"fresh-run RMS after/before discovery over {args.seeds} seeds of the simulated cell "
          f"(fresh run: seed + 1000); 'hurts' = worse by more than {100 * (HURT - 1):.0f} %\n")
    print(f"{'hidden':<27} {'named':>7} {'first ok':>9} {'ratio med':>10} {'worst':>7} {'hurts':>6}  seeds hurt")
    worst_hurt = 0
    start = time.perf_counter()
    for effect in effects:
        rows = [one(effect, seed) for seed in range(args.seeds)]
        named = sum(bool(r[0]) for r in rows)
        first_ok = sum(bool(r[0]) and r[0][0] == effect.split("@")[0] for r in rows)
        ratios = [r[1] for r in rows]
        hurt = [seed for seed, r in enumerate(rows) if r[1] > HURT]
        worst_hurt += len(hurt)
        label = effect or "nothing"
        ok = "-" if not effect else f"{first_ok}/{len(rows)}"
        print(f"{label:<27} {named:>3}/{len(rows):<3} {ok:>9} {statistics.median(ratios):>10.3f} {max(ratios):>7.3f} "
              f"{len(hurt):>6}  {', '.join(f'{s} ({rows[s][1]:.2f}: {rows[s][2]})' for s in hurt) or '-'}")
        drifts = [r for r in rows if "unmonitored_drift" in r[0]]
        if drifts:
            still = [r[3] for r in drifts]
            print(f"{'':<27} ({len(drifts)} seed(s) named unmonitored_drift, judged with its source fixed; on a "
                  f"fresh run that still drifts: median {statistics.median(still):.2f}, worst {max(still):.2f})")
        if args.verbose:
            for seed, (_, ratio, detail, same) in enumerate(rows):
                also = f" (same scenario {same:.3f})" if same != ratio else ""
                print(f"    seed {seed:2d}: {ratio:.3f}{also} {detail or '(nothing named)'}")
    print(f"\n{worst_hurt} seed(s) made worse by more than {100 * (HURT - 1):.0f} % on a fresh run; "
          f"{time.perf_counter() - start:.0f} s wall")
    return 0 if worst_hurt == 0 else 1


if __name__ == "__main__":
    sys.exit(main())
