"""Discovery on the simulated cell: each hidden effect, switched on with the simulator's DEFAULT
parameters, is named first with its parameter, the extended model predicts a fresh run (another seed,
never seen by discovery) better, and nothing is named when nothing is hidden.

Runs are the default calibration run (24 ``train`` cycles, up-and-down sweeps for ``hysteresis``),
except ``thermal_lag`` and ``unmonitored_drift``: in 24 cycles the room falls and rises once, and
what the thermocouples cannot explain of a 2 h lag is, to a correlation of 0.97, a straight line in
time, so the two look alike and the lag's time constant is not identifiable. 48 cycles (6.6 h, the
room settles) tell them apart; the 24-cycle run names nothing (the CLI test below).
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from helpers.discovery_helpers import cell_run, paper_model

from nanodrift.calibration.dataset import Dataset, concat, write_csv
from nanodrift.calibration.discovery import discover
from nanodrift.cli import main
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.effects import EFFECTS
from nanodrift.model.identify import candidate_terms, fit, fit_terms
from nanodrift.model.model import Model, load_model, save_model
from nanodrift.model.terms import Channel, ChannelSquare
from nanodrift.reports.discovery import METHOD_DOC


def rms(data: Dataset, model: Model) -> float:
    assert data.q is not None
    return float(np.sqrt(np.mean((data.q - model.predict(data)) ** 2)))


def default(effect: str, param: str) -> float:
    return EFFECTS[effect].defaults[param]


@dataclass(frozen=True)
class Case:
    cycles: int = 24
    bidirectional: bool = False
    seed: int = 1
    margin: float = 0.8  # the extended model's RMS on a fresh run is at most this fraction of the original's


CASES = {
    "thermal_lag": Case(cycles=48, margin=0.7),
    "temperature_rate": Case(margin=0.9),
    "hysteresis": Case(bidirectional=True, margin=0.6),
    "position_thermal_coupling": Case(margin=0.95),
    "creep": Case(margin=0.4),
    "unmonitored_drift": Case(cycles=48),
}


def test_every_effect_of_the_catalogue_has_an_acceptance_case() -> None:
    assert set(CASES) == set(EFFECTS)


def _run(effect: str, seed: int) -> Dataset:
    case = CASES[effect]
    return cell_run(effect, seed=seed, cycles=case.cycles, bidirectional=case.bidirectional)


@pytest.mark.parametrize("key", list(CASES))
def test_each_hidden_effect_is_named_first_and_the_fresh_run_improves(key: str) -> None:
    case = CASES[key]
    data = _run(key, case.seed)
    given = paper_model(data)
    result = discover(data, given)
    assert result.steps, f"nothing named for {key}: {result.summary}"
    first = result.steps[0]
    assert first.effect == key, result.summary
    assert first.p_value < 0.01 and first.holdout_gain >= 0.10
    assert [s.effect for s in result.steps] == [key], result.summary  # and nothing spurious after it
    params = first.params
    if key == "thermal_lag":
        assert params["tau_behind_fastest_s"] == pytest.approx(default(key, "tau_s"), rel=0.30)
        assert "alike" not in params  # 48 cycles: the lag no longer looks like a line in time
    elif key == "temperature_rate":
        # q compensates a drift of k * dT/dt (k < 0): positive coefficient, attenuated by the
        # thermocouple's noisy derivative, smoothing comparable to the cell's (tau_s behind the air)
        k = -default(key, "k_um_per_c_per_s")
        assert 0.2 * k < next(iter(params["coef"].values())) < 1.3 * k
        assert 30 < params["tau_s"] < 2 * default(key, "tau_s")
    elif key == "hysteresis":
        assert params["coef"]["dir"] == pytest.approx(default(key, "h_um") / 2, rel=0.30)
    elif key == "position_thermal_coupling":
        assert params["channel"] == "T1"  # the stage's own thermocouple
        assert -params["coef"]["x*T1"] == pytest.approx(default(key, "kappa_per_c"), rel=0.30)
    elif key == "creep":
        assert params["tau_s"] == pytest.approx(default(key, "tau_s"), rel=0.30)
    elif key == "unmonitored_drift":
        assert params["rate_um_per_h"] == pytest.approx(default(key, "rate_um_per_h"), rel=0.30)
        assert result.final["not_applied_online"] == ["unmonitored_drift"]
        assert "t" not in result.model.term_names()

    if key == "unmonitored_drift":
        # the daemon cannot predict a drift no sensor sees: what it gains is thermal coefficients free
        # of it, shown on a fresh run of the same cell once the drift's source is fixed
        fresh = cell_run("", seed=case.seed + 100, cycles=case.cycles)
        assert rms(fresh, result.model) < 0.5 * rms(fresh, given)
    else:
        fresh = _run(key, case.seed + 100)
        assert rms(fresh, result.model) < case.margin * rms(fresh, given)


@pytest.mark.parametrize("seed", [0, 2])
def test_a_lag_time_constant_is_recovered_on_more_seeds(seed: int) -> None:
    data = _run("thermal_lag", seed)
    result = discover(data, paper_model(data))
    assert result.steps[0].effect == "thermal_lag"
    assert result.steps[0].params["tau_behind_fastest_s"] == pytest.approx(default("thermal_lag", "tau_s"), rel=0.30)


@pytest.mark.parametrize("effect", ["creep", "hysteresis"])
def test_channels_an_effect_masked_are_readmitted_with_it_not_named_after_it(effect: str) -> None:
    """Seed 0: the large unexplained effect made the paper's stepwise leave T2 out of the given model.

    With the effect named, the model's own selection re-admits it in the same step; a second round
    then has nothing left to name (it used to "find" the missing bracket as a long lag).
    """
    data = _run(effect, 0)
    given = paper_model(data)
    assert "T2" not in given.term_names()
    result = discover(data, given)
    assert [s.effect for s in result.steps] == [effect], result.summary
    assert "T2" in result.steps[0].params["readmitted"]
    assert "T2" in result.model.term_names() and "re-admits" in result.summary
    assert result.final["holdout_rms_um"] < result.steps[0].holdout_rms_after_um


def test_a_missing_geometric_order_is_named() -> None:
    data = cell_run("", seed=3)
    given = fit(data, order=2).model
    result = discover(data, given)
    assert [s.effect for s in result.steps][:1] == ["geometric_order"], result.summary
    assert "x^3" in result.model.term_names()


@pytest.mark.parametrize("seed", [0, 4])
def test_a_channel_that_hurts_out_of_sample_is_excluded(seed: int) -> None:
    """The paper's hot plate: a channel that fits the training data by coincidence and hurts elsewhere.

    The hot plate is switched on five times; the first time the cell happens to move (a door opened),
    the other times nothing follows. In-sample it is highly significant (stepwise would keep it);
    held out it predicts moves that never come, in nearly every block.
    """
    data = cell_run("", seed=seed)
    rng = np.random.default_rng(seed)
    n = len(data)
    row = np.arange(n) / n
    on = [((row > start) & (row < start + 0.08)).astype(float) for start in (0.08, 0.25, 0.45, 0.62, 0.85)]
    data.channels["HP"] = np.round((22.0 + sum(on) + rng.normal(0, 0.005, n)) / 0.01) * 0.01
    assert data.q is not None
    data.q = data.q - 0.6 * on[0]  # the coincident disturbance
    terms = [*candidate_terms(["T1", "T2", "T3", "T4"], 3), Channel("HP")]
    given = fit_terms(data, terms, always=terms)
    result = discover(data, given)
    assert result.steps and result.steps[0].effect == "sensor_exclusion", result.summary
    assert result.steps[0].params["channel"] == "HP"
    assert "HP" not in result.model.term_names()


def test_two_hidden_effects_are_both_named_the_larger_first() -> None:
    data = cell_run("hysteresis:h_um=0.3,position_thermal_coupling:kappa_per_c=1e-3", seed=2, bidirectional=True)
    result = discover(data, paper_model(data))
    named = [s.effect for s in result.steps]
    assert named[:2] == ["hysteresis", "position_thermal_coupling"], result.summary
    assert result.steps[0].holdout_rms_after_um > result.steps[1].holdout_rms_after_um


def test_nothing_is_named_when_nothing_is_hidden() -> None:
    named = {}
    for seed in range(20):
        data = cell_run("", seed=seed)
        result = discover(data, paper_model(data))
        if result.steps:
            named[seed] = [s.effect for s in result.steps]
    assert named == {}


def test_cli_writes_model_report_and_contract_json(tmp_path, capsys) -> None:
    data = cell_run("creep:c=0.01,tau_s=15", seed=7)
    write_csv(data, tmp_path / "d.csv")
    save_model(paper_model(data), tmp_path / "m.json")
    code = main(["discover", str(tmp_path / "d.csv"), "--model", str(tmp_path / "m.json"),
                 "--out", str(tmp_path / "m2.json"), "--report", str(tmp_path / "rep"), "--json"])
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert set(doc) == {"baseline", "disagreements", "steps", "final", "model_out"}
    assert doc["model_out"] == str(tmp_path / "m2.json")
    step = doc["steps"][0]
    assert step["effect"] == "creep"
    for key in ("params", "p_value", "rms_before_um", "rms_after_um", "holdout_rms_before_um",
                "holdout_rms_after_um"):
        assert key in step
    assert step["holdout_rms_after_um"] < step["holdout_rms_before_um"]
    extended = load_model(tmp_path / "m2.json")
    assert any(name.startswith("creep(") for name in extended.term_names())
    assert extended.id == doc["final"]["model"]
    report = (tmp_path / "rep" / "report.md").read_text()
    assert "creep" in report
    assert f"`{METHOD_DOC}`" in report and (Path(__file__).parents[2] / METHOD_DOC).is_file()
    assert (tmp_path / "rep" / "gap.png").stat().st_size > 1000
    assert (tmp_path / "rep" / "residuals_vs_last_step.png").exists()
    # predict applies the discovered term like any other
    assert main(["predict", "--model", str(tmp_path / "m2.json"), str(tmp_path / "d.csv"),
                 "--out", str(tmp_path / "p.csv")]) == 0


def test_cli_names_what_is_wrong(tmp_path, capsys) -> None:
    data = cell_run("", seed=0, cycles=4)
    model = paper_model(data)
    save_model(model, tmp_path / "m.json")
    needed = model.channels[0]
    del data.channels[needed]
    write_csv(data, tmp_path / "d.csv")
    code = main(["discover", str(tmp_path / "d.csv"), "--model", str(tmp_path / "m.json"),
                 "--out", str(tmp_path / "m2.json")])
    assert code == 2
    assert needed in capsys.readouterr().err
    assert not (tmp_path / "m2.json").exists()


def test_cli_names_a_default_thermal_lag_from_simulate_fit_discover(tmp_path, capsys) -> None:
    """The user's story: the three commands with the simulator's defaults.

    In the default 24-cycle run the room falls and rises once: a lag of hours is not pinned (the run
    cannot tell τ from 2τ, nor the lag from a drift in time), and applying it made a fresh run 32 %
    worse on this seed (benchmarks/discovery_fresh.py). Discovery reports the disagreement and names
    nothing; 48 cycles (the room settles) name the lag and the extended model applies it.
    """
    data, model, extended = tmp_path / "d.csv", tmp_path / "m.json", tmp_path / "m2.json"
    assert main(["simulate", "--scenario", "train", "--effects", "thermal_lag", "--seed", "1",
                 "--out", str(data)]) == 0
    assert main(["fit", str(data), "--out", str(model)]) == 0
    capsys.readouterr()
    assert main(["discover", str(data), "--model", str(model), "--out", str(extended), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["steps"] == []
    assert any(d["variable"] == "t" and d["significant"] for d in doc["disagreements"]), doc["disagreements"]

    assert main(["simulate", "--scenario", "train", "--effects", "thermal_lag", "--seed", "1", "--cycles", "48",
                 "--out", str(data)]) == 0
    assert main(["fit", str(data), "--out", str(model)]) == 0
    capsys.readouterr()
    assert main(["discover", str(data), "--model", str(model), "--out", str(extended), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["effect"] for s in doc["steps"]] == ["thermal_lag"], doc["final"]["summary"]
    assert "alike" not in doc["steps"][0]["params"]
    assert any(name.startswith("lag(") for name in load_model(extended).term_names())


def test_a_bending_over_degrees_of_records_is_named_thermal_curvature() -> None:
    """Calibration plus a run 1.5 °C warmer, a model linear in temperature: the residual tracks the
    temperatures (the bracket's bending) and discovery names a channel's square for it."""
    data = concat([simulate_dataset("train", cycles=24, seed=3), simulate_dataset("test5", cycles=30, seed=305)])
    given = fit(data, squares=False).model  # the linear fit a lab had before the square was on offer
    result = discover(data, given)
    assert "thermal_curvature" in {c.effect for c in result.rounds[0].candidates}
    assert result.steps and result.steps[0].effect == "thermal_curvature", result.summary
    first = result.steps[0]
    assert first.p_value < 0.01 and first.holdout_gain >= 0.5
    assert any(isinstance(ft.term, ChannelSquare) for ft in result.model.terms), result.model.term_names()
    fresh = simulate_dataset("test5", cycles=30, seed=353)
    assert rms(fresh, result.model) < 0.6 * rms(fresh, given)


def test_thermal_curvature_is_not_proposed_on_a_calibration_narrower_than_a_degree() -> None:
    data = cell_run("", seed=3)
    result = discover(data, paper_model(data))
    tried = {c.effect for r in result.rounds for c in r.candidates}
    assert "missing_channel" in tried or "position_thermal_coupling" in tried  # the catalogue did run
    assert "thermal_curvature" not in tried
