"""Discovery on the simulated cell: each hidden effect, switched on with the simulator's DEFAULT
parameters, is named first with its parameter, the extended model predicts a fresh run (another seed,
never seen by discovery) better, and nothing is named when nothing is hidden.

Runs are the default calibration run (24 ``train`` cycles, up-and-down sweeps for ``hysteresis``),
except ``thermal_lag`` and ``unmonitored_drift``: in 24 cycles the room falls and rises once, and
what the thermocouples cannot explain of a 2 h lag is, to a correlation of 0.97, a straight line in
time, so the two look alike and the lag's time constant is not identifiable. 48 cycles (6.6 h, the
room settles) tell them apart; the 24-cycle run names nothing (the CLI test in
test_discovery_beyond_effects.py, with the rest of discovery's tests).
"""

from __future__ import annotations

from dataclasses import dataclass

import pytest
from helpers.discovery_helpers import cell_run, paper_model, rms

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.discovery import discover
from nanodrift.drivers.simulated.effects import EFFECTS


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
