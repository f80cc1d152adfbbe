"""``nanodrift fit`` and ``nanodrift predict`` as a user runs them."""

import json
import subprocess
import sys

import numpy as np
from synthetic import paper_run

from daemon.calibration.dataset import read_csv, write_csv
from daemon.cli import main
from daemon.model.model import load_model


def test_fit_then_predict_round_trip(tmp_path, capsys):
    data_path, model_path, pred_path = tmp_path / "cal.csv", tmp_path / "m.json", tmp_path / "p.csv"
    write_csv(paper_run(seed=3), data_path)
    assert main(["fit", str(data_path), "--out", str(model_path)]) == 0
    out = capsys.readouterr().out
    assert "geometric order n1 = 3" in out and "residual RMS" in out and "T1:" in out
    model = load_model(model_path)
    assert len(model.provenance["data_sha256"]) == 64

    fresh = tmp_path / "fresh.csv"
    write_csv(paper_run(seed=4, cycles=4), fresh)
    assert main(["predict", "--model", str(model_path), str(fresh), "--out", str(pred_path)]) == 0
    pred = read_csv(pred_path)
    assert "q_pred_um" in pred.extra
    assert np.sqrt(np.mean((pred.q - pred.extra["q_pred_um"]) ** 2)) < 0.025
    np.testing.assert_array_equal(pred.channels["T1"], read_csv(fresh).channels["T1"])


def test_fit_json_exclude_and_fixed_order(tmp_path, capsys):
    data_path = tmp_path / "cal.csv"
    write_csv(paper_run(seed=3), data_path)
    code = main(["fit", str(data_path), "--out", str(tmp_path / "m.json"), "--order", "2", "--exclude", "T4", "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["order"] == 2 and doc["excluded"] == ["T4"]
    assert "T4" not in [t["term"] for t in doc["terms"]]
    assert doc["fit"]["rows"] == 408


def test_errors_name_the_problem_and_write_nothing(tmp_path):
    bad = tmp_path / "bad.csv"
    bad.write_text("t_s,x_um,q_um,T1\n0,0,0,20\n1,30,30,oops\n")
    run = subprocess.run(
        [sys.executable, "-m", "daemon.cli", "fit", str(bad), "--out", str(tmp_path / "m.json")],
        capture_output=True, text=True,
    )
    assert run.returncode == 2
    assert "row 3, column T1" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "m.json").exists()

    run = subprocess.run(
        [sys.executable, "-m", "daemon.cli", "predict", "--model", str(tmp_path / "none.json"), str(bad),
         "--out", str(tmp_path / "p.csv")],
        capture_output=True, text=True,
    )
    assert run.returncode == 2 and "no such model file" in run.stderr
    assert not (tmp_path / "p.csv").exists()


def test_order_option_is_validated(tmp_path, capsys):
    data_path = tmp_path / "cal.csv"
    write_csv(paper_run(seed=3, cycles=3), data_path)
    assert main(["fit", str(data_path), "--out", str(tmp_path / "m.json"), "--order", "cubic"]) == 2
    assert "--order must be 'auto'" in capsys.readouterr().err
