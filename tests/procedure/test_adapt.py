"""``validate --adapt``: the daemon's bias tracker in the validation procedure, online = offline.

Offline is ``validate --adapt`` (:func:`nanodrift.procedure.validation.run_validation`); online is the
daemon's health unit (``nanodrift.service.health_unit``) fed through its compensator, command by command and
reading by reading: both must give the same corrections, float for float. A multi-axis cell runs one
tracker per axis (``run_validation_steps``), on the simulated XY cell through its drivers.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
from helpers.sim_helpers import Capture, trained_model

import nanodrift
from nanodrift.assembly import procedure_drivers, simulated_drivers
from nanodrift.calibration import iso9283
from nanodrift.calibration.plans import StepResult, cell_validation_plan
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.cli import main
from nanodrift.compensation import Compensator, Target
from nanodrift.config import parse_config
from nanodrift.drivers.base import Reading, SensorConfig
from nanodrift.drivers.simulated.plugin import shared_cell
from nanodrift.logs import get_logger
from nanodrift.model.cell_model import CellModel, load_any_model
from nanodrift.model.model import Model, save_model
from nanodrift.procedure.validation import run_validation, run_validation_steps
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.table import SensorTable


def shifted(model: Model, bias_um: float) -> Model:
    """The model with its bias moved: every command off by ``bias_um`` (a cell that changed)."""
    terms = [dataclasses.replace(ft, coef=ft.coef + bias_um) if ft.term.name == "1" else ft for ft in model.terms]
    return Model(terms=terms, training=model.training, fit=model.fit, covariance=model.covariance)


def validate(model: Model, cycles: int, adapt: BiasTracker | None, fault: bool = False) -> iso9283.TestResult:
    drivers = simulated_drivers("test2", seed=21)
    if fault:  # the interferometer fails through step 5's window and its retries: an invalid step
        shared_cell(drivers.context).inject_fault("interferometer", 5 * 29 + 20, 5 * 29 + 60, "fault")
    return asyncio.run(run_validation(drivers, model, name="test2", cycles=cycles, progress_stream=Capture(),
                                      adapt=adapt))


@pytest.fixture(scope="module")
def adapted_with_a_fault() -> tuple[Model, iso9283.TestResult, BiasTracker]:
    """The shifted model's ``validate --adapt`` run of 4 cycles with an invalid step, and its tracker: run once for
    the two tests that check it step by step (they only read the result and the tracker's correction)."""
    model = shifted(trained_model(0), 0.3)
    tracker = BiasTracker(300.0, 1.0)
    return model, validate(model, 4, tracker, fault=True), tracker


def test_online_and_offline_trackers_agree_sample_for_sample(
        adapted_with_a_fault: tuple[Model, iso9283.TestResult, BiasTracker]) -> None:
    model, online, _ = adapted_with_a_fault
    assert not all(s.valid for s in online.steps), "the fault should leave an invalid step"
    offline = BiasTracker(300.0, 1.0)
    expected = []
    for step in online.steps:  # a plain tracker fed the same residuals, valid steps only
        expected.append(offline.correction_um)
        if step.valid:
            offline.update(step.t_s, step.positions_um["x"] - step.step.target_um)
    assert online.corrections_um == expected  # identical floats, step by step
    assert expected[-1] < -0.1  # it moved towards cancelling the +0.3 um

    # and each correction went out with its command: the same run without adaptation commands q - c
    static = validate(model, 4, None, fault=True)
    for a, s, c in zip(online.steps, static.steps, online.corrections_um, strict=True):
        assert a.q_um["x"] - c == pytest.approx(s.q_um["x"], abs=1e-9)


def test_the_daemons_health_unit_gives_validate_adapts_corrections_sample_for_sample(
        adapted_with_a_fault: tuple[Model, iso9283.TestResult, BiasTracker]) -> None:
    """The residuals of a ``validate --adapt`` run (one invalid step included), served by the daemon's
    own pieces: each command's ``correction_um`` equals the correction ``validate`` gave that step, and
    its ``q_sigma_um`` the σ the tracker left there (issue 19)."""
    model, offline, offline_tracker = adapted_with_a_fault
    assert not all(s.valid for s in offline.steps)

    config = parse_config({"health": {"settle_s": 3.0, "window_s": 2.0},
                           "adapt": {"mode": "bias", "tau_s": 300.0, "max_um": 1.0}, "sensors": []},
                          source="adapt.toml")
    channels = sorted(offline.steps[0].temperatures)
    sensors = [SensorConfig(name=c, kind="x", max_age_s=60.0) for c in channels]
    sensors.append(SensorConfig(name="interferometer", kind="x", role="position", max_age_s=60.0))
    config = config.model_copy(update={"sensors": sensors})
    table = SensorTable(config.sensors)
    health = HealthUnit(config, model, get_logger("test"))
    compensator = Compensator(model, config.axis_actuators(), table, monitor=health)
    tracker = health.watches["x"].tracker
    assert model.covariance is not None
    wander_um = model.covariance.wander_um or 0.0

    online, online_sigma = [], []
    for i, step in enumerate(offline.steps):
        # the daemon's window (settle 3 s, then 2 s) ends where the step's average ended: integer
        # offsets from t_s, so the window's end is t_s to the last bit
        t_command = step.t_s - 5.0
        for channel, value in step.temperatures.items():
            table.update(channel, Reading(value, t=t_command))
        compensator.observe(t_command, step.temperatures)
        assert compensator.evaluators is not None and tracker is not None
        static_um = compensator.evaluators["x"].sigma(step.step.target_um, t_command)  # the model's own σ here
        left_um = tracker.sigma_um(static_um, wander_um)  # what the tracker leaves of it
        command = compensator.compensate(Target(i, {"x": step.step.target_um}), t_command, 1.7e9)
        assert command.correction_um is not None and command.q_sigma_adapted_um is not None
        online.append(command.correction_um["x"])
        online_sigma.append((command.q_sigma_adapted_um["x"], left_um, static_um))
        assert command.q_sigma_um == {"x": static_um}  # the model's own σ, as the contract has it
        position = "interferometer"
        x_um = step.positions_um["x"]
        health.on_position(step.t_s - 1.0, step.t_s - 1.0, x_um, step.valid, channel=position)  # in the window
        health.on_position(step.t_s + 0.5, step.t_s + 0.5, x_um, True, channel=position)  # the next closes it
    assert online == offline.corrections_um  # identical floats, command by command
    assert [a for a, _, _ in online_sigma] == [left for _, left, _ in online_sigma]
    assert online_sigma[0][0] == online_sigma[0][2]  # nothing learnt yet: the model's own σ
    # the +0.3 µm the residuals showed widened σ; taken out, it no longer counts (as in validate --adapt)
    sent = [a for a, _, _ in online_sigma]
    assert sent[1:] == pytest.approx(offline.q_sigma_adapted_um[1:], rel=0.01)  # the same σ as validate --adapt gave
    assert max(sent) > 0.15  # the +0.3 µm the residuals show counts until it is taken out ...
    assert sent[-1] < 0.6 * max(sent) and sent[-1] > 0.3 + online[-1]  # ... and what is left still does
    assert health.correction_um() == {"x": offline_tracker.correction_um}
    assert health.watches["x"].monitor.n == sum(s.valid for s in offline.steps)
    assert online[-1] < -0.1  # it moved towards cancelling the +0.3 um


def test_adaptation_removes_a_changed_cells_offset() -> None:
    model = shifted(trained_model(0), 0.3)
    static = validate(model, 8, None)
    adaptive = validate(model, 8, BiasTracker(600.0, 1.0))
    assert static.accuracy_nm > 250.0
    assert adaptive.accuracy_nm < 0.6 * static.accuracy_nm
    assert adaptive.adapted and not static.adapted


def test_validate_adapt_on_the_command_line(tmp_path, capsys) -> None:
    path = tmp_path / "m.json"
    save_model(trained_model(0), path)
    assert main(["validate", "--model", str(path), "--cycles", "2", "--adapt", "--adapt-tau-s", "300",
                 "--json"]) == 0
    (doc,) = json.loads(capsys.readouterr().out)["tests"]
    assert doc["adapt"] == {"mode": "bias", "tau_s": 300.0, "max_um": 1.0} and doc["adapted"] is True
    assert doc["final_correction_um"] is not None and 0.0 <= doc["within_2_sigma"] <= 1.0
    assert main(["validate", "--model", str(path), "--cycles", "2", "--adapt", "--no-compensation"]) == 2
    assert "--adapt corrects the model's commands" in capsys.readouterr().err


# ----- a multi-axis cell: one tracker per axis ---------------------------------------------------------

XY_MODEL = Path(nanodrift.__file__).parent / "data" / "default_model_xy.json"  # fitted on the simulated XY cell


def shifted_cell(bias_um: dict[str, float]) -> CellModel:
    """The shipped XY model with each axis' bias moved by ``bias_um[axis]`` (a cell that changed)."""
    model = load_any_model(XY_MODEL)
    assert isinstance(model, CellModel)
    moved = {a: dataclasses.replace(m, id="", terms=[dataclasses.replace(ft, coef=ft.coef + bias_um[a])
                                                     if ft.term.name == "1" else ft for ft in m.terms])
             for a, m in model.models.items()}
    return CellModel(axes=model.axes, models=moved)


def validate_xy(model: CellModel, cycles: int, adapt: dict[str, BiasTracker] | None) -> list[StepResult]:
    """The ISO 9283 plan through ``model`` on the simulated XY cell's drivers, in the drifting room of test 2."""
    config = parse_config({"simulation": {"axes": "xy", "scenario": "test2", "seed": 7}}, source="xy.toml")
    run = asyncio.run(run_validation_steps(
        procedure_drivers(config), cell_validation_plan(("x", "y"), cycles), model,
        limits=config.axis_actuators(), name="test2", progress_stream=Capture(), adapt=adapt))
    return run.steps


def axis_accuracy_nm(steps: list[StepResult]) -> dict[str, float]:
    """Each axis' ISO 9283 accuracy (mean over P1..P5) against the true position."""
    targets = {a: np.array([r.step.target(a) for r in steps]) for a in ("x", "y")}
    attained = {a: np.array([r.true_um[a] for r in steps]) for a in ("x", "y")}
    result = iso9283.summarize_runs("test2", targets, attained, None)
    return {a: result.axis_accuracy_nm(a, with_model=False) for a in ("x", "y")}


def test_each_axis_of_an_xy_cell_runs_its_own_tracker_and_removes_its_own_offset() -> None:
    model = shifted_cell({"x": 0.3, "y": -0.25})
    static = validate_xy(model, 6, None)
    trackers = {a: BiasTracker(300.0, 1.0) for a in ("x", "y")}
    adaptive = validate_xy(model, 6, trackers)
    assert all(r.valid for r in adaptive)

    # each axis' commands carry its own tracker's correction, fed by its own residuals only
    for axis, tracker in trackers.items():
        plain = BiasTracker(300.0, 1.0)
        for a, s in zip(adaptive, static, strict=True):
            assert a.q_um[axis] - plain.correction_um == pytest.approx(s.q_um[axis], abs=1e-9)
            plain.update(a.t_s, a.positions_um[axis] - a.step.target(axis))
        assert tracker.updates == len(adaptive) == 30
        assert tracker.correction_um == plain.correction_um
    assert trackers["x"].correction_um < -0.1 and trackers["y"].correction_um > 0.08  # towards -0.3 and +0.25

    before, after = axis_accuracy_nm(static), axis_accuracy_nm(adaptive)
    assert before["x"] > 200.0 and before["y"] > 150.0  # the offsets the model now makes
    assert after["x"] < 0.6 * before["x"] and after["y"] < 0.6 * before["y"]


def test_validate_adapt_on_an_xy_model_reports_each_axis_and_matches_the_static_run(capsys) -> None:
    """The shipped XY model, right for the room, in the drifting test 2: adaptation does no harm per axis."""
    static_args = ["validate", "--model", str(XY_MODEL), "--cycles", "3", "--scenario", "test2", "--json"]
    assert main(static_args) == 0
    [static] = json.loads(capsys.readouterr().out)["tests"]
    assert main([*static_args, "--adapt", "--adapt-tau-s", "300"]) == 0
    [adaptive] = json.loads(capsys.readouterr().out)["tests"]
    adapt = adaptive["adapt"]
    assert (adapt["mode"], adapt["tau_s"], adapt["max_um"]) == ("bias", 300.0, 1.0)
    assert list(adapt["axes"]) == ["x", "y"]
    for axis in ("x", "y"):
        assert adapt["axes"][axis]["updates"] == 15  # every step of 3 cycles over P1..P5
        assert abs(adapt["axes"][axis]["final_correction_um"]) < 0.2  # a right model: little to correct
        with_static = static["against_truth"]["with"]["axis_accuracy_nm"][axis]
        with_adapt = adaptive["against_truth"]["with"]["axis_accuracy_nm"][axis]
        assert with_adapt <= 1.2 * with_static + 10.0
        # the uncompensated run is the same room, noise and plan in both
        assert adaptive["against_truth"]["without"]["axis_accuracy_nm"][axis] == pytest.approx(
            static["against_truth"]["without"]["axis_accuracy_nm"][axis], rel=0.05)
