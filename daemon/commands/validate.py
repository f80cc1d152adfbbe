"""``nanodrift validate``: ISO 9283 accuracy and repeatability with and without the model (Table I).

``--adapt`` runs the daemon's bias tracker (``[adapt] mode = "bias"``) over the test, so a lab can see
offline what adaptation would have given.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
from typing import Any

import numpy as np

from daemon.calibration.residuals import BiasTracker
from daemon.commands._catalogues import scenario_epilog
from daemon.commands._cell import add_config_flag, add_output_check_flag, add_simulation_flags, guards, open_cell
from daemon.errors import UserError
from daemon.model.model import ModelFileError, load_model
from daemon.procedure.validation import run_validation
from daemon.reports.validation import coverage_lines, table1, write_report


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
    add_simulation_flags(parser, "test2")
    add_output_check_flag(parser)


def main(args: argparse.Namespace) -> int:
    if args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    try:
        model = load_model(args.model)
    except (ModelFileError, OSError) as err:
        raise UserError(str(err)) from None
    config, drivers = open_cell(args, "test2")
    name = args.scenario or ("test2" if args.config is None else "validation")
    compensate = not args.no_compensation
    tracker = None
    if args.adapt:
        if not compensate:
            raise UserError("--adapt corrects the model's commands: it cannot run with --no-compensation")
        if not (args.adapt_tau_s > 0 and args.adapt_max_um >= 0):
            raise UserError(f"--adapt-tau-s must be > 0 and --adapt-max-um >= 0, got {args.adapt_tau_s:g}, "
                            f"{args.adapt_max_um:g}")
        tracker = BiasTracker(args.adapt_tau_s, args.adapt_max_um)
    follow, ready = guards(config, drivers, args)
    try:
        result = asyncio.run(run_validation(drivers, model if compensate else None, limits=config.actuator,
                                            name=name, cycles=args.cycles, timing=config.procedure.timing,
                                            follow=follow, ready=ready, adapt=tracker))
    except ValueError as err:
        raise UserError(str(err)) from None
    text = table1([result])
    doc: dict[str, Any] = {"model": model.id, "backend": drivers.description, "cycles": args.cycles,
                           **result.to_dict()}
    coverage_text, coverage_warning = coverage_lines(result)
    if coverage_text:
        doc["coverage_warning"] = coverage_warning
    if coverage_warning:
        print(f"warning: {coverage_warning}", file=sys.stderr)
    if tracker is not None:
        doc["adapt"] = {"mode": "bias", "tau_s": tracker.tau_s, "max_um": tracker.max_um}
    if args.report:
        files = write_report([result], args.report, text, doc)
        print(f"report: {', '.join(str(f) for f in files)}", file=sys.stderr)
    if args.json:
        print(json.dumps(doc, indent=2, default=_json_default))
    else:
        print(text)
        if tracker is not None:
            print(f"\nadaptation: bias tracker (tau_s {tracker.tau_s:g} s, max {tracker.max_um:g} um), "
                  f"{tracker.updates} settled residuals, final correction {tracker.correction_um * 1e3:+.0f} nm")
        for line in coverage_text:
            print(line)
        print(f"\nper point ({'with compensation' if compensate else 'without compensation'}):")
        for p in result.points:
            acc, rep = (p.accuracy_nm, p.repeatability_nm) if compensate else (p.accuracy_without_nm,
                                                                                 p.repeatability_without_nm)
            print(f"  x' = {p.target_um:5.0f} µm: accuracy {acc:7.1f} nm, repeatability {rep:7.1f} nm "
                  f"({p.visits} visits)")
    return 0


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")
