"""Multi-axis procedures through the drivers, on the simulated XY cell (``[simulation] axes = "xy"``, virtual clock).

``calibrate --config`` drives the space-filling plan on every axis and writes the multi-axis CSV and a
CellModel; ``validate --config`` drives the ISO 9283 plan and prints Table I per axis and AP/RP in 2-D,
agreeing with the vectorised simulated path; a dirty window on one axis' sensor is measured again;
an interrupted calibration resumes from its file.
"""

from __future__ import annotations

import asyncio
import contextlib
import io
import json
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

import nanodrift
from nanodrift.assembly import procedure_drivers
from nanodrift.calibration.dataset import read_csv
from nanodrift.calibration.plans import StepResult, StepTiming, cell_calibration_plan, cell_validation_plan
from nanodrift.calibration.residuals import BiasTracker
from nanodrift.cli import main as cli
from nanodrift.config import load_config
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.plugin import RESOURCE_KEY
from nanodrift.model.cell_model import CellModel, load_any_model, save_cell_model
from nanodrift.procedure.recording import record_calibration
from nanodrift.procedure.steps import run_steps
from nanodrift.procedure.validation import run_validation_steps


def _config(tmp_path: Path, axes: str = "xy") -> Path:
    path = tmp_path / f"sim_{axes}.toml"
    path.write_text(f'cell = "c"\n[simulation]\naxes = "{axes}"\nscenario = "train"\nseed = 1\n')
    return path


@pytest.fixture(scope="module")
def calibrated_xy(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """``calibrate --cycles 2`` on the simulated XY cell, run once for the tests that read what it wrote (the
    directory holding ``xy.json`` and ``xy_data.csv``) and what it printed: the command is deterministic, and
    the tests only read its files (a test that writes copies them first)."""
    tmp_path = tmp_path_factory.mktemp("calibrated_xy")
    config = _config(tmp_path)
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(io.StringIO()):
        code = cli(["calibrate", "--config", str(config), "--cycles", "2", "--out", str(tmp_path / "xy.json")])
    assert code == 0
    return tmp_path, stdout.getvalue()


def test_calibrate_drives_every_axis_along_the_plan_and_writes_a_cell_model(
        calibrated_xy: tuple[Path, str]) -> None:
    tmp_path, printed = calibrated_xy
    out = tmp_path / "xy.json"
    data = read_csv(tmp_path / "xy_data.csv")
    plan = cell_calibration_plan(("x", "y"), 2)
    assert data.axes == ("x", "y") and len(data) == len(plan) == 34
    assert list(data.columns())[:5] == ["t_s", "x_um", "y_um", "q_x_um", "q_y_um"]
    for axis in ("x", "y"):
        commanded = np.array([s.target(axis) for s in plan])
        assert np.array_equal(data.commands[axis], commanded)  # the plan, as commanded
        # each axis' own interferometer follows its command (geometry, crosstalk and drift: a few µm at most)
        assert np.max(np.abs(data.positions[axis] - commanded)) < 3.0
    assert np.all(data.extra["valid"] == 1)
    assert np.all(np.diff(data.t) == pytest.approx(29.0))  # the paper's 4 s rise + 25 s hold per step
    model = load_any_model(out)  # its ids checked against its content
    assert isinstance(model, CellModel) and model.axes == ("x", "y")
    # every axis' training range covers the commanded 0..480 µm, as a one-axis calibration's x range does:
    # a commanded point measured 0.1 µm off is no extrapolation
    assert all(lo <= 0.0 and hi >= 480.0 for lo, hi in model.position_ranges.values())
    assert model.out_of_range({"x": 0.0, "y": 480.0}) == []
    y_terms = [t.term.name for t in model.models["y"].terms]
    assert "x" in y_terms  # y's command corrects x's crosstalk: a cross term only a multi-axis fit has
    assert f"model {model.id} (axes x, y)" in printed


def test_validate_through_the_drivers_prints_ap_2d_like_the_simulated_path(tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    config = _config(tmp_path)
    model = tmp_path / "xy.json"
    assert cli(["calibrate", "--config", str(config), "--cycles", "6", "--out", str(model)]) == 0
    capsys.readouterr()
    assert cli(["validate", "--config", str(config), "--model", str(model), "--cycles", "2",
                "--scenario", "test2"]) == 0
    driven, progress = capsys.readouterr()
    # the one-axis procedure's progress, for each of the two runs (uncompensated, then through the model)
    assert progress.count("test2: 0/10 steps") == 2 and progress.count("test2: 10/10 steps") == 2
    assert cli(["validate", "--model", str(model), "--cycles", "2", "--scenario", "test2"]) == 0
    simulated = capsys.readouterr().out

    def ap(text: str) -> tuple[float, float]:
        found = re.search(r"AP 2-D\s+(\d+) nm\s+(\d+) nm", text)
        assert found is not None, text
        return float(found[1]), float(found[2])

    assert "axis x" in driven and "axis y" in driven and "RP 2-D" in driven
    # extrapolation is counted on the driven cell as on the simulated path (the same room)
    assert ("steps extrapolating" in driven) == ("steps extrapolating" in simulated)
    (without, with_model), (sim_without, sim_with) = ap(driven), ap(simulated)
    assert with_model < without / 2  # the model compensates on the driven cell too
    # the same plan, room and noise as the vectorised path: the same figures within a few percent
    assert without == pytest.approx(sim_without, rel=0.05) and with_model == pytest.approx(sim_with, rel=0.2)


def test_a_dirty_window_on_one_axis_sensor_is_measured_again(tmp_path: Path) -> None:
    config = load_config(_config(tmp_path))
    drivers = procedure_drivers(config)
    cell = drivers.context.resources.get(RESOURCE_KEY, SimulatedCell)
    assert isinstance(cell, SimulatedCell)
    timing = StepTiming(ramp_s=4.0, hold_s=25.0, window_s=5.0)
    # the y beam is lost during the second step's averaging window (t 49..58 s): that window is dirty
    cell.inject_fault("interferometer_y", 55.0, 57.0, "fault")
    plan = cell_calibration_plan(("x", "y"), 1)[:3]
    results: list[StepResult] = asyncio.run(run_steps(drivers, plan, limits=config.axis_actuators(),
                                                          timing=timing))
    assert [r.retries for r in results] == [0, 1, 0]
    assert all(r.valid for r in results)
    second = results[1]
    assert second.positions_um["y"] == pytest.approx(30.0, abs=2.0)  # measured again, not averaged with a fault
    assert second.t_s == pytest.approx(58.0 + 5.0)  # one more window


def test_an_interrupted_calibration_resumes_from_its_file(tmp_path: Path) -> None:
    config = load_config(_config(tmp_path))
    data = tmp_path / "xy_data.csv"
    plan = cell_calibration_plan(("x", "y"), 1)
    limits = config.axis_actuators()
    drivers = procedure_drivers(config)
    assert asyncio.run(record_calibration(drivers, data, limits=limits, plan=plan[:5])) == 5
    with pytest.raises(FileExistsError):
        asyncio.run(record_calibration(drivers, data, limits=limits, plan=plan))
    last_t = float(read_csv(data).t[-1])
    drivers = procedure_drivers(config, start_s=last_t + 1.0)
    assert asyncio.run(record_calibration(drivers, data, limits=limits, plan=plan, resume=True)) == len(plan) - 5
    recorded = read_csv(data)
    assert len(recorded) == len(plan) and np.all(np.diff(recorded.t) > 0)
    assert np.array_equal(recorded.commands["y"], [s.target("y") for s in plan])


def test_a_three_axis_cell_calibrates_through_its_drivers(tmp_path: Path) -> None:
    out = tmp_path / "xyz.json"
    assert cli(["calibrate", "--config", str(_config(tmp_path, "xyz")), "--cycles", "2", "--out", str(out)]) == 0
    data = read_csv(tmp_path / "xyz_data.csv")
    assert data.axes == ("x", "y", "z")
    assert np.max(np.abs(data.positions["z"] - data.commands["z"])) < 3.0
    model = load_any_model(out)
    assert isinstance(model, CellModel) and model.axes == ("x", "y", "z")


def test_validate_through_the_drivers_counts_the_steps_outside_the_training_ranges(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], calibrated_xy: tuple[Path, str]) -> None:
    config = _config(tmp_path)
    model = tmp_path / "xy.json"  # the 2-cycle calibration's model (validate only reads it; a copy all the same)
    shutil.copyfile(calibrated_xy[0] / "xy.json", model)
    # the paper's test 5: a room far outside the calibration's (a hot plate near the stage)
    assert cli(["validate", "--config", str(config), "--model", str(model), "--cycles", "1",
                "--scenario", "test5", "--json"]) == 0
    (doc,) = json.loads(capsys.readouterr().out)["tests"]
    assert doc["extrapolating_steps"] == 5  # every compensated step of P1..P5
    # the calibration's own room from its start: not every step is outside (a step can be: 2 cycles span little)
    assert cli(["validate", "--config", str(config), "--model", str(model), "--cycles", "1",
                "--scenario", "train", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["tests"][0]["extrapolating_steps"] < 5


def test_no_command_before_every_channel_the_model_reads_has_a_clean_sample(tmp_path: Path) -> None:
    config = load_config(_config(tmp_path))
    drivers = procedure_drivers(config)
    cell = drivers.context.resources.get(RESOURCE_KEY, SimulatedCell)
    assert isinstance(cell, SimulatedCell)
    cell.inject_fault("T2", 0.0, 1000.0, "fault")  # burnt out from the start
    model = load_any_model(Path(nanodrift.__file__).parent / "data" / "default_model_xy.json")
    assert isinstance(model, CellModel) and "T2" in model.channels
    plan = cell_validation_plan(("x", "y"), 1)
    with pytest.raises(RuntimeError, match="no clean temperature sample yet"):
        asyncio.run(run_validation_steps(drivers, plan, model, limits=config.axis_actuators(),
                                         progress_stream=io.StringIO()))
    # uncompensated, the same plan runs: nothing asks the model
    run = asyncio.run(run_validation_steps(procedure_drivers(config), plan, None, limits=config.axis_actuators(),
                                           progress_stream=io.StringIO()))
    assert len(run.steps) == len(plan) and run.extrapolating == 0


def test_validate_refuses_a_model_reading_a_channel_the_cell_does_not_measure_before_anything_moves(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The uncompensated run comes first and asks nothing of the model: the model's channels are checked before
    it, not after a whole plan has run."""
    xy = Path(nanodrift.__file__).parent / "data" / "default_model_xy.json"
    model = CellModel.from_dict(json.loads(re.sub(r"\bT2\b", "T9", xy.read_text())), check_id=False)
    save_cell_model(model, tmp_path / "t9.json")
    assert cli(["validate", "--config", str(_config(tmp_path)), "--model", str(tmp_path / "t9.json"),
                "--cycles", "1"]) == 2
    err = capsys.readouterr().err
    assert "needs channel(s) T9 that this cell does not measure" in err
    assert " steps, " not in err  # no progress line: no plan started


def test_validate_refuses_a_one_axis_model_on_a_cell_of_several_axes_naming_them(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    one_axis = Path(nanodrift.__file__).parent / "data" / "default_model.json"
    assert cli(["validate", "--config", str(_config(tmp_path)), "--model", str(one_axis), "--cycles", "1"]) == 2
    err = capsys.readouterr().err
    assert "a one-axis model drives a cell of one axis, this cell has axes x, y" in err
    assert " steps, " not in err  # no progress line: no plan started


def test_every_axis_command_records_its_sigma_and_its_tracker_correction(tmp_path: Path) -> None:
    """What the one-axis test always recorded per command (the model's q_sigma, the bias correction it carried,
    the σ the tracker leaves) is recorded for every axis of a cell."""
    config = load_config(_config(tmp_path))
    model = load_any_model(Path(nanodrift.__file__).parent / "data" / "default_model_xy.json")
    plan = cell_validation_plan(("x", "y"), 2)
    trackers = {a: BiasTracker(600.0, 1.0) for a in ("x", "y")}
    run = asyncio.run(run_validation_steps(procedure_drivers(config), plan, model, limits=config.axis_actuators(),
                                           progress_stream=io.StringIO(), adapt=trackers))
    assert len(run.sigmas_um) == len(run.corrections_um) == len(run.adapted_sigmas_um) == len(plan)
    assert all(set(s) == {"x", "y"} and all(0.0 < v < 1.0 for v in s.values()) for s in run.sigmas_um)
    assert run.corrections_um[0] == {"x": 0.0, "y": 0.0}  # no residual before the first step
    assert run.adapted_sigmas_um[0] == run.sigmas_um[0]  # before the first residual: the model's own σ
    static = asyncio.run(run_validation_steps(procedure_drivers(config), plan, model, limits=config.axis_actuators(),
                                              progress_stream=io.StringIO()))  # the same room, no tracker
    for axis, tracker in trackers.items():
        assert tracker.updates == sum(r.valid for r in run.steps) and any(c[axis] for c in run.corrections_um)
        # each command is the model's plus the correction recorded for it
        assert [r.q_um[axis] - c[axis] for r, c in zip(run.steps, run.corrections_um, strict=True)] == \
            pytest.approx([r.q_um[axis] for r in static.steps], abs=1e-6)


def test_a_multi_axis_calibration_of_one_cycle_is_refused_before_anything_moves(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One cycle of the plan is its diagonal (x = y at every step): a model fitted on it cannot tell the axes
    apart (it served ~300 µm errors at (435, 45) without a word), so the command refuses it, writing nothing."""
    assert [s.target("x") for s in cell_calibration_plan(("x", "y"), 2)[:17]] == \
        [s.target("y") for s in cell_calibration_plan(("x", "y"), 2)[:17]]  # why: the first cycle is the diagonal
    out = tmp_path / "xy.json"
    assert cli(["calibrate", "--config", str(_config(tmp_path)), "--cycles", "1", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "a calibration of 2 axes needs at least 2 cycles, got 1" in err and "[procedure] cycles" in err
    assert not out.exists() and not (tmp_path / "xy_data.csv").exists()
