"""ISO 9283 validation, Table I output, the simulate command and the shipped sample data."""

from __future__ import annotations

import asyncio
import csv
import itertools
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.sim_helpers import Capture, trained_model

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration.dataset import read_csv
from nanodrift.calibration.iso9283 import pose_accuracy, pose_repeatability, summarize
from nanodrift.calibration.plans import PlannedStep, StepResult, validation_plan
from nanodrift.cli import main
from nanodrift.model.identify import fit
from nanodrift.model.model import load_model, save_model
from nanodrift.procedure.validation import run_validation
from nanodrift.reports.validation import table1

REPO = Path(__file__).resolve().parents[2]
DATA_DIR = REPO / "daemon" / "data"


def test_iso9283_one_axis():
    x = np.array([10.1, 10.3, 9.9, 10.1])
    accuracy, repeatability = pose_accuracy(x[:, None], [10.0]), pose_repeatability(x[:, None])
    assert accuracy == pytest.approx(0.1)
    dist = np.abs(x - 10.1)
    assert repeatability == pytest.approx(dist.mean() + 3 * dist.std(ddof=1))


def test_without_is_computed_from_the_same_period():
    steps = [StepResult(PlannedStep.on_x(i, i, 80.0), float(i), q_um={"x": 79.6},
                        positions_um={"x": 80.02 + 0.01 * i},
                        temperatures={"T1": 22.0}, valid=True) for i in range(4)]
    steps.append(StepResult(PlannedStep.on_x(4, 4, 80.0), 5.0, {"x": 70.0}, {"x": 70.0}, {"T1": 22.0}, valid=False))
    result = summarize("t", steps, compensated=True)
    (point,), (without,) = result.points, result.points_without
    assert point.visits == without.visits == 4 and result.invalid_steps == 1  # invalid steps never count
    assert point.accuracy_nm == pytest.approx(35.0)
    assert without.accuracy_nm == pytest.approx(435.0)  # x - (q' - x') = x + 0.4
    assert result.improvement == pytest.approx(435.0 / 35.0)


def test_plan_approaches_every_point_from_one_side():
    """ISO 9283 pose repeatability is unidirectional (issue 27): every visit of a point comes from the same side."""
    plan = validation_plan(4)
    assert [s.target_um for s in plan[:14]] == [0, 80, 160, 240, 320, 400, 480] * 2
    assert len(plan) == 28 and {s.cycle for s in plan} == {0, 1, 2, 3}
    sides: dict[float, set[bool]] = {}
    for before, step in itertools.pairwise(plan):
        sides.setdefault(step.target_um, set()).add(step.target_um > before.target_um)
    assert all(len(directions) == 1 for directions in sides.values()), sides


def test_compensation_beats_no_compensation_in_range():
    model = trained_model(0)
    with_ = asyncio.run(run_validation(simulated_drivers("test2", seed=11), model, name="test2", cycles=8,
                                       progress_stream=Capture()))
    without = asyncio.run(run_validation(simulated_drivers("test2", seed=11), None, name="test2", cycles=8,
                                         progress_stream=Capture()))
    assert with_.accuracy_nm < 90.0 and with_.accuracy_without_nm > 300.0
    assert with_.improvement > 4.0
    # the computed "without" matches what the stage really does without the model, same room, same seed
    assert with_.accuracy_without_nm == pytest.approx(without.accuracy_without_nm, abs=25.0)
    assert np.isnan(without.accuracy_nm) and not without.compensated
    text = table1([without, with_])
    assert "*" in text.splitlines()[-2] and "—" in text.splitlines()[-3]


def test_out_of_range_test_is_flagged_and_still_improved():
    model = trained_model(0)
    result = asyncio.run(run_validation(simulated_drivers("test5", seed=12), model, name="test5", cycles=4,
                                        progress_stream=Capture()))
    assert result.extrapolating_steps == len(result.steps)
    assert result.accuracy_without_nm > 1000.0 and result.improvement > 1.5


def test_validate_command_json_and_report(tmp_path, capsys):
    model_path = tmp_path / "m.json"
    save_model(trained_model(0), model_path)
    report = tmp_path / "rep"
    assert main(["validate", "--model", str(model_path), "--cycles", "4", "--json", "--report", str(report),
                 "--scenario", "test3", "--seed", "2"]) == 0
    printed = json.loads(capsys.readouterr().out)
    assert printed == json.loads((report / "validation.json").read_text())
    assert set(printed) == {"model", "backend", "cycles", "tests"}  # one test: the shape of several (issue 27)
    (doc,) = printed["tests"]
    assert doc["test"] == "test3" and doc["compensated"] and len(doc["points"]) == 7
    assert doc["with_comp_nm"] < doc["without_comp_nm"] and doc["without_is_computed"]
    for name in ("table1.txt", "validation.json", "fig9_drift_at_zero.png", "fig11_accuracy.png", "validation_raw.csv"):
        assert (report / name).stat().st_size > 0
    assert (report / "fig9_drift_at_zero.png").read_bytes()[:4] == b"\x89PNG"
    assert 'id="sigma-band' in (report / "fig9_drift_at_zero.svg").read_text()  # ±2σ about x' = 0
    raw = list(csv.DictReader((report / "validation_raw.csv").open()))
    header = (report / "validation_raw.csv").read_text().splitlines()[0]
    assert header.startswith("test,t_s,cycle,target_um,q_um,x_measured_um,x_without_um,valid,T1")
    assert header.endswith(",x_true_um,q_sigma_um")  # appended, never renamed
    assert len(raw) == 4 * 7
    sigmas = [float(row["q_sigma_um"]) for row in raw]
    assert all(0.0 < sigma < 1.0 for sigma in sigmas)  # every compensated step carries its command's σ


def test_validate_runs_the_papers_test1_without_the_model(tmp_path, capsys):
    """Issue 27: the paper's test 1 is the stage without compensation; validate --scenario test1 runs it so."""
    model_path = tmp_path / "m.json"
    save_model(trained_model(0), model_path)
    assert main(["validate", "--model", str(model_path), "--cycles", "2", "--json", "--scenario", "test1"]) == 0
    (doc,) = json.loads(capsys.readouterr().out)["tests"]
    assert doc["test"] == "test1" and not doc["compensated"] and doc["with_comp_nm"] is None
    assert doc["without_comp_nm"] > 100.0
    assert main(["validate", "--model", str(model_path), "--cycles", "2", "--scenario", "test1", "--adapt"]) == 2
    assert "--scenario test1 runs without the model" in capsys.readouterr().err


def test_validate_command_refuses_bad_model_and_unknown_scenario(tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{not json")
    assert main(["validate", "--model", str(bad)]) == 2
    assert str(bad) in capsys.readouterr().err
    good = tmp_path / "m.json"
    save_model(trained_model(0), good)
    assert main(["validate", "--model", str(good), "--scenario", "test9"]) == 2
    assert "valid scenarios: steady, train" in capsys.readouterr().err


def test_simulate_command_writes_a_fittable_calibration(tmp_path, capsys):
    out = tmp_path / "train.csv"
    assert main(["simulate", "--scenario", "train", "--effects", "thermal_lag:tau_s=1800", "--cycles", "6",
                 "--seed", "9", "--out", str(out)]) == 0
    ds = read_csv(out)
    assert len(ds) == 6 * 17 and list(ds.channels) == ["T1", "T2", "T3", "T4"]
    assert np.array_equal(ds.cycles(), np.repeat(np.arange(6), 17))
    assert fit(ds).model.fit["residual_rms_nm"] < 200.0
    test = tmp_path / "test1.csv"
    assert main(["simulate", "--scenario", "test1", "--cycles", "2", "--out", str(test)]) == 0
    assert np.allclose(read_csv(test).x[:7], [0, 80, 160, 240, 320, 400, 480], atol=1.0)
    assert main(["simulate", "--scenario", "train", "--effects", "warp", "--out", str(tmp_path / "x.csv")]) == 2
    assert "valid effects: thermal_lag, hysteresis" in capsys.readouterr().err


def test_shipped_sample_data_and_model_are_what_the_script_makes(tmp_path):
    made = subprocess.run([sys.executable, str(REPO / "scripts" / "make_default_data.py"), str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert made.returncode == 0, made.stderr
    assert made.stdout.startswith(f"wrote {tmp_path / 'sample_calibration.csv'} and ")
    shipped = read_csv(DATA_DIR / "sample_calibration.csv")
    fresh = read_csv(tmp_path / "sample_calibration.csv")
    # the same up to the last bits another CPU's exp/log may move (numpy's SIMD paths differ between CPUs)
    assert np.allclose(shipped.x, fresh.x, rtol=1e-12, atol=1e-12)
    assert np.allclose(shipped.channels["T4"], fresh.channels["T4"], rtol=1e-12, atol=1e-12)
    shipped_model = load_model(DATA_DIR / "default_model.json")
    fresh_model = load_model(tmp_path / "default_model.json")
    assert shipped_model.term_names() == fresh_model.term_names()
    assert np.allclose(shipped_model.predict(shipped), fresh_model.predict(shipped), atol=1e-6)
    residual = shipped.q - shipped_model.predict(shipped)
    assert np.sqrt(np.mean(residual**2)) < 0.03
