"""``nanodrift validate``: ISO 9283 accuracy and repeatability with and without the model (Table I).

``--adapt`` runs the daemon's bias tracker (``[adapt] mode = "bias"``) over the test, one per axis as the
daemon does, so a lab can see offline what adaptation would have given.

On the simulated cell ``--scenario`` may name several tests (``--scenario test2,test3,test5``, or
repeated): each runs in turn and one report holds them all (Table I a row per test, the figures
comparing them). There each step is also scored against the true position the cell knows
(the simulated cell's sensor group), beside the interferometer's view.

A multi-axis model (``"axes"``) is validated on a cell of its axes: without ``--config`` on the
simulated stacked stage (:mod:`nanodrift.drivers.simulated.runs`), the ISO 9283 plan (P1..P5 off
the calibration levels) run through the model and once more uncompensated in the same room with the
same noise; with ``--config`` through the config's drivers (:func:`nanodrift.procedure.steps.run_steps`),
once uncompensated, then through the model. It prints Table I per axis and AP/RP in 2-D/3-D, scored
against the position sensors and against the true position where the cell knows it. With ``--adapt`` and
no ``--config`` it runs through the drivers of the built-in simulated cell of the model's axes: the trackers
need each step's residual before the next command, which the vectorised stage does not give.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.calibration.iso9283 import TestResult, summarize_runs
from nanodrift.calibration.plans import StepResult, cell_validation_plan
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.commands import _cell
from nanodrift.config import Config, ConfigError, load_config, parse_config
from nanodrift.drivers.simulated.config import SECTION, SimulationConfig
from nanodrift.drivers.simulated.effects import UnknownNameError
from nanodrift.drivers.simulated.physics import CellPhysics, cross_params
from nanodrift.drivers.simulated.runs import cell_command, run_cell_validation
from nanodrift.drivers.simulated.scenarios import get_scenario
from nanodrift.drivers_set import DriverSet
from nanodrift.errors import UserError, user_errors
from nanodrift.model.cell_model import CellModel, load_any_model
from nanodrift.model.model import Model, ModelFileError
from nanodrift.procedure.validation import check_channels, run_validation, run_validation_steps
from nanodrift.reports.validation import (
    SAME_ROOM_NOTE,
    cell_json,
    cell_table,
    coverage_lines,
    provenance_text,
    table1,
    truth_table,
    write_cell_report,
    write_report,
)
from nanodrift.settings import BUILTIN_SOURCE

#: the paper's test 1 is the stage without compensation (Table I: "without" only); validate runs it so
UNCOMPENSATED_TEST = "test1"


def configure(parser: argparse.ArgumentParser) -> None:
    _cell.add_procedure_flags(parser, "test2", several=True)
    parser.add_argument("--model", required=True, metavar="M.json", help="the model to validate")
    parser.add_argument("--cycles", type=int, default=30, metavar="N", help="validation sweeps (ISO 9283: 30)")
    parser.add_argument("--json", action="store_true",
                        help='print the results as JSON instead of Table I: {"model", "backend", "cycles", '
                             '"tests": [one object per test]}, for one test or several')
    parser.add_argument("--report", metavar="DIR",
                        help="also write Table I, JSON, raw steps and figures (PNG + SVG) into DIR")
    parser.add_argument("--no-compensation", action="store_true",
                        help="command the targets as they are (--scenario test1 always runs so: the paper's test 1)")
    parser.add_argument("--adapt", action="store_true",
                        help="correct the commands with the daemon's bias tracker ([adapt] mode = \"bias\"), fed "
                             "by each step's residual")
    parser.add_argument("--adapt-tau-s", type=float, default=600.0, metavar="S",
                        help="the tracker's time constant (default 600 s, as [adapt] tau_s)")
    parser.add_argument("--adapt-max-um", type=float, default=1.0, metavar="UM",
                        help="clamp on the correction (default 1 µm, as [adapt] max_um)")


def main(args: argparse.Namespace) -> int:
    if args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    with user_errors(ModelFileError, OSError):
        model = load_any_model(args.model)
    compensate = not args.no_compensation
    if args.adapt:
        if not compensate:
            raise UserError("--adapt corrects the model's commands: it cannot run with --no-compensation")
        if not (args.adapt_tau_s > 0 and args.adapt_max_um >= 0):
            raise UserError(f"--adapt-tau-s must be > 0 and --adapt-max-um >= 0, got {args.adapt_tau_s:g}, "
                            f"{args.adapt_max_um:g}")
    scenarios = _cell.scenario_list(args.scenario)
    for scenario in scenarios:  # every name checked before the first test runs
        try:
            get_scenario(scenario)
        except UnknownNameError as err:
            raise UserError(f"--scenario: {err}") from None
    if args.adapt and scenarios == [UNCOMPENSATED_TEST]:
        raise UserError(f"--adapt corrects the model's commands: --scenario {UNCOMPENSATED_TEST} runs without the "
                        "model (the paper's test 1)")
    given = load_config(args.config)  # as given, before --scenario/--seed override its [simulation]
    if len(scenarios) > 1 and not given.virtual_cell:
        raise UserError(f"several --scenario ({', '.join(scenarios)}) need the simulated cell; "
                        f"{given.source} drives hardware")
    asked: list[str | None] = list(scenarios) or [None]  # None: the config's (or the default) room
    if isinstance(model, CellModel):  # each test through the config's drivers, or on the simulated stacked stage
        test = _driven_test if args.config is not None or args.adapt else _simulated_test
        tests = [test(args, model, scenario) for scenario in asked]
        print(json.dumps({"model": model.id, "tests": [doc for _, doc in tests]}, indent=2) if args.json
              else "\n\n".join(text for text, _ in tests))
        return 0
    runs = [_run_one(args, model, scenario) for scenario in asked]
    results = [result for result, _, _ in runs]
    for result in results:  # a miscalibrated q_sigma is said on stderr, whatever is printed
        warning = coverage_lines(result)[1]
        if warning:
            print(f"warning: {warning}" + (f" ({result.name})" if len(runs) > 1 else ""), file=sys.stderr)
    truth = truth_table(results)
    text = table1(results) + (f"\n\n{truth}" if truth else "")
    doc: dict[str, Any] = {"model": model.id, "backend": runs[0][2], "cycles": args.cycles,
                           "tests": [_test_doc(args, result, tracker) for result, tracker, _ in runs]}
    if args.report:
        files = write_report(results, args.report, text, doc, training=model.training,
                             provenance=provenance_text(model.id, model.provenance.get("data_file"),
                                                        _cell_text(given, args, results)))
        print(f"report: {', '.join(str(f) for f in files)}", file=sys.stderr)
    if args.json:
        print(json.dumps(doc, indent=2, default=_json_default))
        return 0
    print(text)
    for result, tracker, _ in runs:
        _print_details(result, tracker, several=len(runs) > 1)
    return 0


def _run_one(args: argparse.Namespace, model: Model, scenario: str | None
             ) -> tuple[TestResult, BiasTracker | None, str]:
    """One test on a fresh cell (``scenario`` None: the config's room, or test2 with no config): its result, its
    tracker (``--adapt``) and the cell's drivers, described."""
    config, drivers = _open(args, scenario)
    name = scenario or ("test2" if args.config is None else "validation")
    compensate = not args.no_compensation and name != UNCOMPENSATED_TEST
    tracker = BiasTracker(args.adapt_tau_s, args.adapt_max_um) if args.adapt and compensate else None
    follow, ready = _cell.guards(config, drivers, args)
    with user_errors(ValueError):
        result = _cell.run_procedure(run_validation(
            drivers, model if compensate else None, limits=config.axis_actuators(), name=name, cycles=args.cycles,
            timing=config.procedure.timing, follow=follow, ready=ready, adapt=tracker))
    return result, tracker, drivers.description


def _test_doc(args: argparse.Namespace, result: TestResult, tracker: BiasTracker | None) -> dict[str, Any]:
    doc = result.to_dict()
    coverage_text, coverage_warning = coverage_lines(result)
    if coverage_text:
        doc["coverage_warning"] = coverage_warning
    if tracker is not None:
        doc["adapt"] = _adapt_doc(args)
    return doc


def _adapt_doc(args: argparse.Namespace) -> dict[str, Any]:
    """The tracker ``--adapt`` runs, as the JSON names it ([adapt]'s keys)."""
    return {"mode": "bias", "tau_s": args.adapt_tau_s, "max_um": args.adapt_max_um}


def _open(args: argparse.Namespace, scenario: str | None, builtin: Config | None = None) -> tuple[Config, DriverSet]:
    """A fresh cell for one test in ``scenario`` (None: the config's room, or test2 with no config); ``builtin``:
    the built-in cell to drive instead of ``--config``'s."""
    return _cell.open_cell(argparse.Namespace(**{**vars(args), "scenario": scenario}), "test2", config=builtin)


def _cell_text(given: Config, args: argparse.Namespace, results: list[TestResult]) -> str:
    """Where the figures' data came from: the simulated rooms and the seed that reproduces them, or the
    config of the hardware."""
    section = given.section(SECTION)
    if not isinstance(section, SimulationConfig):
        return f"cell of {given.source}"
    seed = section.seed if args.seed is None else args.seed
    where = "" if args.config is None else f" of {given.source}"
    return f"simulated cell{where}: {', '.join(r.name for r in results)}, --seed {seed}"


def _print_details(result: TestResult, tracker: BiasTracker | None, *, several: bool) -> None:
    """What follows Table I for one test: the tracker, the uncertainty's coverage, the figures per point.

    Several tests: one block per test, each after a blank line and naming its test."""
    which = f" ({result.name})" if several else ""
    gap = "" if several else "\n"  # one test: as validate always printed it
    if several:
        print()
    if tracker is not None:
        print(f"{gap}adaptation{which}: {_tracker_text(tracker)}")
    for line in coverage_lines(result)[0]:
        print(line.replace("uncertainty:", f"uncertainty{which}:", 1))
    kind = "with compensation" if result.compensated else "without compensation"
    print(f"{gap}per point ({f'{result.name}, ' if several else ''}{kind}):")
    for p in (result.points if result.compensated else result.points_without):
        print(f"  x' = {p.target_um[result.axis]:5.0f} µm: accuracy {p.accuracy_nm:7.1f} nm, repeatability "
              f"{p.repeatability_nm:7.1f} nm ({p.visits} visits)")


def _tracker_text(tracker: BiasTracker) -> str:
    """What ``--adapt`` says of a tracker after the test (the one axis', or each axis' of a cell)."""
    return (f"bias tracker (tau_s {tracker.tau_s:g} s, max {tracker.max_um:g} um), {tracker.updates} settled "
            f"residuals, final correction {tracker.correction_um * 1e3:+.0f} nm")


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


# ----- a multi-axis model: Table I per axis, AP/RP in 2-D/3-D ------------------------------------------


#: each axis' attained positions: without the model, then with it (None: not run)
Attained = tuple[dict[str, np.ndarray], dict[str, np.ndarray] | None]


def _cell_test(args: argparse.Namespace, model: CellModel, name: str, targets_um: dict[str, np.ndarray],
               measured_um: Attained, truth_um: Attained | None, *, backend: str, extrapolating: int,
               without_note: str | None = None, notes: Sequence[str] = (), adapt: dict[str, Any] | None = None,
               **extra: Any) -> tuple[str, dict[str, Any]]:
    """One test of a cell scored against its position sensors and (``truth_um``) the true position: its Table I
    text and JSON document, and with ``--report`` its files (one directory per test when several are asked for)."""
    measured = summarize_runs(name, targets_um, *measured_um)
    truth = measured if truth_um is None else summarize_runs(name, targets_um, *truth_um)
    text = cell_table(name, truth, measured)
    if without_note is not None:
        text = text.replace(SAME_ROOM_NOTE, without_note)
    if extrapolating:
        text += f"\n[{extrapolating} steps extrapolating: outside the model's training ranges]"
    text += "".join(f"\n{note}" for note in notes)
    doc = cell_json(name, truth, measured, model=model.id, backend=backend, cycles=args.cycles, **extra,
                    extrapolating_steps=extrapolating)
    if adapt is not None:
        doc["adapt"] = adapt
    if args.report:
        several = len(_cell.scenario_list(args.scenario)) > 1
        directory = Path(args.report) / name if several else Path(args.report)
        provenance = provenance_text(model.id, model.provenance.get("data_file"), backend)
        attained = measured_um if truth_um is None else truth_um
        files = write_cell_report(directory, text, doc, truth, targets_um, *attained, provenance=provenance)
        print(f"report: {', '.join(str(f) for f in files)}", file=sys.stderr)
    return text, doc


def _simulated_test(args: argparse.Namespace, model: CellModel, scenario: str | None) -> tuple[str, dict[str, Any]]:
    """One test on a fresh simulated cell (the vectorised stack), its uncompensated run in the same room."""
    missing = [c for c in model.channels if c not in ("T1", "T2", "T3", "T4")]
    if missing:
        raise UserError(f"{args.model} needs channel(s) {', '.join(missing)} that the simulated cell does not "
                        "measure")
    try:
        cross = cross_params(args.effects or None)
    except (UnknownNameError, KeyError, ValueError) as err:
        raise UserError(f"simulated {''.join(model.axes)} cell: {err}") from None
    scenario = scenario or "test2"
    seed = _cell.scenario_seed(args.seed or 0, scenario)
    physics = CellPhysics.create(scenario, seed=seed, axes=model.axes, cross=cross)
    run = run_cell_validation(physics, None if args.no_compensation else cell_command(model), cycles=args.cycles,
                              name=scenario, out_of_range=lambda p, temps: bool(model.out_of_range(p, temps)))

    def attained(against: str) -> Attained:
        return run.attained(False, against), run.attained(True, against) if run.compensated is not None else None

    return _cell_test(args, model, scenario, run.targets_um, attained("interferometer"), attained("truth"),
                      backend=f"simulated {''.join(model.axes)} cell, scenario {scenario}, seed {seed}",
                      extrapolating=run.extrapolating_steps)


def _driven_run(args: argparse.Namespace, model: CellModel, scenario: str | None, builtin: Config | None, *,
                compensate: bool, adapt: dict[str, BiasTracker] | None = None
                ) -> tuple[Config, DriverSet, list[StepResult], int]:
    """One run of the plan on a fresh cell (a simulated one restarts its room: both runs see the same one)."""
    config, drivers = _open(args, scenario, builtin)
    if sorted(config.axis_names) != sorted(model.axes):
        raise UserError(f"{args.model} serves axes {', '.join(model.axes)}, {config.source} has axes "
                        f"{', '.join(config.axis_names)}")
    limits = config.axis_actuators()
    plan = cell_validation_plan(config.axis_names, args.cycles, {a: lim.workspace_um for a, lim in limits.items()})
    follow, ready = _cell.guards(config, drivers, args)
    with user_errors(ValueError):
        check_channels(model, drivers)  # uncompensated too: refused before the first run moves anything
        run = _cell.run_procedure(run_validation_steps(
            drivers, plan, model if compensate else None, limits=limits, name=scenario or "validation",
            timing=config.procedure.timing, follow=follow, ready=ready, adapt=adapt))
    return config, drivers, run.steps, run.extrapolating


def _driven_test(args: argparse.Namespace, model: CellModel, scenario: str | None) -> tuple[str, dict[str, Any]]:
    """One test through the config's drivers (or, ``--adapt`` without ``--config``, the built-in simulated cell's
    of the model's axes): the plan run uncompensated, then through the model."""
    builtin = None
    if args.config is None:
        try:
            builtin = parse_config({"simulation": {"axes": "".join(model.axes), "scenario": "test2"}},
                                   source=BUILTIN_SOURCE)
        except ConfigError as err:
            raise UserError(f"--adapt: no built-in simulated cell of axes {''.join(model.axes)}: give --config "
                            f"({err})") from None
    config, drivers, without, _ = _driven_run(args, model, scenario, builtin, compensate=False)
    runs, extrapolating = [without], 0
    trackers = {a: BiasTracker(args.adapt_tau_s, args.adapt_max_um) for a in model.axes} if args.adapt else None
    if not args.no_compensation:
        _, _, compensated, extrapolating = _driven_run(args, model, scenario, builtin, compensate=True,
                                                       adapt=trackers)
        runs.append(compensated)
    section = config.section(SECTION)
    name = scenario or (section.scenario if isinstance(section, SimulationConfig) else "validation")
    targets = {a: np.array([r.step.target(a) for r in without]) for a in model.axes}
    knows_truth = all(math.isfinite(v) for run in runs for r in run for v in r.true_um.values())

    def attained(truth: bool) -> Attained:
        per_run = [{a: np.array([(r.true_um if truth else r.positions_um)[a] for r in run]) for a in model.axes}
                   for run in runs]
        return per_run[0], per_run[1] if len(per_run) > 1 else None

    without_note = (f"without comp.: the same plan run uncompensated (command = target) first, then through the "
                    f"model{' and a bias tracker per axis' if trackers else ''}, on {drivers.description} "
                    f"({config.source})" + ("" if knows_truth else "; no true position on hardware: the TRUE columns "
                                             "repeat the position sensors'") + ".")
    invalid = sum(not r.valid for run in runs for r in run)
    notes = [f"[{invalid} steps kept with a dirty window (valid = 0) are scored as measured]"] if invalid else []
    adapt = None
    if trackers is not None:
        notes += [f"adaptation, axis {a}: {_tracker_text(t)}" for a, t in trackers.items()]
        adapt = {**_adapt_doc(args), "axes": {a: {"updates": t.updates, "final_correction_um": t.correction_um}
                                              for a, t in trackers.items()}}
    return _cell_test(args, model, name, targets, attained(False), attained(True) if knows_truth else None,
                      extrapolating=extrapolating, backend=f"{drivers.description} ({config.source})",
                      without_note=without_note, notes=notes, adapt=adapt, truth_known=knows_truth)
