"""``nanodrift calibrate --config xy.toml``: the space-filling calibration of an XY/XYZ cell through its drivers.

The plan is :func:`nanodrift.calibration.plans.cell_calibration_plan` (the paper's 17 steps per cycle, every
axis moving); each step ramps every axis under its own limits, holds, and averages each axis' position
sensor and the thermocouples (:mod:`nanodrift.procedure.cell_steps`); each step is appended to the
multi-axis CSV as it is measured (``--resume`` continues it); then every axis' model is fitted into one
model file. The one-axis calibration (``nanodrift.commands.calibrate``) hands a multi-axis config here.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nanodrift.calibration.dataset import DataError
from nanodrift.calibration.plans import cell_calibration_plan
from nanodrift.commands._cell import guards, open_cell, run_procedure
from nanodrift.config import Config
from nanodrift.drivers_set import DriverSet
from nanodrift.errors import UserError
from nanodrift.model.describe import describe_cell_model
from nanodrift.model.identify import FitError
from nanodrift.procedure.cell_recording import cell_calibration_columns, fit_cell_recorded, record_cell_calibration
from nanodrift.procedure.cell_steps import CellDrive
from nanodrift.procedure.follow import FollowCheck, StageNotFollowingError
from nanodrift.procedure.preflight import PreflightError
from nanodrift.procedure.recording import completed_steps, resume_hint
from nanodrift.procedure.serving import ServeError, serve_model


def cell_drive(config: Config, drivers: DriverSet) -> CellDrive:
    return CellDrive(drivers, config.axis_actuators())


#: an axis' move shorter than this is not follow-checked: the other axes' moves push it by up to a couple of
#: micrometres on a stacked stage (crosstalk and non-orthogonality: ~0.4 % of their travel)
CELL_FOLLOW_MIN_MOVE_UM = 10.0


def follow_checks(config: Config, drive: CellDrive) -> dict[str, FollowCheck]:
    """One follow check per axis on its own position sensor (none when ``[procedure] follow_steps = 0``)."""
    settings = config.procedure
    if not settings.follow_steps:
        return {}
    return {axis: FollowCheck(channel, settings.follow_tolerance, settings.follow_steps,
                              min_move_um=CELL_FOLLOW_MIN_MOVE_UM)
            for axis, channel in drive.position_channels.items()}


def main(args: argparse.Namespace, config: Config, drivers: DriverSet, data: Path) -> int:
    if config.procedure.points is not None or config.procedure.trajectory != "forward":
        raise UserError(f"{config.source}: [procedure] points/trajectory shape a one-axis sweep; a multi-axis cell "
                        "runs the space-filling plan on the paper's 17 levels (remove them)")
    drive = cell_drive(config, drivers)
    columns = cell_calibration_columns(drive)
    cycles = args.cycles if args.cycles is not None else config.procedure.cycles
    plan = cell_calibration_plan(drive.axes, cycles)
    try:
        done, last_t = completed_steps(data, columns) if args.resume else (0, 0.0)
    except DataError as err:
        raise UserError(str(err)) from None
    if args.resume and config.virtual_cell and done:  # the simulated room continues where the file ends
        config, drivers = open_cell(args, "train", start_s=last_t + 1.0, over_config=True)
        drive = cell_drive(config, drivers)
    _, ready = guards(config, drivers, args)
    print(f"calibration of axes {', '.join(drive.axes)} on {drivers.description}: {len(plan)} steps ({cycles} "
          f"cycles), data -> {data}" + (f", resuming after {done} recorded steps" if done else ""), file=sys.stderr)
    try:
        run_procedure(record_cell_calibration(drive, data, plan, timing=config.procedure.timing, resume=args.resume,
                                            follow=follow_checks(config, drive), ready=ready))
    except PreflightError:
        raise
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
        cell = fit_cell_recorded(data, args.out)
    except (FitError, DataError, ValueError) as err:
        raise UserError(f"the recorded steps in {data} are kept, but the fit failed: {err}") from None
    print(describe_cell_model(cell, args.out))
    if args.serve:
        try:
            serve_model(Path(args.config), Path(args.out))
        except ServeError as err:
            raise UserError(f"the model {args.out} is written, but {err}") from None
        print(f"served by: {args.config} now serves {cell.id}; the daemon takes it at its next start or reload")
    return 0
