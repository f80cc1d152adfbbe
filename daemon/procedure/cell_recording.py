"""A multi-axis calibration: run (or continue) the space-filling plan, append each step to the CSV, fit.

:mod:`nanodrift.procedure.recording` for an XY/XYZ cell: each completed step is one row of the
multi-axis CSV contract (``t_s, x_um, y_um, q_x_um, q_y_um, cycle, valid, T1, ...``), appended and
fsynced, so an interrupted run resumes from the file; the fit is :func:`nanodrift.model.identify.fit_cell`
on the valid rows.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import IO

from nanodrift.calibration.dataset import CsvAppender, command_column, position_column, read_csv
from nanodrift.calibration.plans import PAPER_TIMING, PlannedCellStep, PlannedStep, StepTiming
from nanodrift.model.cell_model import CellModel, save_cell_model
from nanodrift.model.identify import fit_cell
from nanodrift.model.provenance import stamp_data
from nanodrift.procedure.cell_steps import CellDrive, CellStepResult, run_cell_steps
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.recording import completed_steps


def cell_calibration_columns(drive: CellDrive) -> list[str]:
    axes = drive.axes
    return ["t_s", *map(position_column, axes), *map(command_column, axes), "cycle", "valid",
            *drive.drivers.temperature_channels]


def cell_progress(plan: Sequence[PlannedCellStep], label: str, stream: IO[str] | None, done: int) -> Progress:
    """The one-axis progress line over a multi-axis plan (it reads each step's cycle)."""
    return Progress([PlannedStep(s.index, s.cycle, s.targets_um[0][1]) for s in plan], label, stream, done=done)


async def record_cell_calibration(
    drive: CellDrive,
    data_path: str | Path,
    plan: Sequence[PlannedCellStep],
    *,
    timing: StepTiming = PAPER_TIMING,
    resume: bool = False,
    progress_stream: IO[str] | None = None,
    follow: dict[str, FollowCheck] | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
) -> int:
    """Run (or continue) ``plan``, appending each step to ``data_path``; the steps recorded in this call.

    With ``resume`` the steps already in the file are skipped; without it an existing non-empty file is
    an error (hours of data are never overwritten)."""
    path = Path(data_path)
    columns = cell_calibration_columns(drive)
    done = 0
    if resume:
        done, _ = completed_steps(path, columns)
    elif path.exists() and path.stat().st_size > 0:
        raise FileExistsError(f"{path} already holds recorded steps; use --resume to continue it, or another --data")
    remaining = list(plan)[done:]
    appender: CsvAppender | None = None  # created with the first step: a run refused before it leaves no file

    def write(result: CellStepResult) -> None:
        nonlocal appender
        if appender is None:
            appender = CsvAppender(path, columns)
        row = {"t_s": result.t_s, **{position_column(a): v for a, v in result.positions_um.items()},
               **{command_column(a): v for a, v in result.q_um.items()}, "cycle": result.step.cycle,
               "valid": int(result.valid), **result.temperatures}
        appender.append(row)

    try:
        await run_cell_steps(drive, remaining, timing=timing, on_step=write,
                             progress=cell_progress(plan, "calibration", progress_stream, done), follow=follow,
                             ready=ready)
    finally:
        if appender is not None:
            appender.close()
    return len(remaining)


def fit_cell_recorded(data_path: str | Path, model_path: str | Path) -> CellModel:
    """Every axis' model from the recorded steps (valid rows only), the data file stamped into each axis'
    provenance, saved atomically."""
    ds = read_csv(data_path)
    cell = fit_cell(ds.valid_rows(), source=str(data_path)).model
    for model in cell.models.values():
        stamp_data(model, [(data_path, len(ds))])
    cell.provenance = dict(cell.models[cell.axes[0]].provenance)
    save_cell_model(cell, model_path)
    return cell
