"""The demo's two-axis part: an XY stage calibrated and validated as one cell, beside two one-axis models.

What ``nanodrift simulate --axes xy``, ``fit`` and ``validate`` do for an XY stage, in seconds: the
space-filling calibration of the stacked XY stage (24 cycles of the paper's 17 levels, 3.3 h of
simulated time, vectorised), one model per axis over both positions (``fit_cell``), then the paper's
test 2 (inside the training range) at ISO 9283 points off the calibration levels, scored against the
true position: Table I per axis and the pose accuracy AP in 2-D, beside the same data fitted as two
independent one-axis models (each axis' command from its own position) and the follow-up paper's
2-DoF anchor (1400 nm -> 200 nm).
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from nanodrift.calibration.dataset import write_csv
from nanodrift.calibration.iso9283 import TestResult, summarize_runs
from nanodrift.commands._cell import scenario_seed
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CellPhysics
from nanodrift.drivers.simulated.runs import cell_command, independent_command, run_cell_validation
from nanodrift.model.cell_model import save_cell_model
from nanodrift.model.identify import fit, fit_cell
from nanodrift.reports.validation import ANCHOR_2DOF_NM

AXES = ("x", "y")


def two_axis_part(seed: int, cycles: int, calibration_cycles: int, keep: Path | None) -> list[str]:
    """The lines the demo prints for the XY cell (and, with ``keep``, its data and model files)."""
    data = simulate_dataset("train", axes="xy", cycles=calibration_cycles, seed=seed)
    cell = fit_cell(data).model
    independent = {axis: fit(data.alone(axis)).model for axis in AXES}  # two one-axis cells' models
    test = "test2"
    physics = CellPhysics.create(test, seed=scenario_seed(seed, test), axes=AXES)
    run = run_cell_validation(physics, cell_command(cell), cycles=cycles, name=test)
    alone = run_cell_validation(physics, independent_command(independent), cycles=cycles, name=test)
    targets = run.targets_um
    truth = summarize_runs(test, targets, run.attained(False, "truth"), run.attained(True, "truth"))
    alone_truth = summarize_runs(test, targets, alone.attained(False, "truth"), alone.attained(True, "truth"))
    measured = summarize_runs(test, targets, run.attained(False, "interferometer"),
                              run.attained(True, "interferometer"))
    lines = [f"model {cell.id}: per axis, over both positions:"]
    lines += [f"   q_{axis} from {', '.join(cell.models[axis].term_names())}" for axis in AXES]
    head = f"   {'':<10}{'without':>10}{'two one-axis models':>22}{'one XY model':>15}{'improvement':>13}"
    lines += [f"{test} at ISO 9283 points off the calibration levels, {cycles} cycles, against the TRUE position:",
              head]
    picks: list[tuple[str, Callable[[TestResult, bool], float]]] = [
        *((f"axis {a}", lambda r, w, a=a: r.axis_accuracy_nm(a, with_model=w)) for a in AXES),
        ("AP 2-D", lambda r, w: r.accuracy_nm if w else r.accuracy_without_nm),
        ("RP 2-D", lambda r, w: r.repeatability_nm if w else r.repeatability_without_nm)]
    for label, pick in picks:
        before, alone_nm, after = pick(truth, False), pick(alone_truth, True), pick(truth, True)
        gain = f"{before / after:.0f}×" if after > 0 and not label.startswith("RP") else ""  # RP: spread, not bias
        lines.append(f"   {label:<10}{before:>7.0f} nm{alone_nm:>19.0f} nm{after:>12.0f} nm{gain:>13}")
    a0, a1 = ANCHOR_2DOF_NM
    lines.append(f"   (the interferometers read AP 2-D {measured.accuracy_nm:.0f} nm with the XY model; the follow-up "
                 f"paper's 2-DoF robot: {a0:.0f} nm -> {a1:.0f} nm, {a0 / a1:.0f}×)")
    lines.append("   Each axis' command depends on where the other axis is (crosstalk, non-orthogonality, bending): "
                 "two one-axis cells side by side cannot see it.")
    if keep is not None:
        write_csv(data, keep / "xy_calibration.csv")
        save_cell_model(cell, keep / "xy_model.json")
        lines.append(f"   kept: {keep / 'xy_calibration.csv'}, {keep / 'xy_model.json'}; "
                     f"nanodrift validate --model {keep / 'xy_model.json'} --scenario test2")
    return lines
