"""The discovered terms: names round-trip, streaming equals batch, the daemon's evaluator equals predict."""

from __future__ import annotations

import math

import numpy as np
import pytest
from helpers.discovery_helpers import cell_run

from nanodrift.model.effect_terms import Creep, PositionCoupling, Rate
from nanodrift.model.model import FittedTerm, Model, Training, load_model, save_model
from nanodrift.model.terms import Bias, Channel, Direction, Lag, Power, UnknownTermError, parse_term


@pytest.mark.parametrize(
    "name", ["x*T1", "rate(T4, 300 s)", "rate(T4, 88.9 s)", "creep(15.3 s)", "creep(15 s, 1 um)"]
)
def test_names_round_trip(name: str) -> None:
    assert parse_term(name).name == name


def test_bad_names_are_refused() -> None:
    with pytest.raises(UnknownTermError):
        parse_term("rate(T4)")
    with pytest.raises(ValueError, match="> 0"):
        parse_term("creep(0 s)")


def _irregular_series(n: int = 400, seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(0.5, 40.0, n))
    x = np.round(rng.uniform(0, 480, n) / 30) * 30 + rng.normal(0, 0.01, n)
    x[10:20] = x[9] + rng.normal(0, 0.05, 10)  # held still: steps inside the deadband
    temps = {"T1": 22 + np.cumsum(rng.normal(0, 0.01, n)), "T4": 21 + np.cumsum(rng.normal(0, 0.02, n))}
    return t, x, temps


@pytest.mark.parametrize("term", [PositionCoupling("T1"), Rate("T4", 300.0), Creep(15.0), Creep(120.0, 2.0)])
def test_stream_equals_batch_on_irregular_samples(term) -> None:
    t, x, temps = _irregular_series()
    batch = term.batch(t, x, temps)
    stream = term.stream()
    online = []
    for k in range(t.size):
        stream.observe(float(t[k]), {c: float(v[k]) for c, v in temps.items()})
        online.append(stream.value(float(t[k]), float(x[k])))
        stream.moved(float(t[k]), float(x[k]))
    scale = max(1.0, float(np.abs(batch).max()))
    np.testing.assert_allclose(online, batch, rtol=0, atol=1e-12 * scale)


def test_creep_is_the_decayed_sum_of_the_steps() -> None:
    t = np.array([0.0, 10.0, 20.0, 50.0])
    x = np.array([0.0, 30.0, 30.2, 0.0])  # the 0.2 um move is inside the 0.5 um deadband
    feature = Creep(10.0).batch(t, x, {})
    expected = [0.0, 30.0, 30.0 * math.exp(-1.0), 30.0 * math.exp(-4.0) - 30.2]
    np.testing.assert_allclose(feature, expected, atol=1e-12)


def test_rate_of_a_ramp_is_its_slope() -> None:
    t = np.arange(0.0, 20000.0, 1.0)
    u = 20.0 + 1e-4 * t
    rate = Rate("T4", 300.0).batch(t, t * 0, {"T4": u})
    assert rate[-1] == pytest.approx(1e-4, rel=2e-3)  # the exact discretisation lags by ~dt/2


def test_daemon_evaluator_reproduces_predict_with_every_new_term(tmp_path) -> None:
    """A recorded run fed sample by sample (as the daemon does) gives predict's q to 1e-9 um."""
    data = cell_run("creep,hysteresis", seed=5, cycles=6, bidirectional=True)
    terms = [Power(3), Power(2), Power(1), Channel("T1"), Channel("T2"), Lag("T4", 2100.0), Direction(),
             PositionCoupling("T1"), Rate("T3", 150.0), Creep(15.3)]
    coefs = [3e-9, -4e-6, 1.001, -0.4, -0.5, -0.8, 0.075, -2e-3, 3000.0, 0.002]
    fitted = [FittedTerm(term, coef) for term, coef in zip(terms, coefs, strict=True)] + [FittedTerm(Bias(), 21.0)]
    model = Model(fitted, Training.of(data, ["T1", "T2", "T3", "T4"]))
    save_model(model, tmp_path / "m.json")
    model = load_model(tmp_path / "m.json")  # what the daemon would load
    batch = model.predict(data)
    evaluator = model.evaluator()
    online = np.empty(len(data))
    for k in range(len(data)):
        evaluator.observe(float(data.t[k]), {c: float(v[k]) for c, v in data.channels.items()})
        online[k] = evaluator.command(float(data.x[k]), float(data.t[k]))
    assert np.max(np.abs(online - batch)) < 1e-9
