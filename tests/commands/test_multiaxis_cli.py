"""The multi-axis commands as a user runs them, and the one-axis outputs they must leave byte for byte."""

import json
import re
import subprocess
from pathlib import Path

import numpy as np
import pytest
from helpers.daemon_harness import run_cli
from helpers.floats import assert_same

from nanodrift.calibration.dataset import read_csv
from nanodrift.cli import main
from nanodrift.model.cell_model import CellModel, load_any_model


def _run(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    """``nanodrift ARGS`` run in ``cwd``, in this process (the installed script runs these commands in
    tests/commands/test_readme_verbatim.py): a subprocess would import numpy and scipy again, most of a ``fit``'s
    CPU."""
    return run_cli(*args, cwd=cwd)


@pytest.fixture(scope="module")
def xy_files(tmp_path_factory):
    """A simulated XY calibration and its model, made through the command line."""
    tmp = tmp_path_factory.mktemp("xy")
    sim = _run("simulate", "--scenario", "train", "--axes", "xy", "--seed", "2", "--out", "cal.csv",
               cwd=tmp)
    assert sim.returncode == 0, sim.stderr
    assert "408 steps of axes x,y (17 per cycle, 3.28 h)" in sim.stderr
    fitted = _run("fit", "cal.csv", "--out", "m.json", cwd=tmp)
    assert fitted.returncode == 0, fitted.stderr
    return tmp, fitted.stdout


def test_fit_and_predict_a_multi_axis_file_from_the_command_line(xy_files):
    tmp, fit_out = xy_files
    assert "(axes x, y)" in fit_out and "\nq_x = " in fit_out and "\nq_y = " in fit_out
    assert "axis y (model m-" in fit_out
    model = load_any_model(tmp / "m.json")
    assert isinstance(model, CellModel) and model.id in fit_out
    assert "y" in model.models["x"].term_names()  # the crosstalk the stage has, found from the file
    pred = _run("predict", "--model", "m.json", "cal.csv", "--out", "p.csv", cwd=tmp)
    assert pred.returncode == 0, pred.stderr
    out = read_csv(tmp / "p.csv")
    for a in "xy":
        residual = out.extra[f"q_pred_{a}_um"] - out.commands[a]
        assert abs(residual).max() < 0.2 and 0 < out.extra[f"q_sigma_{a}_um"].min()
    assert "q_pred_um" not in out.extra


def test_fit_json_per_axis_restamp_and_refusals(xy_files, tmp_path, capsys):
    tmp, _ = xy_files
    assert main(["fit", str(tmp / "cal.csv"), "--out", str(tmp_path / "m.json"), "--json", "--order", "3"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert list(doc["axes"]) == ["x", "y"] and doc["axes"]["y"]["equation"].startswith("q_y = ")
    assert doc["model"] == load_any_model(tmp_path / "m.json").id

    edited = json.loads((tmp_path / "m.json").read_text())
    edited["models"]["y"]["terms"][-1]["coef"] += 0.01  # a deliberate hand edit of y's bias
    (tmp_path / "m.json").write_text(json.dumps(edited))
    assert main(["predict", "--model", str(tmp_path / "m.json"), str(tmp / "cal.csv"), "--out",
                 str(tmp_path / "p.csv")]) == 2
    assert "models.y: its id" in capsys.readouterr().err and not (tmp_path / "p.csv").exists()
    assert main(["restamp", str(tmp_path / "m.json")]) == 0
    restamped = load_any_model(tmp_path / "m.json")  # loads with the id check
    assert restamped.id != doc["model"] and restamped.provenance["restamped_from"] == doc["model"]

    one_axis = tmp_path / "one.csv"
    one_axis.write_text("t_s,x_um,q_um,T1,T2,T3,T4\n0,0,0,22,22,22,22\n")
    assert main(["predict", "--model", str(tmp_path / "m.json"), str(one_axis), "--out", str(tmp_path / "p.csv")]) == 2
    assert "positions axes x (a one-axis file) but" in capsys.readouterr().err


def test_validate_a_multi_axis_model_on_the_simulated_cell(xy_files, tmp_path, capsys):
    tmp, _ = xy_files
    code = main(["validate", "--model", str(tmp / "m.json"), "--cycles", "4", "--report", str(tmp_path / "r")])
    assert code == 0
    out = capsys.readouterr().out
    for label in ("axis x", "axis y", "AP 2-D", "RP 2-D", "(x = 45, y = 435) µm"):
        assert label in out
    doc = json.loads((tmp_path / "r" / "validation.json").read_text())
    truth = doc["against_truth"]
    assert truth["improvement_ratio"] > 10 and len(truth["with"]["points"]) == 5
    assert (tmp_path / "r" / "fig_cell_accuracy.png").stat().st_size > 10_000
    # issue 27: the XY figure says where it came from and its text is as readable as fig9's and fig11's
    svg = (tmp_path / "r" / "fig_cell_accuracy.svg").read_text()
    assert 'id="provenance"' in svg and doc["model"] in svg and "seed" in svg
    sizes = [float(v) for v in re.findall(r"font-size: ([\d.]+)px", svg)]
    assert sizes and sorted(sizes)[1] >= 9.0, sorted(set(sizes))  # only the footer is smaller


def test_validate_a_multi_axis_model_over_several_tests_in_one_call(xy_files, tmp_path, capsys):
    tmp, _ = xy_files
    code = main(["validate", "--model", str(tmp / "m.json"), "--cycles", "2", "--scenario", "test2,test5", "--json",
                 "--report", str(tmp_path / "r")])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert [t["test"] for t in doc["tests"]] == ["test2", "test5"]
    assert all(t["model"] == doc["model"] for t in doc["tests"])
    assert sorted(p.name for p in (tmp_path / "r").iterdir()) == ["test2", "test5"]
    assert main(["validate", "--model", str(tmp / "m.json"), "--scenario", "test2,nope"]) == 2
    assert "nope" in capsys.readouterr().err


def test_simulate_refuses_effects_of_the_other_kind(tmp_path, capsys):
    assert main(["simulate", "--scenario", "train", "--axes", "xy", "--effects", "thermal_lag",
                 "--out", str(tmp_path / "a.csv")]) == 2
    assert "a one-axis effect" in capsys.readouterr().err
    assert main(["simulate", "--scenario", "train", "--effects", "crosstalk", "--out", str(tmp_path / "b.csv")]) == 2
    assert "need --axes xy or xyz" in capsys.readouterr().err
    assert not (tmp_path / "a.csv").exists() and not (tmp_path / "b.csv").exists()


#: one-axis outputs for ``simulate --scenario train --cycles 3 --seed 5``: simulate's CSV, fit's printout,
#: predict's CSV and printout. Made before the multi-axis work (commit 4d39ca7) and kept since (issue 19
#: changed the covariance block, so fit's σ and predict's ``q_sigma_um``, once, on purpose; issue 27 made fit's
#: printed SEs and p-values Newey-West HAC ones and added its "selection:" and "SE and p:" lines, on purpose;
#: then σ gained the calibration's wander, 25 -> 36 nm median, and fit its "thermal sensitivity" line, on purpose;
#: then the default selection became coherent, and the wander was cut to what varies within the calibration's
#: runs (this 0.4 h run: 36 -> 14 nm median σ, thermal sensitivity SE 0.92 -> 0.48 µm/°C), on purpose).
#: They are compared with tolerances (``helpers.floats``): a change of behaviour moves a number by far more than
#: the last bits another CPU or BLAS moves it by. The files hashed to the sha256 pins this test used to hold
#: (s.csv 4c7edb5d…, fit bb7aebec…, predict 9f54aaf9…) on the machine that made them.
ONE_AXIS_DATA = Path(__file__).parent / "data" / "one_axis_seed5"
ONE_AXIS_TERMS = [("x^3", 6.004324686877132e-09), ("x^2", -4.800048243020635e-06), ("x", 1.0004969286621292),
                  ("T1", 1.000974063898221), ("1", -22.06304784857551)]
#: the model id these outputs print: it hashes the fitted floats, so another machine's refit has another id;
#: the id of a model file the test writes is pinned in tests/bus/test_one_axis_unchanged.py
PINNED_MODEL_ID = "m-05e578fbc20d"
#: fitted coefficients: a refit on another machine moves them by ~1e-12 relative (seen: 8e-13 on x^3)
COEF_REL_TOL = 1e-6
#: a command's σ (see below)
SIGMA_REL_TOL = 1e-5


def test_one_axis_outputs_are_unchanged_within_float_tolerances(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["simulate", "--scenario", "train", "--cycles", "3", "--seed", "5", "--out", "s.csv"]) == 0
    capsys.readouterr()
    assert main(["fit", "s.csv", "--out", "m.json"]) == 0
    fit_out = capsys.readouterr().out
    assert main(["predict", "--model", "m.json", "s.csv", "--out", "p.csv"]) == 0
    predict_out = capsys.readouterr().out
    doc = json.loads((tmp_path / "m.json").read_text())
    assert [t["term"] for t in doc["terms"]] == [term for term, _ in ONE_AXIS_TERMS]
    for found, (term, coef) in zip(doc["terms"], ONE_AXIS_TERMS, strict=True):
        assert found["coef"] == pytest.approx(coef, rel=COEF_REL_TOL), term

    def same_model(text: str) -> str:
        return text.replace(doc["id"], PINNED_MODEL_ID)

    assert_same((tmp_path / "s.csv").read_text(), (ONE_AXIS_DATA / "s.csv").read_text())
    # q_sigma_um: its noise model is chosen by likelihood over a grid, which turns a 1e-11 change of a sum
    # into ~1e-7 of σ (seen when the sums were regrouped); a real change moves σ by percents
    assert_same((tmp_path / "p.csv").read_text(), (ONE_AXIS_DATA / "p.csv").read_text(), rel=SIGMA_REL_TOL)
    fresh, pinned = read_csv(tmp_path / "p.csv"), read_csv(ONE_AXIS_DATA / "p.csv")
    assert np.allclose(fresh.extra["q_pred_um"], pinned.extra["q_pred_um"], rtol=1e-9, atol=1e-12)
    assert_same(same_model(fit_out), (ONE_AXIS_DATA / "fit.txt").read_text(), rounded=True)
    assert_same(same_model(predict_out), (ONE_AXIS_DATA / "predict.txt").read_text(), rounded=True)
