"""ISO 9283 validation on a cell: drive the validation plan through the model (or without it).

With ``adapt`` (``validate --adapt``) the model's command gets the daemon's bias correction: the same
:class:`nanodrift.calibration.residuals.BiasTracker`, fed with each valid step's settled residual (the
step's averaged position minus its target, the measurement the daemon's monitor takes while a
target is held), its correction added to every following command.

On a simulated cell each step also carries the position the stage truly attained, averaged over the
same readings as the interferometer's (``StepResult.true_um``, from the sensor group's
``true_values``), and the result lists them (``TestResult.x_true_um``): the test is scored against the
truth beside the interferometer. Hardware knows no truth: the list stays empty.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence
from typing import IO, Any

from nanodrift.calibration.iso9283 import TestResult, summarize
from nanodrift.calibration.plans import PlannedStep, StepResult, StepTiming, validation_plan
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.drivers_set import DriverSet
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Evaluator, Model, aim
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.steps import Limits, axis_limits, run_steps


def check_channels(model: Model | CellModel, drivers: DriverSet) -> None:
    """A model reading a channel this cell does not measure is refused before anything moves."""
    missing = [c for c in model.channels if c not in drivers.temperature_channels]
    if missing:
        raise ValueError(f"the model needs channel(s) {', '.join(missing)} that this cell does not measure")


def check_ready(*evaluators: Evaluator) -> None:
    """No command from a model before every channel it reads has a clean sample."""
    if not all(evaluator.ready for evaluator in evaluators):
        raise RuntimeError("no clean temperature sample yet for every channel the model needs")


def feed_tracker(tracker: BiasTracker, result: StepResult, axis: str) -> float:
    """One step into the tracker, as the daemon feeds a settled residual: valid steps only. The correction."""
    if result.valid:
        tracker.update(result.t_s, result.positions_um[axis] - result.step.target(axis))
    return tracker.correction_um


async def run_validation(
    drivers: DriverSet,
    model: Any | None,
    *,
    limits: Limits | None = None,
    name: str = "validation",
    cycles: int = 30,
    timing: StepTiming | None = None,
    progress_stream: IO[str] | None = None,
    follow: Mapping[str, FollowCheck] | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
    adapt: BiasTracker | None = None,
) -> TestResult:
    """One test: drive the validation plan with the model (or without when ``model`` is None).

    ``adapt``: a bias tracker (``[adapt] mode = "bias"``) whose correction is added to the model's
    commands, fed by each valid step. The result records, per step, the correction its command
    carried and the model's ``q_sigma_um`` for it.
    """
    timing = timing or StepTiming()
    limits = axis_limits(drivers, limits)
    (axis,) = limits  # the one-axis model's axis
    plan = validation_plan(cycles)
    evaluator = model.evaluator() if model is not None else None
    if adapt is not None and model is None:
        raise ValueError("adaptation corrects the model's commands: it needs a model")
    latest: dict[str, float] = {}
    extrapolating = 0
    corrections: list[float] = []
    sigmas: list[float] = []
    adapted_sigmas: list[float] = []
    wander_um = model.wander_um if model is not None else 0.0
    if model is not None:
        check_channels(model, drivers)

    def observe(t: float, temps: dict[str, float]) -> None:
        latest.update(temps)
        if evaluator is not None:
            evaluator.observe(t, temps)

    def command_for(targets: dict[str, float], t: float) -> dict[str, float]:
        nonlocal extrapolating
        target = targets[axis]
        if evaluator is None or model is None:  # the one is None when the other is
            return targets
        check_ready(evaluator)
        if model.out_of_range(target, latest):
            extrapolating += 1
        correction = adapt.correction_um if adapt is not None else 0.0
        corrections.append(correction)
        sigma = evaluator.sigma(target, t)
        sigmas.append(sigma)
        if adapt is not None:
            adapted_sigmas.append(adapt.sigma_um(sigma, wander_um))
        return {axis: float(evaluator.command(target, t)) + correction}

    def on_step(result: StepResult) -> None:
        if adapt is not None:
            feed_tracker(adapt, result, axis)

    progress = Progress(plan, name, progress_stream)
    steps = await run_steps(drivers, plan, limits=limits, timing=timing, command_for=command_for,
                                 on_step=on_step, on_temperatures=observe, progress=progress, follow=follow,
                                 ready=ready)
    result = summarize(name, steps, model is not None, extrapolating, axis)
    if model is not None:
        result.corrections_um = corrections
        result.q_sigma_um = sigmas
        result.q_sigma_adapted_um = adapted_sigmas
        result.adapted = adapt is not None
        result.measurement_sigma_um = wander_um
    return result


async def run_cell_validation_steps(
    drivers: DriverSet,
    plan: Sequence[PlannedStep],
    model: CellModel,
    *,
    compensate: bool,
    limits: Limits,
    name: str = "validation",
    timing: StepTiming | None = None,
    progress_stream: IO[str] | None = None,
    follow: Mapping[str, FollowCheck] | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
) -> tuple[list[StepResult], int]:
    """A multi-axis cell's ISO 9283 plan, through ``model`` when ``compensate`` (else command = target): its
    steps, and how many commands were for a target or temperatures outside the model's training ranges."""
    check_channels(model, drivers)
    evaluators = model.evaluators()
    latest: dict[str, float] = {}
    extrapolating = 0

    def observe(t: float, temps: dict[str, float]) -> None:
        latest.update(temps)
        for evaluator in evaluators.values():
            evaluator.observe(t, temps)

    def command_for(targets: dict[str, float], t: float) -> dict[str, float]:
        nonlocal extrapolating
        check_ready(*evaluators.values())
        extrapolating += bool(model.out_of_range(targets, latest))
        x = aim(evaluators.values(), targets)
        return {axis: evaluator.command(x, t) for axis, evaluator in evaluators.items()}

    steps = await run_steps(drivers, plan, limits=limits, timing=timing or StepTiming(),
                            command_for=command_for if compensate else None, on_temperatures=observe,
                            progress=Progress(plan, name, progress_stream), follow=follow, ready=ready)
    return steps, extrapolating
