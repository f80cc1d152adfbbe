"""Calibration: run (or continue) the trajectory, append each step to the CSV, fit the model.

One recording for a cell of any number of axes: each completed step is one row of the CSV contract
(``t_s, x_um, q_um, cycle, valid, T1, ...`` for one axis; ``t_s, x_um, y_um, q_x_um, q_y_um, ...``
for several), appended and fsynced, so an interrupted run resumes from the file; an existing file is
never overwritten without ``--resume``. The fit writes the model file of the cell's shape.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Awaitable, Callable, Mapping, Sequence
from pathlib import Path
from typing import IO

from nanodrift.calibration.dataset import CsvAppender, DataError, command_column, position_column, read_csv
from nanodrift.calibration.plans import PAPER_TIMING, PlannedStep, StepResult, StepTiming, calibration_plan
from nanodrift.drivers_set import DriverSet
from nanodrift.model.cell_model import CellModel, save_cell_model
from nanodrift.model.identify import fit_cell
from nanodrift.model.model import Model
from nanodrift.model.provenance import stamp_data
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.steps import Limits, axis_limits, run_steps


def command_columns(axes: Sequence[str]) -> dict[str, str]:
    """Each axis' command column: ``q_<axis>_um``; a one-axis file keeps ``q_um`` (the CSV contract)."""
    return {axes[0]: "q_um"} if len(axes) == 1 else {a: command_column(a) for a in axes}


def calibration_columns(drivers: DriverSet, axes: Sequence[str]) -> list[str]:
    return ["t_s", *map(position_column, axes), *command_columns(axes).values(), "cycle", "valid",
            *drivers.temperature_channels]


def completed_steps(data_path: Path, columns: Sequence[str]) -> tuple[int, float]:
    """Rows already recorded in ``data_path`` (for --resume) and the last time stamp."""
    if not data_path.exists() or data_path.stat().st_size == 0:
        return 0, -math.inf
    ds = read_csv(data_path)
    found = list(ds.columns())
    if sorted(found) != sorted(columns):
        raise DataError(f"{data_path}: cannot resume, its columns {found} differ from this cell's {list(columns)}")
    return len(ds), float(ds.t[-1])


async def record_calibration(
    drivers: DriverSet,
    data_path: str | Path,
    *,
    limits: Limits | None = None,
    cycles: int = 24,
    plan: Sequence[PlannedStep] | None = None,
    timing: StepTiming = PAPER_TIMING,
    resume: bool = False,
    progress_stream: IO[str] | None = None,
    on_step: Callable[[StepResult], None] | None = None,
    follow: Mapping[str, FollowCheck] | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
) -> int:
    """Run (or continue) the calibration ``plan`` (default: the paper's sweeps of ``cycles`` cycles, one
    axis), appending each step to ``data_path``.

    Returns the number of steps recorded in this call. With ``resume``, steps already in the file
    are skipped; without it, an existing non-empty file is an error (never overwrite hours of data).
    ``limits``, ``follow`` and ``ready``: see :func:`nanodrift.procedure.steps.run_steps`.
    """
    path = Path(data_path)
    limits = axis_limits(drivers, limits)
    columns = calibration_columns(drivers, tuple(limits))
    q_columns = command_columns(tuple(limits))
    plan = list(plan if plan is not None else calibration_plan(cycles))
    done = 0
    if resume:
        done, _ = completed_steps(path, columns)
    elif path.exists() and path.stat().st_size > 0:
        raise FileExistsError(f"{path} already holds recorded steps; use --resume to continue it, or another --data")
    remaining = plan[done:]
    progress = Progress(plan, "calibration", progress_stream, done=done)
    appender: CsvAppender | None = None  # created with the first step: a run refused before it leaves no file

    def write(result: StepResult) -> None:
        nonlocal appender
        if appender is None:
            appender = CsvAppender(path, columns)
        appender.append({"t_s": result.t_s, **{position_column(a): v for a, v in result.positions_um.items()},
                         **{q_columns[a]: v for a, v in result.q_um.items()}, "cycle": result.step.cycle,
                         "valid": int(result.valid), **result.temperatures})
        if on_step is not None:
            on_step(result)

    try:
        await run_steps(drivers, remaining, limits=limits, timing=timing, on_step=write, progress=progress,
                        follow=follow, ready=ready)
    finally:
        if appender is not None:
            appender.close()
    return len(remaining)


def resume_hint(out: str | Path, data: str | Path, recorded: int, total: int) -> str:
    return (f"calibration stopped after {recorded} of {total} steps; every completed step is in {data}. "
            f"Resume with: nanodrift calibrate --out {out} --data {data} --resume")


def fit_recorded(data_path: str | Path, model_path: str | Path, *, plan: Sequence[PlannedStep] = ()) -> CellModel:
    """Identify every axis' model from the recorded steps (valid rows only), each covering the plan's targets,
    stamp the data file (its SHA-256 and rows) into its provenance and save it atomically (a cell of one axis:
    the one-axis file).

    ``plan``: the calibration's. The models' training ranges cover its targets (:func:`cover_commanded`).
    Empty: the measured range alone, as ``nanodrift fit`` gives.
    """
    ds = read_csv(data_path)
    cell = fit_cell(ds, source=str(data_path)).model
    for model in cell.models.values():
        cover_commanded(model, plan)
    stamp_data(cell, [(data_path, len(ds))])
    save_cell_model(cell, model_path)
    return cell


def cover_commanded(model: Model, plan: Sequence[PlannedStep]) -> None:
    """Widen the model's training range of every axis' position to the plan's targets, and give it the id of
    that content.

    The position ranges decide which targets are flagged as extrapolating. A calibration commands 0..480 µm
    and measures 0.1..480.4 µm: the sub-micrometre gap is the stage's noise and offset, not a part of
    the travel the model has not seen. Only a newly fitted model is widened (the range is part of
    its id): files already written keep theirs.
    """
    if not plan:
        return

    def widened(axis: str, measured: tuple[float, float]) -> tuple[float, float]:
        targets = [step.target(axis) for step in plan]
        return min(measured[0], min(targets)), max(measured[1], max(targets))

    training = model.training
    model.training = dataclasses.replace(
        training, x_range=widened("x", training.x_range),
        position_ranges={axis: widened(axis, r) for axis, r in training.position_ranges.items()})
    model.id = model.content_id()


#: a temperature channel that varied less than this during a calibration is too narrow a range to trust:
#: its coefficient is mostly the interferometer's wander, and the room leaves the range at once
NARROW_RANGE_C = 0.3


def narrow_channels(data_path: str | Path) -> dict[str, tuple[float, float]]:
    """The temperature channels of a calibration's valid rows whose range is below :data:`NARROW_RANGE_C`."""
    ds = read_csv(data_path).valid_rows()
    ranges = {name: (float(ds.channels[name].min()), float(ds.channels[name].max()))
              for name in ds.channel_names if len(ds)}
    return {name: (lo, hi) for name, (lo, hi) in ranges.items() if hi - lo < NARROW_RANGE_C}
