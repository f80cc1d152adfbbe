"""Multi-axis cells on the simulated XY and XYZ stages: ``python benchmarks/multiaxis.py``.

Per cell (2 and 3 axes) and seed (8 each, seeds 0..7; the stage's magnitudes were set on seeds 100..103):

1. Calibration: the space-filling plan (``nanodrift.calibration.plans.cell_calibration_plan``: 24 cycles of 17
   steps, 4 s ramp + 25 s hold, 3.3 h) through the vectorised multi-axis run in the ``train`` room;
   fitted with ``fit_cell`` (cross terms) and, on the same rows, as independent one-axis models of
   the paper's form (each axis' command on its own position and T1..T4: ``fit`` on a one-axis view).
2. Validation: ISO 9283 points P1..P5 off the calibration levels, 30 cycles both ways, in range
   (``test2`` room) and out of range (``test5`` room, ~1.5 °C above training). Each test runs twice
   in the same room with the same noise: uncompensated (command = target) and through the model.
   Accuracy: ISO 9283 pose accuracy AP in 2-D/3-D (distance from the barycentre of the attained
   points to the target), mean over the five points, against the TRUE position and against the
   interferometers' readings.
3. Must hold (printed PASS/FAIL): improvement >= 10x in range and >= 4x out of range on every seed,
   for 2 and 3 axes, against the truth. Anchor: Tan, Clévy, Chaillet (Micromachines 2015), a 2-DoF
   stage: 2-D accuracy 1400 nm -> 200 nm (7x).
"""

from __future__ import annotations

import argparse
import sys
import time

from nanodrift.calibration.iso9283 import summarize_runs
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CellPhysics
from nanodrift.drivers.simulated.runs import CellValidationRun, cell_command, independent_command, run_cell_validation
from nanodrift.model.identify import fit, fit_cell

ANCHOR = (1400.0, 200.0)  # Tan, Clévy, Chaillet 2015: 2-DoF accuracy without / with, nm
FLOORS = {"test2": 10.0, "test5": 4.0}
TESTS = {"test2": "in range", "test5": "out of range"}


def accuracy_nm(run: CellValidationRun, with_model: bool, against: str) -> float:
    result = summarize_runs(run.name, run.targets_um, run.attained(False, against), run.attained(True, against))
    return result.accuracy_nm if with_model else result.accuracy_without_nm


def one_seed(axes: str, seed: int) -> list[dict[str, float | str]]:
    data = simulate_dataset("train", axes=axes, seed=seed)
    cell = fit_cell(data).model
    singles = {a: fit(data.alone(a)).model for a in data.axes}
    rows: list[dict[str, float | str]] = []
    for test in TESTS:
        test_seed = seed * 100 + int(test[-1])  # the paper's tests draw their own room and noise (scenario_seed)
        physics = CellPhysics.create(test, seed=test_seed, axes=axes)
        run = run_cell_validation(physics, cell_command(cell), name=test,
                                  out_of_range=lambda p, temps: bool(cell.out_of_range(p, temps)))
        alone = run_cell_validation(physics, independent_command(singles), name=test)
        row: dict[str, float | str] = {"axes": axes, "seed": seed, "test": test,
                                       "extrapolating": run.extrapolating_steps}
        for against, key in (("truth", "true"), ("interferometer", "ifm")):
            row[f"without_{key}"] = accuracy_nm(run, False, against)
            row[f"with_{key}"] = accuracy_nm(run, True, against)
            row[f"alone_{key}"] = accuracy_nm(alone, True, against)
        rows.append(row)
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="multi-axis cells: cross-term model vs independent one-axis models")
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--axes", default="xy,xyz", help="cells to run, comma-separated (default xy,xyz)")
    args = parser.parse_args(argv)
    t0 = time.perf_counter()
    rows = [r for axes in args.axes.split(",") for seed in range(args.seeds) for r in one_seed(axes, seed)]
    wall = time.perf_counter() - t0

    print("ISO 9283 pose accuracy AP (mean over P1..P5, nm), 2-D for xy, 3-D for xyz; 30 cycles both ways per test")
    print("  true: against the true position; ifm: against the interferometers' readings")
    print("  cell: one model with cross terms (fit_cell); alone: independent one-axis models of the paper's form")
    head = (f"{'cell':<5}{'seed':>5} {'test':<21}{'without':>9}{'cell':>7}{'ratio':>8}{'alone':>7}{'ratio':>7}"
            f" | {'ifm: without':>12}{'cell':>7}{'ratio':>8}{'alone':>7}{'ratio':>7}")
    print(head)
    print("-" * len(head))
    ok = True
    verdicts: dict[tuple[str, str], list[float]] = {}
    for r in rows:
        ratio = float(r["without_true"]) / float(r["with_true"])
        verdicts.setdefault((str(r["axes"]), str(r["test"])), []).append(ratio)
        label = f"{r['test']} ({TESTS[str(r['test'])]})"
        extra = f"  [{r['extrapolating']} steps extrapolating]" if r["extrapolating"] else ""
        print(f"{r['axes']:<5}{r['seed']:>5} {label:<21}{r['without_true']:>9.0f}{r['with_true']:>7.0f}{ratio:>7.1f}×"
              f"{r['alone_true']:>7.0f}{float(r['without_true']) / float(r['alone_true']):>6.1f}×"
              f" | {r['without_ifm']:>12.0f}{r['with_ifm']:>7.0f}"
              f"{float(r['without_ifm']) / float(r['with_ifm']):>7.1f}×{r['alone_ifm']:>7.0f}"
              f"{float(r['without_ifm']) / float(r['alone_ifm']):>6.1f}×{extra}")
    print(f"anchor (Tan, Clévy, Chaillet, Micromachines 2015, 2-DoF): {ANCHOR[0]:.0f} nm -> {ANCHOR[1]:.0f} nm "
          f"({ANCHOR[0] / ANCHOR[1]:.0f}×)")
    print()
    for (axes, test), ratios in verdicts.items():
        passed = all(v >= FLOORS[test] for v in ratios)
        ok &= passed
        print(f"{'PASS' if passed else 'FAIL'}: {axes} {test} ({TESTS[test]}): improvement against the truth "
              f"min {min(ratios):.1f}× >= {FLOORS[test]:.0f}× on every seed ({len(ratios)} seeds; "
              f"median {sorted(ratios)[len(ratios) // 2]:.1f}×)")
    print(f"\n{len(rows)} tests in {wall:.1f} s wall (calibration 408 steps = 3.3 h simulated per seed)")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
