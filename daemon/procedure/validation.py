"""ISO 9283 validation on a cell: drive the validation plan through the model (or without it).

One procedure (:func:`run_validation_steps`) drives a cell of any number of axes; a one-axis model is run as a
cell of its one axis. :func:`run_validation` is the one-axis test as ``validate`` and the demo score it.

With ``adapt`` (``validate --adapt``) the model's command gets the daemon's bias correction: the same
:class:`nanodrift.calibration.residuals.BiasTracker`, fed with each valid step's settled residual (the
step's averaged position minus its target, the measurement the daemon's monitor takes while a
target is held), its correction added to every following command. The cell has one tracker per
axis (:func:`run_validation_steps`), as the daemon's health unit does.

On a simulated cell each step also carries the position the stage truly attained, averaged over the
same readings as the interferometer's (``StepResult.true_um``, from the sensor group's
``true_values``), and the result lists them (``TestResult.x_true_um``): the test is scored against the
truth beside the interferometer. Hardware knows no truth: the list stays empty.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import IO

from nanodrift.calibration.iso9283 import TestResult, summarize
from nanodrift.calibration.plans import PlannedStep, StepResult, StepTiming, validation_plan
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.drivers_set import DriverSet
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Model, aim
from nanodrift.procedure.follow import FollowCheck
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.steps import Limits, axis_limits, run_steps


def check_channels(model: Model | CellModel, drivers: DriverSet) -> None:
    """A model reading a channel this cell does not measure is refused before anything moves."""
    missing = [c for c in model.channels if c not in drivers.temperature_channels]
    if missing:
        raise ValueError(f"the model needs channel(s) {', '.join(missing)} that this cell does not measure")


def one_axis(limits: Limits) -> str:
    """The axis of the cell a one-axis test runs on (a one-axis model's): refused on a cell of several."""
    if len(limits) != 1:
        raise ValueError(f"a one-axis model drives a cell of one axis, this cell has axes {', '.join(limits)}")
    return next(iter(limits))


async def run_validation(
    drivers: DriverSet,
    model: Model | None,
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
    """One test of a one-axis model (or none, when ``model`` is None): :func:`run_validation_steps` over the
    one-axis plan, scored with the uncompensated position computed from the same run.

    ``adapt``: a bias tracker (``[adapt] mode = "bias"``) whose correction is added to the model's
    commands, fed by each valid step. The result records, per step, the correction its command
    carried and the model's ``q_sigma_um`` for it.
    """
    limits = axis_limits(drivers, limits)
    axis = one_axis(limits)
    run = await run_validation_steps(drivers, validation_plan(cycles), model, limits=limits, name=name, timing=timing,
                                     progress_stream=progress_stream, follow=follow, ready=ready,
                                     adapt=None if adapt is None else {axis: adapt})
    result = summarize(name, run.steps, model is not None, run.extrapolating, axis)
    if model is not None:
        result.corrections_um = [c[axis] for c in run.corrections_um]
        result.q_sigma_um = [s[axis] for s in run.sigmas_um]
        result.q_sigma_adapted_um = [s[axis] for s in run.adapted_sigmas_um]
        result.adapted = adapt is not None
        result.measurement_sigma_um = model.wander_um
    return result


@dataclass
class ValidationSteps:
    """A validation plan as it ran: its steps, how many commands were for a target or temperatures outside the
    model's training ranges, and per command (none without a model) each axis' bias correction, the model's
    ``q_sigma`` and, with trackers, the σ the corrected command keeps."""

    steps: list[StepResult]
    extrapolating: int = 0
    corrections_um: list[dict[str, float]] = field(default_factory=list)
    sigmas_um: list[dict[str, float]] = field(default_factory=list)
    adapted_sigmas_um: list[dict[str, float]] = field(default_factory=list)


async def run_validation_steps(
    drivers: DriverSet,
    plan: Sequence[PlannedStep],
    model: Model | CellModel | None,
    *,
    limits: Limits,
    name: str = "validation",
    timing: StepTiming | None = None,
    progress_stream: IO[str] | None = None,
    follow: Mapping[str, FollowCheck] | None = None,
    ready: Callable[[], Awaitable[None]] | None = None,
    adapt: Mapping[str, BiasTracker] | None = None,
) -> ValidationSteps:
    """The ISO 9283 ``plan`` on a cell of any number of axes, through ``model`` (None: command = target).

    ``adapt``: a bias tracker per axis, as the daemon's health unit keeps one per axis; each adds its
    correction to its own axis' command and is fed that axis' residual of every valid step."""
    if adapt is not None and model is None:
        raise ValueError("adaptation corrects the model's commands: it needs a model")
    trackers = dict(adapt or {})
    cell = None if model is None else CellModel.of(model)
    # the cell's axis for each of the model's: a one-axis model's x is the cell's one axis, whatever its name
    axis_of = {} if cell is None else {"x": one_axis(limits)} if isinstance(model, Model) else {a: a for a in cell.axes}
    if model is not None:
        check_channels(model, drivers)
    evaluators = {} if cell is None else cell.evaluators()
    run = ValidationSteps([])
    latest: dict[str, float] = {}

    def observe(t: float, temps: dict[str, float]) -> None:
        latest.update(temps)
        for evaluator in evaluators.values():
            evaluator.observe(t, temps)

    def command_for(targets: dict[str, float], t: float) -> dict[str, float]:
        assert cell is not None  # command_for is given to run_steps only with a model
        if not all(evaluator.ready for evaluator in evaluators.values()):  # no command before a clean sample
            raise RuntimeError("no clean temperature sample yet for every channel the model needs")
        positions = {m: targets[a] for m, a in axis_of.items()}
        run.extrapolating += bool(cell.out_of_range(positions, latest))
        x = aim(evaluators.values(), positions)
        sigmas = {axis_of[m]: e.sigma(x, t) for m, e in evaluators.items()}  # before the command: as the daemon
        corrections = {a: tracker.correction_um for a, tracker in trackers.items()}
        run.corrections_um.append({a: corrections.get(a, 0.0) for a in sigmas})
        run.sigmas_um.append(sigmas)
        if trackers:
            wander_um = {a: cell.models[m].wander_um for m, a in axis_of.items()}
            run.adapted_sigmas_um.append({a: tracker.sigma_um(sigmas[a], wander_um[a])
                                          for a, tracker in trackers.items()})
        return {axis_of[m]: float(e.command(x, t)) + corrections.get(axis_of[m], 0.0) for m, e in evaluators.items()}

    def on_step(result: StepResult) -> None:  # as the daemon feeds a settled residual: valid steps only
        for axis, tracker in trackers.items():
            if result.valid:
                tracker.update(result.t_s, result.positions_um[axis] - result.step.target(axis))

    run.steps = await run_steps(drivers, plan, limits=limits, timing=timing or StepTiming(),
                                command_for=None if model is None else command_for, on_step=on_step,
                                on_temperatures=observe, progress=Progress(plan, name, progress_stream), follow=follow,
                                ready=ready)
    return run
