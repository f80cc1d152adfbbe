"""Discovery that never hurts: does a named effect improve a fresh run, not just held-out blocks?

    nice .venv/bin/python benchmarks/discovery_fresh.py [--seeds 16]

For nothing hidden and for each effect of the simulator's catalogue hidden (its default
parameters), over ``--seeds`` seeds: a calibration run of the simulated cell (the runs of
``tests/calibration/test_discovery.py``: 24 ``train`` cycles; 48 for ``thermal_lag`` and
``unmonitored_drift``; up-and-down sweeps for ``hysteresis``), the paper's model fitted on it
(``fit --order 3``), ``discover`` on it; and ``thermal_curvature``: the same calibration plus 30
cycles of test 5's room (1.5 °C warmer, seed + 500) as a second run, the model fitted linear in
temperature; then both models predict a fresh run of the same scenario
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

Predicted beside measured: each report carries the fresh-run gain it expects (``final
["fresh_gain_expected"]``, RMS after / before, estimated from the calibration run alone; for
``unmonitored_drift`` with its source fixed). Printed: its median over the seeds beside the median
measured ratio, and the median of the per-seed quotient. Must hold, for every scenario, over the
seeds where something is named: the median predicted within a factor ``FACTOR`` of the median
measured. The predictor is the report's own (``nanodrift.calibration.discovery.confirmation``), with no
parameter fitted to these seeds; the fresh runs (seed + 1000) are never seen by discovery.
Exit status 1 when a seed is hurt or a prediction is off by more than ``FACTOR``. Measured against
the interferometer (``x_um`` of the fresh run, as a user measures it, and as the report predicts);
beside it, ``vs truth``: the same fresh run with a perfect interferometer, so x is the true position.
Known miss (measured, 16 seeds): on ``thermal_curvature`` seed 0 discovery names an unmonitored drift
after the curvature (test 5's room warms steadily, so in that run a line in time looks like what the
square leaves); the written model then costs the fresh run 1.63x. The report warns of it (a fresh
run with the drift's source still there: x 3.05), but the seed counts as hurt and the exit status is
1. Not fixed yet: a drift test that knows a second run of records is no calibration cycle.
``--predictor held-out`` puts the held-out ratio in its place (what the report implied before it
gave a fresh-run figure): it fails the check, which shows the check can fail.
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

from nanodrift.calibration.dataset import Dataset, concat
from nanodrift.calibration.discovery import discover
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.effects import EFFECTS
from nanodrift.model.identify import fit
from nanodrift.model.model import Model

HURT = 1.05
FACTOR = 1.5  # the predicted fresh-run gain must be within this factor of the measured one


@dataclass(frozen=True)
class Run:
    cycles: int = 24
    bidirectional: bool = False


RUNS = {"": Run(), "thermal_lag": Run(48), "unmonitored_drift": Run(48), "hysteresis": Run(bidirectional=True),
        # the user's default story (`nanodrift simulate` makes 24 cycles): the room falls and rises once,
        # so a lag of hours and a drift in time look alike and the lag's time constant is not pinned
        "thermal_lag@24": Run(24), "unmonitored_drift@24": Run(24)}
#: not a hidden effect: the bracket's bending is always in the cell, and shows over degrees. Its run is the
#: calibration plus a day of records in test 5's room, 1.5 °C warmer; the given model is eq. 3 linear in
#: temperature (``fit(..., squares=False)``), as a lab fitted it before the square was on offer
CURVATURE = "thermal_curvature"
DEFAULT = ",".join(["", *EFFECTS, "thermal_lag@24", "unmonitored_drift@24", CURVATURE])


def cell_run(effect: str, seed: int, source_fixed: bool = False, truth: bool = False) -> Dataset:
    """A run with ``effect`` hidden; ``source_fixed``: without an unmonitored drift (other effects stay);
    ``truth``: x is the true position (the interferometer's noise and wander switched off)."""
    if effect == CURVATURE:
        quiet = {"interferometer_noise_um": 0.0, "interferometer_wander_um": 0.0} if truth else {}
        return concat([simulate_dataset("train", cycles=24, seed=seed, **quiet),
                       simulate_dataset("test5", cycles=30, seed=seed + 500, **quiet)])
    run = RUNS.get(effect, Run())
    effect = effect.split("@")[0]
    hidden = None if not effect or (source_fixed and effect == "unmonitored_drift") else effect
    if truth:  # the same random streams: only the interferometer's noise and wander are scaled to 0
        return simulate_dataset("train", hidden, cycles=run.cycles, seed=seed, bidirectional=run.bidirectional,
                                interferometer_noise_um=0.0, interferometer_wander_um=0.0)
    return simulate_dataset("train", hidden, cycles=run.cycles, seed=seed, bidirectional=run.bidirectional)


def rms(data: Dataset, model: Model) -> float:
    assert data.q is not None
    return float(np.sqrt(np.mean((data.q - model.predict(data)) ** 2)))


@dataclass(frozen=True)
class Seed:
    named: list[str]
    ratio: float  # the judged fresh-run RMS ratio (after / before)
    detail: str
    same: float  # the ratio on a fresh run of the same scenario (an unmonitored drift still drifting)
    predicted: float  # the report's expected fresh-run ratio
    truth: float  # the judged ratio with the fresh run scored against the true position
    still_predicted: float  # an unmonitored drift: the report's expected ratio on a fresh run that still drifts
    seconds: float  # discover() wall time


def one(effect: str, seed: int, predictor: str = "report") -> Seed:
    data = cell_run(effect, seed)
    given = fit(data, order=3, squares=effect != CURVATURE).model
    start = time.perf_counter()
    result = discover(data, given)
    seconds = time.perf_counter() - start
    named = [s.effect for s in result.steps]
    if not named:
        return Seed(named, 1.0, "", 1.0, 1.0, 1.0, 1.0, seconds)
    fresh = cell_run(effect, seed + 1000)
    same = rms(fresh, result.model) / rms(fresh, given)
    ratio = same
    fixed = "unmonitored_drift" in named
    if fixed:
        judged = cell_run(effect, seed + 1000, source_fixed=True)
        ratio = rms(judged, result.model) / rms(judged, given)
    true_run = cell_run(effect, seed + 1000, source_fixed=fixed, truth=True)
    truth = rms(true_run, result.model) / rms(true_run, given)
    detail = ", ".join(f"{s.effect}({_param(s.params)})" for s in result.steps)
    still = [s.fresh_if_source_remains.ratio for s in result.steps if s.fresh_if_source_remains is not None]
    predicted = (float(result.final["fresh_gain_expected"]) if predictor == "report"
                 else result.final["holdout_rms_um"] / result.baseline["holdout_rms_um"])
    return Seed(named, ratio, detail, same, predicted, truth, still[0] if still else 1.0, seconds)


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
    parser.add_argument("--predictor", choices=("report", "held-out"), default="report",
                        help="the predicted ratio: the report's fresh_gain_expected, or the held-out ratio")
    parser.add_argument("--verbose", action="store_true", help="every seed's named steps and ratio")
    args = parser.parse_args()
    effects = args.effects.split(",")
    print(f"fresh-run RMS after/before discovery over {args.seeds} seeds of the simulated cell "
          f"(fresh run: seed + 1000); 'hurts' = worse by more than {100 * (HURT - 1):.0f} %\n")
    print(f"{'hidden':<27} {'named':>7} {'first ok':>9} {'ratio med':>10} {'worst':>7} {'predicted':>10} "
          f"{'measured':>9} {'pred/meas':>10} {'holds':>6} {'vs truth':>9} {'hurts':>6}  seeds hurt")
    worst_hurt, off = 0, []
    start = time.perf_counter()
    seconds: list[float] = []
    for effect in effects:
        rows = [one(effect, seed, args.predictor) for seed in range(args.seeds)]
        seconds += [r.seconds for r in rows]
        named = [r for r in rows if r.named]
        first_ok = sum(r.named[0] == effect.split("@")[0] for r in named)
        hurt = [seed for seed, r in enumerate(rows) if r.ratio > HURT]
        worst_hurt += len(hurt)
        label = effect or "nothing"
        ok = "-" if not effect else f"{first_ok}/{len(rows)}"
        if named:
            predicted = statistics.median(r.predicted for r in named)
            measured = statistics.median(r.ratio for r in named)
            quotient = statistics.median(r.predicted / r.ratio for r in named)
            holds = 1 / FACTOR <= predicted / measured <= FACTOR
            if not holds:
                off.append(label)
            truth = statistics.median(r.truth for r in named)
            figures = (f"{predicted:>10.3f} {measured:>9.3f} {quotient:>10.2f} {'yes' if holds else 'NO':>6} "
                       f"{truth:>9.3f}")
        else:
            figures = f"{'-':>10} {'-':>9} {'-':>10} {'-':>6} {'-':>9}"
        print(f"{label:<27} {len(named):>3}/{len(rows):<3} {ok:>9} {statistics.median(r.ratio for r in rows):>10.3f} "
              f"{max(r.ratio for r in rows):>7.3f} {figures} {len(hurt):>6}  "
              f"{', '.join(f'{s} ({rows[s].ratio:.2f}: {rows[s].detail})' for s in hurt) or '-'}")
        drifts = [r for r in rows if "unmonitored_drift" in r.named]
        if drifts:
            still = [r.same for r in drifts]
            print(f"{'':<27} ({len(drifts)} seed(s) named unmonitored_drift, judged with its source fixed; on a "
                  f"fresh run that still drifts: median {statistics.median(still):.2f}, worst {max(still):.2f}; "
                  f"predicted median {statistics.median(r.still_predicted for r in drifts):.2f})")
        if args.verbose:
            for seed, r in enumerate(rows):
                also = f" (same scenario {r.same:.3f})" if r.same != r.ratio else ""
                print(f"    seed {seed:2d}: measured {r.ratio:.3f}{also} predicted {r.predicted:.3f} "
                      f"{r.detail or '(nothing named)'}")
    print("\npredicted, measured: medians over the seeds where something is named of the fresh-run RMS ratio "
          "after / before (q - q_pred with x from the interferometer, as a user measures it); pred/meas: median "
          "per seed; vs truth: the measured ratio with x the stage's true position (the same fresh run, the "
          "interferometer's noise and wander off), not what the report predicts")
    print(f"{worst_hurt} seed(s) made worse by more than {100 * (HURT - 1):.0f} % on a fresh run; "
          f"{len(off)} scenario(s) predicted off by more than {FACTOR:g}x{': ' + ', '.join(off) if off else ''}; "
          f"discover() median {statistics.median(seconds):.2f} s, max {max(seconds):.2f} s per run; "
          f"{time.perf_counter() - start:.0f} s wall")
    return 0 if worst_hurt == 0 and not off else 1


if __name__ == "__main__":
    sys.exit(main())
