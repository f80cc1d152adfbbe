"""``nanodrift validate --model M.json`` with a multi-axis model: ISO 9283 on the simulated XY/XYZ cell.

The cell's axes come from the model file. The ISO 9283 plan (P1..P5 off the calibration levels,
``--cycles`` cycles, each point approached from both sides) runs on the simulated stacked stage
(:mod:`nanodrift.drivers.simulated.runs`) through the model, and once more uncompensated in the same room
with the same noise; both are scored against the true position and against the interferometers.
With ``--config`` (an XY/XYZ cell on hardware, or the simulated one of ``[simulation] axes``) the same
plan is driven through the config's drivers (:mod:`nanodrift.procedure.cell_steps`): once uncompensated,
then through the model, each axis' position sensor averaged per step; scored against the sensors, and
against the true position where the cell knows it (simulated).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.calibration.iso9283 import CellTestResult, summarize_cell
from nanodrift.calibration.plans import cell_validation_plan
from nanodrift.commands._cell import guards, open_cell, run_procedure, scenario_list, scenario_seed
from nanodrift.commands._cell_calibrate import cell_drive, follow_checks
from nanodrift.config import Config
from nanodrift.drivers.simulated.config import SECTION, SimulationConfig
from nanodrift.drivers.simulated.effects import UnknownNameError
from nanodrift.drivers.simulated.physics import CellPhysics, CrossParams, cross_params
from nanodrift.drivers.simulated.runs import CellValidationRun, cell_command, run_cell_validation
from nanodrift.drivers.simulated.scenarios import get_scenario
from nanodrift.drivers_set import DriverSet
from nanodrift.errors import UserError
from nanodrift.model.cell_model import CellModel, load_any_model
from nanodrift.model.model import ModelFileError
from nanodrift.procedure.cell_steps import CellStepResult, run_cell_steps
from nanodrift.reports.cell_validation import CellScores, cell_json, cell_table, write_cell_report


def is_cell_model_file(path: str) -> bool:
    """Whether ``path`` holds a multi-axis model (``"axes"``); False for anything else (the one-axis load
    then says what is wrong with it)."""
    try:
        doc = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError, RecursionError):
        return False
    return isinstance(doc, dict) and "axes" in doc


def scores(run: CellValidationRun, against: str) -> CellScores:
    without = summarize_cell(run.name, run.targets_um, run.attained(False, against))
    with_model = (summarize_cell(run.name, run.targets_um, run.attained(True, against))
                  if run.compensated is not None else None)
    return CellScores(without, with_model)


def main(args: argparse.Namespace) -> int:
    try:
        model = load_any_model(args.model)
    except (ModelFileError, OSError) as err:
        raise UserError(str(err)) from None
    if not isinstance(model, CellModel):  # is_cell_model_file said so; a race with an editor
        raise UserError(f"{args.model}: not a multi-axis model")
    if args.adapt:
        raise UserError("--adapt runs the one-axis bias tracker: not available for a multi-axis model")
    if args.config is not None:
        return _on_drivers(args, model)
    missing = [c for c in model.channels if c not in ("T1", "T2", "T3", "T4")]
    if missing:
        raise UserError(f"{args.model} needs channel(s) {', '.join(missing)} that the simulated cell does not measure")
    scenarios = scenario_list(args.scenario) or ["test2"]
    try:
        for scenario in scenarios:  # every name checked before the first test runs
            get_scenario(scenario)
        cross = cross_params(args.effects or None)
    except (UnknownNameError, KeyError, ValueError) as err:
        raise UserError(f"simulated {''.join(model.axes)} cell: {err}") from None
    texts, docs = [], []
    for scenario in scenarios:
        text, doc = _one_test(args, model, scenario, cross)
        texts.append(text)
        docs.append(doc)
    if args.json:
        print(json.dumps(docs[0] if len(docs) == 1 else {"model": model.id, "tests": docs}, indent=2))
    else:
        print("\n\n".join(texts))
    return 0


def _one_test(args: argparse.Namespace, model: CellModel, scenario: str,
              cross: CrossParams) -> tuple[str, dict[str, Any]]:
    """One test on a fresh simulated cell: its Table I text and JSON document (and report, with --report:
    one directory per test when several are asked for)."""
    seed = scenario_seed(args.seed or 0, scenario)
    physics = CellPhysics.create(scenario, seed=seed, axes=model.axes, cross=cross)
    run = run_cell_validation(physics, None if args.no_compensation else cell_command(model), cycles=args.cycles,
                              name=scenario, out_of_range=lambda p, temps: bool(model.out_of_range(p, temps)))
    truth, measured = scores(run, "truth"), scores(run, "interferometer")
    text = cell_table(scenario, truth, measured)
    if run.extrapolating_steps:
        text += f"\n[{run.extrapolating_steps} steps extrapolating: outside the model's training ranges]"
    doc = cell_json(scenario, truth, measured, model=model.id, backend=f"simulated {''.join(model.axes)} cell, "
                    f"scenario {scenario}, seed {seed}", cycles=args.cycles,
                    extrapolating_steps=run.extrapolating_steps)
    if args.report:
        several = args.scenario is not None and len(scenario_list(args.scenario)) > 1
        directory = Path(args.report) / scenario if several else Path(args.report)
        files = write_cell_report(directory, text, doc, truth, run.targets_um, run.attained(False, "truth"),
                                  run.attained(True, "truth") if run.compensated is not None else None)
        print(f"report: {', '.join(str(f) for f in files)}", file=sys.stderr)
    return text, doc


def _on_drivers(args: argparse.Namespace, model: CellModel) -> int:
    """The ISO 9283 plan through the config's drivers, per ``--scenario`` (none: the config's room)."""
    texts, docs = [], []
    scenarios: list[str | None] = [*scenario_list(args.scenario)] or [None]
    for scenario in scenarios:
        text, doc = _driven_test(args, model, scenario)
        texts.append(text)
        docs.append(doc)
    if args.json:
        print(json.dumps(docs[0] if len(docs) == 1 else {"model": model.id, "tests": docs}, indent=2))
    else:
        print("\n\n".join(texts))
    return 0


def _driven_run(args: argparse.Namespace, model: CellModel, scenario: str | None,
                compensate: bool) -> tuple[Config, DriverSet, list[CellStepResult]]:
    """One run of the plan on a fresh cell (a simulated one restarts its room: both runs see the same one)."""
    config, drivers = open_cell(argparse.Namespace(**{**vars(args), "scenario": scenario}), "test2")
    if sorted(config.axis_names) != sorted(model.axes):
        raise UserError(f"{args.model} serves axes {', '.join(model.axes)}, {config.source} has axes "
                        f"{', '.join(config.axis_names)}")
    drive = cell_drive(config, drivers)
    workspaces = {axis: actuator.workspace_um for axis, actuator in config.axis_actuators().items()}
    plan = cell_validation_plan(drive.axes, args.cycles, workspaces)
    evaluator = model.evaluator()
    _, ready = guards(config, drivers, args)
    try:
        results = run_procedure(run_cell_steps(
            drive, plan, timing=config.procedure.timing,
            command_for=(lambda targets, t: evaluator.command(targets, t)) if compensate else None,
            on_temperatures=evaluator.observe, follow=follow_checks(config, drive), ready=ready))
    except ValueError as err:
        raise UserError(str(err)) from None
    return config, drivers, results


def _driven_scores(name: str, runs: list[list[CellStepResult]], against: str) -> CellScores:
    def summary(results: list[CellStepResult]) -> CellTestResult:
        axes = tuple(results[0].q_um)
        targets = {a: np.array([r.step.target(a) for r in results]) for a in axes}
        read = (lambda r: r.true_um) if against == "truth" else (lambda r: r.positions_um)
        return summarize_cell(name, targets, {a: np.array([read(r)[a] for r in results]) for a in axes})

    return CellScores(summary(runs[0]), summary(runs[1]) if len(runs) > 1 else None)


def _driven_test(args: argparse.Namespace, model: CellModel, scenario: str | None) -> tuple[str, dict[str, Any]]:
    config, drivers, without = _driven_run(args, model, scenario, compensate=False)
    runs = [without]
    if not args.no_compensation:
        runs.append(_driven_run(args, model, scenario, compensate=True)[2])
    section = config.section(SECTION)
    name = scenario or (section.scenario if isinstance(section, SimulationConfig) else "validation")
    measured = _driven_scores(name, runs, "interferometer")
    knows_truth = all(math.isfinite(v) for run in runs for r in run for v in r.true_um.values())
    truth = _driven_scores(name, runs, "truth") if knows_truth else measured
    text = cell_table(name, truth, measured)
    before = "without comp.: the same plan run uncompensated (command = target) in the same room, same noise."
    text = text.replace(before, f"without comp.: the same plan run uncompensated (command = target) first, then "
                        f"through the model, on {drivers.description} ({config.source})"
                        + ("" if knows_truth else "; no true position on hardware: the TRUE columns repeat the "
                           "position sensors'") + ".")
    invalid = sum(not r.valid for run in runs for r in run)
    if invalid:
        text += f"\n[{invalid} steps kept with a dirty window (valid = 0) are scored as measured]"
    doc = cell_json(name, truth, measured, model=model.id, backend=f"{drivers.description} ({config.source})",
                    cycles=args.cycles, truth_known=knows_truth)
    if args.report:
        several = args.scenario is not None and len(scenario_list(args.scenario)) > 1
        directory = Path(args.report) / name if several else Path(args.report)
        targets = {a: np.array([r.step.target(a) for r in without]) for a in model.axes}
        attained = [{a: np.array([(r.true_um if knows_truth else r.positions_um)[a] for r in run])
                     for a in model.axes} for run in runs]
        files = write_cell_report(directory, text, doc, truth, targets, attained[0],
                                  attained[1] if len(attained) > 1 else None)
        print(f"report: {', '.join(str(f) for f in files)}", file=sys.stderr)
    return text, doc
