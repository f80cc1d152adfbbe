"""``nanodrift validate``: ISO 9283 accuracy and repeatability with and without the model (Table I).

``--adapt`` runs the daemon's bias tracker (``[adapt] mode = "bias"``) over the test, so a lab can see
offline what adaptation would have given.

On the simulated cell ``--scenario`` may name several tests (``--scenario test2,test3,test5``, or
repeated): each runs in turn and one report holds them all (Table I a row per test, the figures
comparing them). There each step is also scored against the true position the cell knows
(the simulated cell's sensor group), beside the interferometer's view.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import dataclass
from typing import Any

import numpy as np

from nanodrift.calibration.iso9283 import TestResult
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.commands import _cell_validate
from nanodrift.commands._catalogues import scenario_epilog
from nanodrift.commands._cell import (
    add_config_flag,
    add_output_check_flag,
    add_simulation_flags,
    guards,
    open_cell,
    run_procedure,
    scenario_list,
)
from nanodrift.config import Config, load_config
from nanodrift.drivers.simulated.config import SECTION, SimulationConfig
from nanodrift.drivers.simulated.effects import UnknownNameError
from nanodrift.drivers.simulated.scenarios import get_scenario
from nanodrift.drivers_set import DriverSet
from nanodrift.errors import UserError
from nanodrift.model.model import Model, ModelFileError, load_model
from nanodrift.procedure.validation import run_validation
from nanodrift.reports.validation import coverage_lines, provenance_text, table1, truth_table, write_report


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = scenario_epilog()
    add_config_flag(parser)
    parser.add_argument("--model", required=True, metavar="M.json", help="the model to validate")
    parser.add_argument("--cycles", type=int, default=30, metavar="N", help="validation sweeps (ISO 9283: 30)")
    parser.add_argument("--json", action="store_true", help="print the results as JSON instead of Table I")
    parser.add_argument("--report", metavar="DIR",
                        help="also write Table I, JSON, raw steps and figures (PNG + SVG) into DIR")
    parser.add_argument("--no-compensation", action="store_true", help="command the targets as they are (test 1)")
    parser.add_argument("--adapt", action="store_true",
                        help="correct the commands with the daemon's bias tracker ([adapt] mode = \"bias\"), fed "
                             "by each step's residual")
    parser.add_argument("--adapt-tau-s", type=float, default=600.0, metavar="S",
                        help="the tracker's time constant (default 600 s, as [adapt] tau_s)")
    parser.add_argument("--adapt-max-um", type=float, default=1.0, metavar="UM",
                        help="clamp on the correction (default 1 µm, as [adapt] max_um)")
    add_simulation_flags(parser, "test2", several=True)
    add_output_check_flag(parser)


def main(args: argparse.Namespace) -> int:
    if args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    if _cell_validate.is_cell_model_file(args.model):  # a multi-axis model: the simulated XY/XYZ cell
        return _cell_validate.main(args)
    try:
        model = load_model(args.model)
    except (ModelFileError, OSError) as err:
        raise UserError(str(err)) from None
    compensate = not args.no_compensation
    if args.adapt:
        if not compensate:
            raise UserError("--adapt corrects the model's commands: it cannot run with --no-compensation")
        if not (args.adapt_tau_s > 0 and args.adapt_max_um >= 0):
            raise UserError(f"--adapt-tau-s must be > 0 and --adapt-max-um >= 0, got {args.adapt_tau_s:g}, "
                            f"{args.adapt_max_um:g}")
    scenarios = scenario_list(args.scenario)
    for scenario in scenarios:  # every name checked before the first test runs
        try:
            get_scenario(scenario)
        except UnknownNameError as err:
            raise UserError(f"--scenario: {err}") from None
    given = load_config(args.config)  # as given, before --scenario/--seed override its [simulation]
    if len(scenarios) > 1 and not given.virtual_cell:
        raise UserError(f"several --scenario ({', '.join(scenarios)}) need the simulated cell; "
                        f"{given.source} drives hardware")
    asked: list[str | None] = list(scenarios) or [None]  # None: the config's (or the default) room
    runs = [_run_one(args, model, scenario) for scenario in asked]
    results = [run.result for run in runs]
    for run in runs:  # a miscalibrated q_sigma is said on stderr, whatever is printed
        warning = coverage_lines(run.result)[1]
        if warning:
            print(f"warning: {warning}" + (f" ({run.result.name})" if len(runs) > 1 else ""), file=sys.stderr)
    config = runs[0].config
    text = table1(results)
    truth = truth_table(results)
    doc: dict[str, Any] = {"model": model.id, "backend": runs[0].drivers.description, "cycles": args.cycles}
    if len(runs) == 1:  # one test: the document validate always printed
        doc.update(runs[0].to_dict())
    else:
        doc["tests"] = [run.to_dict() for run in runs]
    if args.report:
        report_text = text + (f"\n\n{truth}" if truth else "")
        files = write_report(results, args.report, report_text, doc, training=model.training,
                             provenance=provenance_text(model.id, model.provenance.get("data_file"),
                                                        _cell_text(config, given, args, results)))
        print(f"report: {', '.join(str(f) for f in files)}", file=sys.stderr)
    if args.json:
        print(json.dumps(doc, indent=2, default=_json_default))
        return 0
    print(text)
    if truth:
        print(f"\n{truth}")
    for run in runs:
        _print_details(run.result, run.tracker, compensate, several=len(runs) > 1)
    return 0


@dataclass
class ValidationRun:
    """One test as it ran: its result, its tracker (``--adapt``), the config and drivers of its cell."""

    result: TestResult
    tracker: BiasTracker | None
    config: Config
    drivers: DriverSet

    def to_dict(self) -> dict[str, Any]:
        doc = self.result.to_dict()
        coverage_text, coverage_warning = coverage_lines(self.result)
        if coverage_text:
            doc["coverage_warning"] = coverage_warning
        if self.tracker is not None:
            doc["adapt"] = {"mode": "bias", "tau_s": self.tracker.tau_s, "max_um": self.tracker.max_um}
        return doc


def _run_one(args: argparse.Namespace, model: Model, scenario: str | None) -> ValidationRun:
    """One test on a fresh cell (``scenario`` None: the config's room, or test2 with no config)."""
    config, drivers = open_cell(argparse.Namespace(**{**vars(args), "scenario": scenario}), "test2")
    name = scenario or ("test2" if args.config is None else "validation")
    compensate = not args.no_compensation
    tracker = BiasTracker(args.adapt_tau_s, args.adapt_max_um) if args.adapt else None
    follow, ready = guards(config, drivers, args)
    try:
        result = run_procedure(run_validation(drivers, model if compensate else None, limits=config.actuator,
                                            name=name, cycles=args.cycles, timing=config.procedure.timing,
                                            follow=follow, ready=ready, adapt=tracker))
    except ValueError as err:
        raise UserError(str(err)) from None
    return ValidationRun(result, tracker, config, drivers)


def _cell_text(config: Config, given: Config, args: argparse.Namespace, results: list[TestResult]) -> str:
    """Where the figures' data came from: the simulated rooms and the seed that reproduces them, or the
    config of the hardware."""
    given_section = given.section(SECTION)
    if isinstance(config.section(SECTION), SimulationConfig):
        seed = args.seed if args.seed is not None else (
            given_section.seed if isinstance(given_section, SimulationConfig) else 0)
        rooms = ", ".join(r.name for r in results)
        where = "" if args.config is None else f" of {config.source}"
        return f"simulated cell{where}: {rooms}, --seed {seed}"
    return f"cell of {config.source}"


def _print_details(result: TestResult, tracker: BiasTracker | None, compensate: bool, *, several: bool) -> None:
    """What follows Table I for one test: the tracker, the uncertainty's coverage, the figures per point.

    Several tests: one block per test, each after a blank line and naming its test."""
    which = f" ({result.name})" if several else ""
    gap = "" if several else "\n"  # one test: as validate always printed it
    if several:
        print()
    if tracker is not None:
        print(f"{gap}adaptation{which}: bias tracker (tau_s {tracker.tau_s:g} s, "
              f"max {tracker.max_um:g} um), {tracker.updates} settled residuals, final correction "
              f"{tracker.correction_um * 1e3:+.0f} nm")
    for line in coverage_lines(result)[0]:
        print(line.replace("uncertainty:", f"uncertainty{which}:", 1))
    kind = "with compensation" if compensate else "without compensation"
    print(f"{gap}per point ({f'{result.name}, ' if several else ''}{kind}):")
    for p in result.points:
        acc, rep = (p.accuracy_nm, p.repeatability_nm) if compensate else (p.accuracy_without_nm,
                                                                             p.repeatability_without_nm)
        print(f"  x' = {p.target_um:5.0f} µm: accuracy {acc:7.1f} nm, repeatability {rep:7.1f} nm "
              f"({p.visits} visits)")


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
