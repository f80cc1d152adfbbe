"""``nanodrift fit`` and ``nanodrift predict`` as a user runs them."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from helpers.synthetic import paper_run

from nanodrift.calibration.dataset import read_csv, write_csv
from nanodrift.cli import main
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.model.model import load_model


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
        [sys.executable, "-m", "nanodrift.cli", "fit", str(bad), "--out", str(tmp_path / "m.json")],
        capture_output=True, text=True,
    )
    assert run.returncode == 2
    assert "row 3, column T1" in run.stderr and "Traceback" not in run.stderr
    assert not (tmp_path / "m.json").exists()

    run = subprocess.run(
        [sys.executable, "-m", "nanodrift.cli", "predict", "--model", str(tmp_path / "none.json"), str(bad),
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


def test_fit_prints_the_equation_and_json_carries_the_same_in_nm(tmp_path, capsys):
    data_path = tmp_path / "cal.csv"
    write_csv(paper_run(seed=3, cycles=8), data_path)
    assert main(["fit", str(data_path), "--out", str(tmp_path / "m.json"), "--order", "3"]) == 0
    human = capsys.readouterr().out
    equation_line = next(line for line in human.splitlines() if line.startswith("q = "))
    assert "·x³" in equation_line and "+ -" not in equation_line and "*" not in equation_line
    assert "not selected: T3" in human

    assert main(["fit", str(data_path), "--out", str(tmp_path / "m2.json"), "--order", "3", "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["equation"] == equation_line
    assert [entry["term"] for entry in doc["not_selected"]] == ["T3"]
    assert doc["not_selected"][0]["p_if_added"] > 0.05
    model = load_model(tmp_path / "m2.json")
    assert doc["residual_rms_nm"] == model.fit["residual_rms_nm"] and doc["rows"] == 8 * 17
    assert doc["rmse_nm"] == model.fit["rmse_um"] * 1000.0  # every RMS in nm, in a key that says so
    assert doc["order_holdout_rms_nm"] == {} and doc["order_choice"] == "fixed"  # fixed order: nothing tried

    def keys(node: object) -> list[str]:  # every key at any depth
        if isinstance(node, dict):
            return [k for k, v in node.items() for k in [k, *keys(v)]]
        return [k for v in node for k in keys(v)] if isinstance(node, list) else []

    rms_keys = [k for k in keys(doc) if re.search(r"(^|_)rmse?_", k)]
    assert {"residual_rms_nm", "rmse_nm", "order_holdout_rms_nm"} <= set(rms_keys)
    assert all(k.endswith("_nm") for k in rms_keys), rms_keys  # one unit per quantity: no µm duplicate
    assert doc["fit"] == {"rmse_nm": doc["rmse_nm"], "r2": model.fit["r2"], "dof": model.fit["dof"],
                          "se_method": model.fit["se_method"], "hac_lag": model.fit["hac_lag"],
                          "iid": model.fit["iid"], "rows": 8 * 17, "residual_rms_nm": doc["residual_rms_nm"],
                          "thermal_sensitivity": model.fit["thermal_sensitivity"]}
    # the SEs printed are HAC ones, and both the printout and the JSON say so
    assert doc["se_method"] == model.fit["se_method"] and doc["se_method"].startswith("Newey-West HAC, Bartlett")
    assert f"SE and p: {doc['se_method']}" in human
    assert doc["selection"] == "coherent" and doc["terms"][0]["se"] == model.terms[0].se  # the default mode


def test_fit_json_order_scores_in_nm(tmp_path, capsys):
    data_path = tmp_path / "cal.csv"
    write_csv(paper_run(seed=3, cycles=6), data_path)
    assert main(["fit", str(data_path), "--out", str(tmp_path / "m.json"), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc["order_holdout_rms_nm"]) == {"1", "2", "3", "4", "5"}
    assert "order_holdout_rms_um" not in doc
    for n, um in load_model(tmp_path / "m.json").selection["order_holdout_rms_um"].items():
        assert doc["order_holdout_rms_nm"][n] == um * 1000.0
    assert doc["holdout_rms_nm"] == doc["order_holdout_rms_nm"][str(doc["order"])]
    held_um = load_model(tmp_path / "m.json").fit["holdout_rms_um"]
    assert doc["fit"]["holdout_rms_nm"] == doc["holdout_rms_nm"] == pytest.approx(held_um * 1000.0)
    assert not [k for k in doc["fit"] if k.endswith("_um")]


def test_predict_says_what_it_did(tmp_path, capsys):
    data_path, model_path, pred_path = tmp_path / "cal.csv", tmp_path / "m.json", tmp_path / "p.csv"
    write_csv(paper_run(seed=3, cycles=6), data_path)
    assert main(["fit", str(data_path), "--out", str(model_path), "--order", "3"]) == 0
    capsys.readouterr()
    model = load_model(model_path)

    assert main(["predict", "--model", str(model_path), str(data_path), "--out", str(pred_path)]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert f"{6 * 17} rows" in line and model.id in line and str(pred_path) in line and "none extrapolating" in line

    warm = paper_run(seed=3, cycles=6)  # the training data itself, but ...
    warm.channels["T1"][:5] += 5.0  # five rows far above the training range of T1
    warm_path = tmp_path / "warm.csv"
    write_csv(warm, warm_path)
    assert main(["predict", "--model", str(model_path), str(warm_path), "--out", str(pred_path)]) == 0
    (line,) = capsys.readouterr().out.splitlines()
    assert "5 extrapolating" in line and "T1 in 5" in line



def test_predict_adds_the_uncertainty_of_each_command(tmp_path, capsys):
    data_path, model_path, pred_path = tmp_path / "cal.csv", tmp_path / "m.json", tmp_path / "p.csv"
    write_csv(paper_run(seed=3), data_path)
    assert main(["fit", str(data_path), "--out", str(model_path)]) == 0
    model = load_model(model_path)
    hot = paper_run(seed=4, cycles=4)
    hot.channels = {c: v + 1.0 for c, v in hot.channels.items()}  # 1 degC above the training range
    sigma = {}
    for name, data in (("fresh.csv", paper_run(seed=4, cycles=4)), ("hot.csv", hot)):
        write_csv(data, tmp_path / name)
        assert main(["predict", "--model", str(model_path), str(tmp_path / name), "--out", str(pred_path)]) == 0
        assert "q_sigma_um (median" in capsys.readouterr().out
        pred = read_csv(pred_path)
        assert "q_sigma_um" not in pred.channels
        np.testing.assert_allclose(pred.extra["q_sigma_um"], model.q_sigma(read_csv(tmp_path / name)), rtol=1e-9)
        sigma[name] = pred.extra["q_sigma_um"]
        if name == "fresh.csv":  # white noise of 20 nm: about that, and it covers the errors
            assert 0.015 < np.median(sigma[name]) < 0.04
            # the errors of recorded commands carry what the block keeps apart as the instrument's wander
            assert model.covariance is not None and model.covariance.wander_um is not None
            measured_sigma = np.hypot(sigma[name], model.covariance.wander_um)
            assert np.mean(np.abs(pred.q - pred.extra["q_pred_um"]) <= 2 * measured_sigma) > 0.9
    assert np.median(sigma["hot.csv"]) > 1.5 * np.max(sigma["fresh.csv"])


def test_keep_forces_a_term_the_stepwise_would_leave_out_and_refuses_what_it_cannot_fit(tmp_path, capsys):
    data = tmp_path / "d.csv"
    write_csv(paper_run(cycles=8, seed=2), data)  # T3 has no part in the true model: the stepwise leaves it out
    assert main(["fit", str(data), "--out", str(tmp_path / "m.json")]) == 0
    assert "T3" not in load_model(tmp_path / "m.json").term_names()
    capsys.readouterr()
    assert main(["fit", str(data), "--out", str(tmp_path / "k.json"), "--keep", "T3", "--keep", "x^3"]) == 0
    out = capsys.readouterr().out
    kept = load_model(tmp_path / "k.json")
    assert {"T3", "x^3"} <= set(kept.term_names()) and kept.selection["forced"] == ["T3", "x^3"]
    assert "kept whatever the stepwise says (--keep): T3, x^3" in out
    for bad, said in ((["--keep", "T9"], "--keep T9: reads channel T9"), (["--keep", "x^99"], "--keep x^99: power"),
                      (["--keep", "T3", "--exclude", "T3"], "--keep T3: reads channel T3"),
                      (["--keep", "lag(T1,1e300s)"], "--keep lag(T1,1e300s): lag time constant 1e+300 s is outside "
                                                      "[0.1, 1e+06] s")):
        assert main(["fit", str(data), "--out", str(tmp_path / "no.json"), *bad]) == 2
        assert said in capsys.readouterr().err
        assert not (tmp_path / "no.json").exists()


def test_fit_offers_a_square_over_a_warm_run_and_no_squares_keeps_eq3_linear(tmp_path, capsys):
    """A calibration plus a run 1.5 °C warmer, as two files: `fit` keeps a channel's square and prints it
    in the equation; `--no-squares` fits eq. 3 linear in temperature, with no square even offered."""
    calibration, warm = tmp_path / "calibration.csv", tmp_path / "warm.csv"
    write_csv(simulate_dataset("train", cycles=24, seed=3), calibration)
    write_csv(simulate_dataset("test5", cycles=30, seed=305), warm)
    assert main(["fit", str(calibration), str(warm), "--out", str(tmp_path / "curved.json")]) == 0
    out = capsys.readouterr().out
    curved = load_model(tmp_path / "curved.json")
    squares = [n for n in curved.term_names() if re.fullmatch(r"\(T\d - [\d.]+\)\^2", n)]
    assert squares, curved.term_names()
    assert re.search(r"·\(T\d − [\d.]+\)²", out), out  # the equation prints the square
    assert main(["fit", str(calibration), str(warm), "--out", str(tmp_path / "linear.json"), "--no-squares"]) == 0
    linear = load_model(tmp_path / "linear.json")
    assert not [n for n in linear.selection["candidates"] if n.endswith(")^2")]
    assert main(["fit", str(calibration), "--out", str(tmp_path / "cal.json")]) == 0  # 0.45 °C: none offered
    assert not [n for n in load_model(tmp_path / "cal.json").selection["candidates"] if n.endswith(")^2")]


def test_fit_selection_hac_uses_hac_tests_and_says_so(tmp_path, capsys):
    """``--selection hac``: the stepwise's own tests are HAC Wald tests (their p-values, in the history, are
    larger than the paper's iid ones for the same first entries), and printout and file name the mode."""
    data_path = tmp_path / "cal.csv"
    write_csv(simulate_dataset("train", seed=4), data_path)
    for mode in ("paper", "hac"):
        assert main(["fit", str(data_path), "--out", str(tmp_path / f"{mode}.json"), "--order", "3",
                     "--selection", mode]) == 0
        assert f"selection: {mode}: " in capsys.readouterr().out
    paper, hac = (load_model(tmp_path / f"{m}.json") for m in ("paper", "hac"))
    assert paper.selection["mode"] == "paper" and hac.selection["mode"] == "hac"
    first_paper, first_hac = paper.selection["history"][1], hac.selection["history"][1]
    assert first_paper["term"] == first_hac["term"]  # the same first channel enters...
    assert first_hac["p"] > 1e6 * first_paper["p"]  # ...judged far less certain under autocorrelation
    with pytest.raises(SystemExit):
        main(["fit", str(data_path), "--out", str(tmp_path / "x.json"), "--selection", "matlab"])
    assert "invalid choice: 'matlab'" in capsys.readouterr().err
