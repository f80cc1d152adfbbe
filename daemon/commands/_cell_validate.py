"""``nanodrift validate --model M.json`` with a multi-axis model: ISO 9283 on the simulated XY/XYZ cell.

The cell's axes come from the model file. The ISO 9283 plan (P1..P5 off the calibration levels,
``--cycles`` cycles, each point approached from both sides) runs on the simulated stacked stage
(:mod:`drivers.simulated.multiaxis`) through the model, and once more uncompensated in the same room
with the same noise; both are scored against the true position and against the interferometers.
A multi-axis cell on hardware (``--config``) is validated by the daemon's procedure, not built yet:
refused with a message.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

from daemon.calibration.iso9283 import summarize_cell
from daemon.commands._cell import scenario_list, scenario_seed
from daemon.errors import UserError
from daemon.model.cell_model import CellModel, load_any_model
from daemon.model.model import ModelFileError
from daemon.reports.cell_validation import CellScores, cell_json, cell_table, write_cell_report
from drivers.simulated.effects import UnknownNameError
from drivers.simulated.multiaxis import (
    CellValidationRun,
    CrossParams,
    MultiAxisPhysics,
    cell_command,
    cross_params,
    run_cell_validation,
)
from drivers.simulated.scenarios import get_scenario


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
    if args.config is not None:
        raise UserError(f"{args.model} serves axes {', '.join(model.axes)}: a multi-axis model is validated on the "
                        "simulated cell (no --config); the daemon's multi-axis procedure on hardware is not built yet")
    if args.adapt:
        raise UserError("--adapt runs the one-axis bias tracker: not available for a multi-axis model")
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
    physics = MultiAxisPhysics.create(model.axes, scenario, seed, cross)
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
