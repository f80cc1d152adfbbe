"""``validate --adapt``: the daemon's bias tracker in the validation procedure, online = offline.

Offline is ``validate --adapt`` (:func:`nanodrift.procedure.validation.run_validation`); online is the
daemon's health unit (``nanodrift.service.health_unit``) fed through its compensator, command by command and
reading by reading: both must give the same corrections, float for float.
"""

from __future__ import annotations

import asyncio
import dataclasses
import json

import pytest
from helpers.sim_helpers import Capture, trained_model

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration import iso9283
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.cli import main
from nanodrift.compensation import Compensator, Target
from nanodrift.config import parse_config
from nanodrift.drivers.base import Reading, SensorConfig
from nanodrift.drivers.simulated.plugin import shared_cell
from nanodrift.logs import get_logger
from nanodrift.model.model import Model, save_model
from nanodrift.procedure.validation import run_validation
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


def test_online_and_offline_trackers_agree_sample_for_sample() -> None:
    model = shifted(trained_model(0), 0.3)
    online = validate(model, 4, BiasTracker(300.0, 1.0), fault=True)
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


def test_the_daemons_health_unit_gives_validate_adapts_corrections_sample_for_sample() -> None:
    """The residuals of a ``validate --adapt`` run (one invalid step included), served by the daemon's
    own pieces: each command's ``correction_um`` equals the correction ``validate`` gave that step, and
    its ``q_sigma_um`` the σ the tracker left there (issue 19)."""
    model = shifted(trained_model(0), 0.3)
    offline_tracker = BiasTracker(300.0, 1.0)
    offline = validate(model, 4, offline_tracker, fault=True)
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
