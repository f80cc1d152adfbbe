"""The simulated cell's physics: magnitudes after the paper, exactness, effects, seeds, names."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.sim_helpers import rms, run_dataset
from scipy.signal import lfilter

from nanodrift.drivers.simulated.config import SimulationConfig
from nanodrift.drivers.simulated.effects import EFFECTS, UnknownNameError, resolve_effects
from nanodrift.drivers.simulated.physics import CellPhysics, CrossParams, StageState, first_order_filter
from nanodrift.drivers.simulated.scenarios import SCENARIOS, get_scenario


def test_drift_opposes_temperature_about_1_1_um_per_degc():
    physics = CellPhysics.create("train", seed=0)
    t = np.array([0.0, 1.6 * 3600, 2.2 * 3600])
    thermal = physics.thermal(t)
    drift = physics.drift(t)["x"]
    assert abs(drift[0]) < 0.03  # the interferometer was zeroed at the start of training
    d_temp = thermal["stage"][2] - thermal["stage"][0]
    assert d_temp < -0.25  # the room cooled
    assert drift[2] > 0  # drift grows as the temperature falls (paper Fig. 2)
    slope = drift[2] / ((thermal["stage"][2] + thermal["bracket"][2] + thermal["beam"][2]) / 3 - 22.0)
    assert -1.6 < slope < -0.8


def test_thermal_nodes_are_exact_lags_at_any_spacing():
    physics = CellPhysics.create("test5", seed=1)
    # RK4 integration of dy/dt = (u - y) / tau (u sampled every 0.25 s) against the closed form
    fine = np.arange(-3 * 3600.0, 1800.0 + 1e-9, 0.25)
    air = physics.thermal(fine)["air"]
    tau = physics.params.tau_stage_s
    y = float(air[0])
    dt = 0.5
    for k in range(0, fine.size - 2, 2):
        u0, um, u1 = air[k], air[k + 1], air[k + 2]
        k1 = (u0 - y) / tau
        k2 = (um - (y + dt / 2 * k1)) / tau
        k3 = (um - (y + dt / 2 * k2)) / tau
        k4 = (u1 - (y + dt * k3)) / tau
        y += dt / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
    assert y == pytest.approx(physics.thermal(np.array([fine[-1]]))["stage"][0], abs=1e-6)
    # arbitrary query times: vector path == scalar path == sparse grid
    sparse = np.array([-1000.0, 17.3, 1234.567])
    vec = physics.thermal(sparse)
    for i, ti in enumerate(sparse):
        one = physics.thermal1(float(ti))
        for node in ("stage", "bracket", "t3", "t4", "beam", "air"):
            assert one[node] == pytest.approx(vec[node][i], abs=1e-12)


@pytest.mark.parametrize(("axes", "effects"), [("x", "creep,hysteresis,position_thermal_coupling,thermal_lag"),
                                              ("xyz", None)])
def test_scalar_and_vector_positions_agree(axes: str, effects: str | None) -> None:
    """The stepped cell's path (floats) and the vectorised run's (arrays) are one computation, for one axis
    with the hidden effects and for a stack with its cross-axis effects."""
    physics = CellPhysics.create("train", effects, seed=2, axes=axes)
    states = {a: physics.after_command(StageState(), 100.0, 240.0 - 90.0 * k, 0.001) for k, a in enumerate(axes)}
    tracks = {a: {name: np.array([value]) for name, value in vars(s).items()} for a, s in states.items()}
    for t in (100.5, 130.0, 4000.0):
        vec = physics.attained_along(np.array([t]), tracks)
        now = physics.attained_now(t, states)
        for a in axes:
            assert now[a] == pytest.approx(vec[a][0], abs=1e-12)
    if len(axes) > 1:  # the stack's cross-axis effects are in both: x moves with y and z
        alone = CellPhysics.create("train", seed=2, axes=axes, cross=CrossParams(0.0, 0.0, 0.0))
        assert abs(alone.attained_now(4000.0, states)["x"] - physics.attained_now(4000.0, states)["x"]) > 0.3


def test_noise_and_quantisation_after_the_paper():
    physics = CellPhysics.create("steady", seed=3)
    rng = np.random.default_rng(0)
    t = np.full(20000, 100.0)
    readings = physics.measure_position("x", t, np.zeros_like(t), rng.normal(size=t.size))
    assert np.std(readings) == pytest.approx(0.020, rel=0.05)  # ~20 nm white per sample
    temps = physics.measure_temperature("T1", np.full(1000, 22.003), rng.normal(size=1000))
    assert np.allclose(np.round(temps * 100), temps * 100)  # 0.01 degC steps
    assert abs(temps.mean() - 22.003) < 0.002  # noise dithers the quantisation


def test_same_seed_same_run_other_seed_differs():
    a, b, c = (run_dataset(seed=s, cycles=2) for s in (7, 7, 8))
    assert np.array_equal(a.x, b.x) and np.array_equal(a.channels["T3"], b.channels["T3"])
    assert not np.array_equal(a.x, c.x)


@pytest.mark.parametrize("effect", sorted(EFFECTS))
def test_each_effect_changes_only_the_position_and_only_when_on(effect):
    kwargs = {"bidirectional": effect == "hysteresis"}
    base = run_dataset(seed=5, cycles=24, **kwargs)
    on = run_dataset(effects=effect, seed=5, cycles=24, **kwargs)
    for ch in base.channels:  # effects are hidden: no thermocouple sees them
        assert np.array_equal(base.channels[ch], on.channels[ch])
    delta = on.x - base.x
    assert rms(delta) > 0.04, f"{effect} should be clearly visible, got {rms(delta) * 1e3:.1f} nm RMS"
    assert rms(delta) < 1.0, f"{effect} should not be absurd, got {rms(delta):.2f} um RMS"
    # zero magnitude == off, exactly
    zero = {"thermal_lag": "k_um_per_c", "hysteresis": "h_um", "position_thermal_coupling": "kappa_per_c",
            "creep": "c", "temperature_rate": "k_um_per_c_per_s", "unmonitored_drift": "rate_um_per_h"}[effect]
    spec = f"{effect}:{zero}=0" + (",walk_um_per_sqrt_h=0" if effect == "unmonitored_drift" else "")
    off = run_dataset(effects=spec, seed=5, cycles=24, **kwargs)
    assert np.allclose(off.x, base.x, atol=1e-12)


def test_effects_have_their_documented_shape():
    base = run_dataset(seed=6, cycles=24)
    x = base.x
    # position_thermal_coupling scales with x (and with the stage temperature change)
    d = run_dataset(effects="position_thermal_coupling", seed=6).x - x
    assert rms(d[base.q > 400]) > 5 * rms(d[base.q < 50])
    # unmonitored drift grows with time
    d = run_dataset(effects="unmonitored_drift:walk_um_per_sqrt_h=0", seed=6).x - x
    rate = EFFECTS["unmonitored_drift"].defaults["rate_um_per_h"]
    assert d[-1] == pytest.approx(rate * base.t[-1] / 3600, rel=0.05)
    # creep shows most after the big return step to 0, far less after 30 um steps
    d = run_dataset(effects="creep", seed=6).x - x
    assert np.mean(d[base.q == 0][1:]) > 0.3 and np.mean(d[base.q == 0][1:]) > 10 * abs(np.median(d[base.q > 0]))
    # hysteresis: approach from below lands h lower than from above
    both = run_dataset(seed=6, bidirectional=True)
    d = run_dataset(effects="hysteresis:h_um=0.2", seed=6, bidirectional=True).x - both.x
    assert np.allclose(np.abs(d), 0.1, atol=1e-3) and (d > 0).any() and (d < 0).any()
    # thermal lag: proportional to the hidden node's excursion
    d = run_dataset(effects="thermal_lag:k_um_per_c=-1", seed=6).x - x
    assert d.max() > 0.15 and d.min() > -0.05  # the room cooled: a colder hidden part pushes +


def test_unknown_names_list_the_valid_ones():
    with pytest.raises(UnknownNameError, match="valid scenarios: steady, train"):
        get_scenario("tarin")
    with pytest.raises(UnknownNameError, match="valid effects: thermal_lag, hysteresis"):
        resolve_effects("thermal_lag,hysterisis")
    with pytest.raises(UnknownNameError, match="its parameters: tau_s, k_um_per_c"):
        resolve_effects({"thermal_lag": {"tau": 3}})
    with pytest.raises(ValueError, match="valid scenarios"):
        SimulationConfig(scenario="nope")
    with pytest.raises(ValueError, match="extra"):
        SimulationConfig.model_validate({"scenaro": "train"})


def test_effect_spec_forms_agree():
    cli = resolve_effects("thermal_lag:tau_s=1800,k_um_per_c=-0.5,hysteresis")
    table = resolve_effects({"thermal_lag": {"tau_s": 1800, "k_um_per_c": -0.5}, "hysteresis": {}})
    assert cli == table == {"thermal_lag": {"tau_s": 1800.0, "k_um_per_c": -0.5},
                            "hysteresis": {"h_um": 0.15, "deadband_um": 0.5}}
    assert resolve_effects(["creep", "hysteresis:h_um=0.3"])["hysteresis"]["h_um"] == 0.3


def test_test5_leaves_the_training_range_and_tests_1_4_stay_in_it():
    train = CellPhysics.create("train").thermal(np.arange(0, 24 * 17 * 29, 60.0))["t4"]
    for name in ("test1", "test2", "test3", "test4"):
        t4 = CellPhysics.create(name).thermal(np.arange(0, 6090, 60.0))["t4"]
        assert train.min() - 0.02 < t4.min() and t4.max() < train.max(), name
    t5 = CellPhysics.create("test5").thermal(np.arange(0, 6090, 60.0))["t4"]
    assert t5.max() - train.max() > 0.7 and t5.max() - t5.min() == pytest.approx(0.7, abs=0.1)
    assert set(SCENARIOS) >= {"train", "test1", "test2", "test3", "test4", "test5", "bidirectional", "steady"}


def test_the_first_order_filter_is_scipys_lfilter_bit_for_bit() -> None:
    """The simulator's recursion replaces ``scipy.signal.lfilter`` (a second of import in every simulated run):
    the same operations in the same order, so every simulated series, the shipped sample data included, is
    unchanged to the bit."""
    rng = np.random.default_rng(1)
    for _ in range(50):
        x = rng.normal(0.0, rng.uniform(0.01, 100.0), int(rng.integers(1, 800)))
        b0, b1, z0 = rng.normal(size=3)
        a = rng.uniform(-0.999, 0.999)
        assert np.array_equal(first_order_filter(b0, b1, -a, x, z0), lfilter([b0, b1], [1.0, -a], x, zi=[z0])[0])
        assert np.array_equal(first_order_filter(1.0, 0.0, -a, x, z0), lfilter([1.0], [1.0, -a], x, zi=[z0])[0])
