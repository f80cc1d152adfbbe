"""``nanodrift calibrate``: the paper's procedure (Fig. 6, 7) on the configured cell, then the fit.

With no ``--config`` the cell is simulated on a virtual clock (a 4-hour calibration in seconds).
``[procedure]`` sets the trajectory (``trajectory``: forward sweeps as in the paper, or up-and-down)
and the timing, on the simulated cell and on hardware alike; ``--scenario`` is only the simulated
room's history. On hardware the configured actuator moves the stage, and the run is refused while a
daemon serves the cell; it stops within its first steps when the position sensor does not see the
stage move.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
from pathlib import Path

from daemon.calibration.dataset import DataError
from daemon.calibration.plans import bidirectional_plan, calibration_plan
from daemon.commands._catalogues import scenario_epilog
from daemon.commands._cell import add_config_flag, add_output_check_flag, add_simulation_flags, guards, open_cell
from daemon.errors import UserError
from daemon.model.equation import equation, training_lines
from daemon.model.identify import FitError
from daemon.procedure.follow import StageNotFollowingError
from daemon.procedure.preflight import PreflightError
from daemon.procedure.recording import (
    calibration_columns,
    completed_steps,
    fit_recorded,
    record_calibration,
    resume_hint,
)


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = scenario_epilog()
    add_config_flag(parser)
    parser.add_argument("--out", required=True, metavar="M.json", help="the model file to write")
    parser.add_argument("--data", metavar="D.csv", help="where the recorded steps go (default: beside --out)")
    parser.add_argument("--cycles", type=int, metavar="N",
                        help="calibration sweeps (default: the config's [procedure] cycles, 24 as in the paper)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run from --data")
    add_simulation_flags(parser, "train")
    add_output_check_flag(parser)


def _data_path(args: argparse.Namespace) -> Path:
    if args.data:
        return Path(args.data)
    out = Path(args.out)
    return out.with_name(out.stem + "_data.csv")


def main(args: argparse.Namespace) -> int:
    if args.cycles is not None and args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    data = _data_path(args)
    if args.resume and not data.exists():
        raise UserError(f"--resume: {data} does not exist (nothing to continue)")
    config, drivers = open_cell(args, "train")
    columns = calibration_columns(drivers)
    cycles = args.cycles if args.cycles is not None else config.procedure.cycles
    points = config.procedure.calibration_points
    plan = (bidirectional_plan if config.procedure.trajectory == "bidirectional" else calibration_plan)(cycles, points)
    try:
        done, last_t = completed_steps(data, columns) if args.resume else (0, 0.0)
    except DataError as err:
        raise UserError(str(err)) from None
    if args.resume and config.virtual_cell and done:  # the simulated room continues where the file ends
        config, drivers = open_cell(args, "train", start_s=last_t + 1.0)
    follow, ready = guards(config, drivers, args)
    print(f"calibration on {drivers.description}: {len(plan)} steps ({cycles} cycles), data -> {data}"
          + (f", resuming after {done} recorded steps" if done else ""), file=sys.stderr)
    try:
        asyncio.run(record_calibration(drivers, data, limits=config.actuator, plan=plan, resume=args.resume,
                                       timing=config.procedure.timing, follow=follow, ready=ready))
    except PreflightError:
        raise  # nothing was commanded
    except StageNotFollowingError as err:
        recorded = completed_steps(data, columns)[0] if data.exists() else 0
        raise UserError(f"{err}. The {recorded} steps recorded in {data} are of a stage that did not move: "
                        "delete the file (or give another --data) before calibrating again") from None
    except (KeyboardInterrupt, Exception) as err:
        recorded = completed_steps(data, columns)[0] if data.exists() else 0
        print(resume_hint(args.out, data, recorded, len(plan)), file=sys.stderr)
        if isinstance(err, FileExistsError | DataError):
            raise UserError(str(err)) from None
        raise
    try:
        result = fit_recorded(data, args.out)
    except (FitError, DataError) as err:
        raise UserError(f"the recorded steps in {data} are kept, but the fit failed: {err}") from None
    model = result.model
    print(f"model -> {args.out} ({model.id}): {equation(model)}", file=sys.stderr)
    residual = model.fit.get("residual_rms_nm", float("nan"))
    print(f"fit residual {residual:.1f} nm RMS over {model.fit.get('rows')} steps", file=sys.stderr)
    print("\n".join(training_lines(model)), file=sys.stderr)
    return 0
