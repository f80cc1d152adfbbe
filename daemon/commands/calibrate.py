"""``nanodrift calibrate``: the paper's procedure (Fig. 6, 7) on the configured cell, then the fit.

With no ``--config`` the cell is simulated on a virtual clock (a 4-hour calibration in seconds).
``[procedure]`` sets the trajectory (``trajectory``: forward sweeps as in the paper, or up-and-down)
and the timing, on the simulated cell and on hardware alike; ``--scenario`` is only the simulated
room's history: the paper's training room (``train``) unless given, whatever room the config's daemon
serves in. On hardware the configured actuator moves the stage, and the run is refused while a
daemon serves the cell; it stops within its first steps when the position sensor does not see the
stage move.

The result goes to stdout: the model, its training ranges, and which config serves it (``--serve``
writes the config's ``[model] path``); progress and warnings (a temperature range too narrow to
trust) go to stderr.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from nanodrift.calibration.dataset import DataError
from nanodrift.calibration.plans import (
    MIN_CELL_CYCLES,
    PlannedStep,
    bidirectional_plan,
    calibration_plan,
    cell_calibration_plan,
)
from nanodrift.commands import _cell
from nanodrift.config import Config, missing_model_channels
from nanodrift.errors import UserError, user_errors
from nanodrift.model.cell_model import CellModel, one_axis
from nanodrift.model.describe import describe_cell_model
from nanodrift.model.equation import equation, training_lines
from nanodrift.model.identify import FitError
from nanodrift.procedure.follow import StageNotFollowingError
from nanodrift.procedure.preflight import PreflightError
from nanodrift.procedure.recording import (
    NARROW_RANGE_C,
    calibration_columns,
    completed_steps,
    fit_recorded,
    narrow_channels,
    record_calibration,
    resume_hint,
)
from nanodrift.procedure.serving import ServeError, check_writable, serve_model, toml_string


def configure(parser: argparse.ArgumentParser) -> None:
    _cell.add_procedure_flags(parser, "train", over_config=True)
    parser.add_argument("--out", required=True, metavar="M.json", help="the model file to write")
    parser.add_argument("--data", metavar="D.csv", help="where the recorded steps go (default: beside --out)")
    parser.add_argument("--cycles", type=int, metavar="N",
                        help="calibration sweeps (default: the config's [procedure] cycles, 24 as in the paper)")
    parser.add_argument("--resume", action="store_true", help="continue an interrupted run from --data")
    parser.add_argument("--serve", action="store_true",
                        help="write the new model's path into the --config file's [model] path (atomically, the "
                             "rest of the file kept), so the daemon serves it after a reload")


def main(args: argparse.Namespace) -> int:
    if args.cycles is not None and args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    if args.serve and not args.config:
        raise UserError("--serve needs --config F: the config whose [model] path is to name the new model "
                        "(the built-in simulated cell has no file)")
    if args.serve:
        with user_errors(ServeError):
            check_writable(Path(args.config))  # refused now, not after hours of calibration
    data = Path(args.data) if args.data else Path(args.out).with_name(Path(args.out).stem + "_data.csv")
    if args.resume and not data.exists():
        raise UserError(f"--resume: {data} does not exist (nothing to continue)")
    config, drivers = _cell.open_cell(args, "train", over_config=True)
    axes = config.axis_names
    cycles = args.cycles if args.cycles is not None else config.procedure.cycles
    if config.multi_axis and cycles < MIN_CELL_CYCLES:
        raise UserError(f"a calibration of {len(axes)} axes needs at least {MIN_CELL_CYCLES} cycles, got {cycles} "
                        "(--cycles, or [procedure] cycles in the config): its first cycle moves every axis to the same "
                        "level at each step, so one cycle cannot tell the axes apart")
    plan = _plan(config, cycles)
    columns = calibration_columns(drivers, axes)
    with user_errors(DataError):
        done, last_t = completed_steps(data, columns) if args.resume else (0, 0.0)
    if args.resume and config.virtual_cell and done:  # the simulated room continues where the file ends
        config, drivers = _cell.open_cell(args, "train", start_s=last_t + 1.0, over_config=True)
    follow, ready = _cell.guards(config, drivers, args)
    which = f" of axes {', '.join(axes)}" if len(axes) > 1 else ""
    print(f"calibration{which} on {drivers.description}: {len(plan)} steps ({cycles} cycles), data -> {data}"
          + (f", resuming after {done} recorded steps" if done else ""), file=sys.stderr)
    try:
        _cell.run_procedure(record_calibration(drivers, data, limits=config.axis_actuators(), plan=plan,
                                               resume=args.resume, timing=config.procedure.timing, follow=follow,
                                               ready=ready))
    except PreflightError:
        raise  # nothing was commanded
    except (KeyboardInterrupt, Exception) as err:
        recorded = completed_steps(data, columns)[0] if data.exists() else 0
        if isinstance(err, StageNotFollowingError):
            raise UserError(f"{err}. The {recorded} steps recorded in {data} are of a stage that did not move: "
                            "delete the file (or give another --data) before calibrating again") from None
        print(resume_hint(args.out, data, recorded, len(plan)), file=sys.stderr)
        if isinstance(err, FileExistsError | DataError):
            raise UserError(str(err)) from None
        raise
    try:
        cell = fit_recorded(data, args.out, plan=plan)
    except (FitError, DataError, ValueError) as err:
        raise UserError(f"the recorded steps in {data} are kept, but the fit failed: {err}") from None
    if one_axis(axes):
        model = cell.models["x"]
        print(f"model -> {args.out} ({model.id}): {equation(model)}")
        residual = model.fit.get("residual_rms_nm", float("nan"))
        print(f"fit residual {residual:.1f} nm RMS over {model.fit.get('rows')} steps")
        print("\n".join(training_lines(model)))
    else:
        print(describe_cell_model(cell, args.out))
    for warning in narrow_warnings(data):
        print(f"nanodrift calibrate: warning: {warning}", file=sys.stderr)
    if args.serve:
        try:
            serve_model(Path(args.config), Path(args.out))
        except ServeError as err:
            raise UserError(f"the model {args.out} is written, but {err}") from None
    print(serving_lines(args, config, cell))
    for warning in sensor_warnings(config, cell) if args.config else []:
        print(f"nanodrift calibrate: warning: {warning}", file=sys.stderr)
    return 0


def _plan(config: Config, cycles: int) -> list[PlannedStep]:
    """The paper's sweeps (``[procedure]`` points and trajectory) on one axis; the space-filling plan on several."""
    settings = config.procedure
    if len(config.axis_names) == 1:
        sweeps = bidirectional_plan if settings.trajectory == "bidirectional" else calibration_plan
        return list(sweeps(cycles, settings.calibration_points))
    if settings.points is not None or settings.trajectory != "forward":
        raise UserError(f"{config.source}: [procedure] points/trajectory shape a one-axis sweep; a multi-axis cell "
                        "runs the space-filling plan on the paper's 17 levels (remove them)")
    return list(cell_calibration_plan(config.axis_names, cycles))


def narrow_warnings(data: Path) -> list[str]:
    """A line per channel whose calibration range is below :data:`NARROW_RANGE_C`, then what it means."""
    narrow = narrow_channels(data)
    if not narrow:
        return []
    return [f"{name} varied only {hi - lo:.3f} °C during the calibration ({lo:.3f}..{hi:.3f} °C)"
            for name, (lo, hi) in narrow.items()] + [
        f"a range below {NARROW_RANGE_C:g} °C is too narrow to trust: the channel's coefficient is mostly noise, and "
        "the model extrapolates as soon as the room moves further; calibrate while the room swings wider (on the "
        "simulated cell: --scenario train, the default)"]


def serving_lines(args: argparse.Namespace, config: Config, model: CellModel) -> str:
    """Which config serves the new model, and how to make it (or a reload) do so."""
    out = Path(args.out).resolve()
    path_line = f"[model] path = {toml_string(str(out))}"
    if not args.config:
        return (f"served by: no config yet (nanodrift run with no --config serves the shipped model); to serve "
                f"{model.id}: put {path_line} in a config (e.g. a copy of config/sim.toml), then "
                "nanodrift run --config F; or calibrate with --config F --serve")
    reload = ("the daemon takes it at its next start or reload (systemctl start or reload nanodrift; by hand: "
              f"kill -HUP its pid); check first: nanodrift check-config {args.config} --strict")
    if args.serve or Path(config.model.path).resolve() == out:
        verb = "now serves" if args.serve else "serves"
        return f"served by: {args.config} {verb} {model.id} ({path_line}); {reload}"
    return (f"served by: {args.config} still serves {config.model.path}, not {model.id}; to serve it: "
            f"calibrate with --serve, or set {path_line} in {args.config}; {reload}")


def sensor_warnings(config: Config, model: CellModel) -> list[str]:
    """What ``check-config --strict`` will refuse about the new model and the config's sensors."""
    warnings = []
    missing = missing_model_channels(config, model.channels)
    if missing:
        warnings.append(f"the model needs {', '.join(missing)}, which no temperature sensor of {config.source} "
                        "provides: targets will be refused until they are configured")
    unused = [s.name for s in config.sensors if s.role == "temperature" and s.name not in model.channels]
    if unused:
        warnings.append(f"sensor(s) {', '.join(unused)} of {config.source} are not used by {model.id} "
                        "(check-config --strict refuses that: remove them, or keep them as monitored only)")
    return warnings
