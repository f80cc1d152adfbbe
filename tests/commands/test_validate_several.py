"""Issue 19: ``validate`` over several tests in one report, and on the simulated cell scored against the
true position beside the interferometer (items 2 and 7)."""

from __future__ import annotations

import asyncio
import json
import math
from dataclasses import replace

import pytest
from helpers.daemon_harness import REPO
from helpers.sim_helpers import Capture, trained_model

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration.iso9283 import summarize
from nanodrift.cli import main
from nanodrift.model.model import save_model
from nanodrift.procedure.validation import run_validation

#: an interferometer that reads the truth: no white noise, no wander (its 0.3 nm resolution remains)
PERFECT_INTERFEROMETER = {"interferometer_noise_um": 0.0, "interferometer_wander_um": 0.0}


@pytest.fixture(scope="module")
def model_path(tmp_path_factory: pytest.TempPathFactory) -> str:
    path = tmp_path_factory.mktemp("model") / "m.json"
    save_model(trained_model(0), path)
    return str(path)


def test_the_truth_is_what_a_perfect_interferometer_reads_and_only_a_simulated_cell_has_it() -> None:
    drivers = simulated_drivers("test2", seed=4, params=PERFECT_INTERFEROMETER)
    result = asyncio.run(run_validation(drivers, trained_model(0), name="test2", cycles=2, progress_stream=Capture()))
    assert len(result.x_true_um) == len(result.steps) == 14 and result.has_truth
    assert max(abs(s.positions_um["x"] - x) for s, x in zip(result.steps, result.x_true_um, strict=True)) < 0.002
    # hardware: steps without a true position (nan) give a result without truth, and no truth figures
    blind = summarize("test2", [replace(s, true_um={"x": math.nan}) for s in result.steps], True, 0)
    assert not blind.has_truth and "true_position" not in blind.to_dict()


def test_validate_on_the_simulated_cell_reports_accuracy_against_the_true_position(model_path, capsys) -> None:
    assert main(["validate", "--model", model_path, "--scenario", "test2", "--seed", "1", "--cycles", "2",
                 "--json"]) == 0
    (doc,) = json.loads(capsys.readouterr().out)["tests"]  # one test: the shape of several
    assert doc["test"] == "test2" and doc["with_comp_nm"] > 0
    truth = doc["true_position"]
    assert set(truth) == {"without_comp_nm", "with_comp_nm", "improvement_ratio", "points"}
    assert len(truth["points"]) == 7 and truth["with_comp_nm"] > 0
    # the interferometer's noise (20 nm) and wander (25 nm) separate the two views, by less than 100 nm
    assert truth["with_comp_nm"] != doc["with_comp_nm"]
    assert abs(truth["with_comp_nm"] - doc["with_comp_nm"]) < 100
    assert truth["with_comp_nm"] < truth["without_comp_nm"]

    assert main(["validate", "--model", model_path, "--scenario", "test2", "--seed", "1", "--cycles", "2"]) == 0
    text = capsys.readouterr().out
    assert text.startswith("TABLE I")
    assert "Against the TRUE position" in text
    assert f"{truth['with_comp_nm']:.0f} nm" in text.split("Against the TRUE position")[1]


def test_validate_over_two_tests_writes_one_report_with_a_row_each(model_path, tmp_path, capsys) -> None:
    report = tmp_path / "report"
    assert main(["validate", "--model", model_path, "--scenario", "test2,test5", "--seed", "1", "--cycles", "2",
                 "--report", str(report)]) == 0
    out = capsys.readouterr().out
    rows = [line.split()[0] for line in out.split("* from calculation")[0].splitlines()[3:]]
    assert rows == ["test2", "test5"]
    assert "per point (test2, with compensation)" in out and "per point (test5, with compensation)" in out
    doc = json.loads((report / "validation.json").read_text())
    assert [t["test"] for t in doc["tests"]] == ["test2", "test5"]
    assert doc["tests"][1]["extrapolating_steps"] == 14  # test 5 is outside the training range
    table = (report / "table1.txt").read_text()
    assert "\ntest2 " in table and "\ntest5 " in table
    svg = (report / "fig11_accuracy.svg").read_text()
    assert "test2*" in svg and "test5*" in svg  # one figure comparing them
    assert "--seed 1" in svg

    # repeated --scenario names the same tests: the same Table I (same seeds, same rooms)
    assert main(["validate", "--model", model_path, "--scenario", "test2", "--scenario", "test5", "--seed", "1",
                 "--cycles", "2", "--json"]) == 0
    again = json.loads(capsys.readouterr().out)
    assert [t["with_comp_nm"] for t in again["tests"]] == [t["with_comp_nm"] for t in doc["tests"]]
    assert not any(math.isnan(t["with_comp_nm"]) for t in again["tests"])


def test_several_tests_on_hardware_are_refused_before_anything_moves(model_path, capsys) -> None:
    lab = str(REPO / "config" / "lab.toml")  # loads without its devices: nothing is opened before the refusal
    assert main(["validate", "--config", lab, "--model", model_path, "--scenario", "test2,test3"]) == 2
    err = capsys.readouterr().err
    assert "several --scenario (test2, test3) need the simulated cell" in err and "lab.toml" in err


def test_an_unknown_test_among_several_is_refused_before_the_first_runs(model_path, tmp_path, capsys) -> None:
    report = tmp_path / "report"
    assert main(["validate", "--model", model_path, "--scenario", "test2,test9", "--report", str(report)]) == 2
    err = capsys.readouterr().err
    assert "unknown scenario 'test9'" in err and "valid scenarios: steady, train" in err
    assert not report.exists()
