"""Calibration: run (or continue) the trajectory, append each step to the CSV, fit the model.

Each completed step is appended to the CSV and fsynced, so an interrupted run resumes from the file;
an existing file is never overwritten without ``--resume``.
"""

from __future__ import annotations

import math
from collections.abc import Awaitable, Callable, Sequence
from pathlib import Path
from typing import IO

from daemon.calibration.dataset import CsvAppender, DataError, read_csv
from daemon.calibration.plans import PAPER_TIMING, PlannedStep, StepResult, StepTiming, calibration_plan
from daemon.config import ActuatorConfig
from daemon.drivers_set import DriverSet
from daemon.model.identify import FitResult, fit
from daemon.model.model import save_model
from daemon.model.provenance import stamp_data
from daemon.procedure.follow import FollowCheck
from daemon.procedure.progress import Progress
from daemon.procedure.steps import run_steps


def calibration_columns(drivers: DriverSet) -> list[str]:
    return ["t_s", "x_um", "q_um", "cycle", "valid", *drivers.temperature_channels]


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
    limits: ActuatorConfig | None = None,
    cycles: int = 24,
    plan: Sequence[PlannedStep] | None = None,
    timing: StepTiming = PAPER_TIMING,
    resume: bool = False,
    progress_stream: IO[str] | None = None,
    on_step: Callable[[StepResult], None] | None = None,
    follow: FollowCheck | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
) -> int:
    """Run (or continue) the calibration trajectory, appending each step to ``data_path``.

    Returns the number of steps recorded in this call. With ``resume``, steps already in the file
    are skipped; without it, an existing non-empty file is an error (never overwrite hours of data).
    ``follow`` and ``ready``: see :func:`daemon.procedure.steps.run_steps`.
    """
    path = Path(data_path)
    columns = calibration_columns(drivers)
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
        row = {"t_s": result.t_s, "x_um": result.x_um, "q_um": result.q_um, "cycle": result.step.cycle,
               "valid": int(result.valid), **result.temperatures}
        appender.append(row)
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


def fit_recorded(data_path: str | Path, model_path: str | Path) -> FitResult:
    """Identify the model from the recorded steps (valid rows only), stamp the data file (its SHA-256 and
    rows) into its provenance and save it atomically."""
    ds = read_csv(data_path)
    result = fit(ds, source=str(data_path))
    stamp_data(result.model, [(data_path, len(ds))])
    save_model(result.model, model_path)
    return result
