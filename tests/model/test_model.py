"""Terms, the model file and the streaming evaluator: batch and streaming agree; bad files refused."""

import json
import math

import numpy as np
import pytest
from helpers.synthetic import paper_run

from nanodrift.model.identify import fit
from nanodrift.model.model import (
    FittedTerm,
    MissingChannelError,
    Model,
    ModelFileError,
    Training,
    load_model,
    save_model,
)
from nanodrift.model.terms import Bias, Channel, Direction, Lag, Power, UnknownTermError, lag_filter, parse_term


def stream_rows(model: Model, data) -> np.ndarray:
    ev = model.evaluator()
    names = list(data.channels)
    out = np.empty(len(data.t))
    for k in range(len(data.t)):
        ev.observe(float(data.t[k]), {c: float(data.channels[c][k]) for c in names})
        out[k] = ev.command(float(data.x[k]), float(data.t[k]))
    return out


def model_of(terms: dict[str, float], channels=("T1", "T4")) -> Model:
    return Model(
        terms=[FittedTerm(parse_term(n), c) for n, c in terms.items()],
        training=Training((0.0, 480.0), {c: (19.0, 21.0) for c in channels}, 10, 100.0),
    )


@pytest.mark.parametrize(
    "name", ["x", "x^2", "x^3", "1", "T1", "stage.top", "lag(T4, 2100 s)", "lag(T4, 0.5 s)", "dir", "(T2 - 22.05)^2",
             "(T2 + 5)^2", "(stage.top - 0.125)^2"]
)
def test_term_names_round_trip(name):
    assert parse_term(name).name == name


@pytest.mark.parametrize("name", ["x^0", "y^2", "lag(T4)", "lag(T4, -5 s)", "lag(T4, 0 s)", "sin(T1)", "", "T 1",
                                  "(T2 - 22)^3", "(T2 - nan)^2", "(T2 - inf)^2", "(T2 22)^2", "T2^2"])
def test_unknown_or_invalid_term_names_are_refused(name):
    with pytest.raises((UnknownTermError, ValueError)):
        parse_term(name)


def test_lag_matches_its_recurrence_on_irregular_and_long_series():
    rng = np.random.default_rng(0)
    t = np.cumsum(rng.uniform(0.1, 50.0, 5000))
    u = 20 + np.cumsum(rng.normal(0, 0.01, 5000))
    tau = 300.0  # the series spans ~400 tau: exercises the chunked closed form
    y = lag_filter(t, u, tau)
    ref = np.empty_like(u)
    ref[0] = u[0]
    for k in range(1, u.size):
        ref[k] = ref[k - 1] + (1 - math.exp(-(t[k] - t[k - 1]) / tau)) * (u[k] - ref[k - 1])
    np.testing.assert_allclose(y, ref, rtol=0, atol=1e-11)


def test_lag_step_response_reaches_63_percent_after_tau():
    t = np.arange(0.0, 10000.0, 1.0)
    u = np.where(t > 0, 1.0, 0.0)
    y = lag_filter(t, u, 2100.0)
    assert abs(y[2100] - (1 - math.exp(-1))) < 1e-3


def test_direction_tracks_last_step_beyond_deadband():
    x = np.array([0, 30, 60, 60.2, 59.9, 30, 30.3, 0, 80])
    np.testing.assert_array_equal(Direction().batch(np.arange(9.0), x, {}), [1, 1, 1, 1, 1, -1, -1, -1, 1])


def test_streaming_equals_predict_for_every_term_kind():
    data = paper_run(cycles=6, seed=4)
    rng = np.random.default_rng(1)
    data.t = data.t + np.cumsum(rng.uniform(0, 3, len(data.t)))  # irregular sampling
    data.x = data.x[rng.permutation(len(data.x))]  # moves up and down
    model = model_of(
        {"x^3": 3e-9, "x^2": -4e-6, "x": 1.001, "T1": -0.6, "lag(T4, 2100 s)": -0.8, "lag(T1, 40 s)": 0.1,
         "dir": 0.07, "(T4 - 19.9)^2": 0.4, "1": 21.0}
    )
    batch = model.predict(data)
    assert np.max(np.abs(stream_rows(model, data) - batch)) < 1e-9


def test_evaluator_observes_channels_separately_and_reports_readiness():
    model = model_of({"x": 1.0, "T1": -0.5, "T4": 0.25, "1": 0.0})
    ev = model.evaluator()
    assert not ev.ready
    ev.observe(0.0, {"T1": 20.0})
    assert not ev.ready and math.isnan(ev.command(10.0, 0.0))
    ev.observe(0.5, {"T4": 22.0})
    assert ev.ready
    assert ev.command(10.0, 1.0) == pytest.approx(10.0 - 10.0 + 5.5)


def test_model_file_round_trip_keeps_everything(tmp_path):
    result = fit(paper_run(seed=1), order=3)
    path = tmp_path / "m.json"
    save_model(result.model, path)
    loaded = load_model(path)
    assert loaded.id == result.model.id
    assert loaded.term_names() == result.model.term_names()
    np.testing.assert_array_equal(loaded.coefs, result.model.coefs)
    assert loaded.training == result.model.training
    doc = json.loads(path.read_text())
    assert doc["format"] == "nanodrift-model/1"
    assert set(doc["training"]["channels"]) == set(loaded.channels)
    assert doc["selection"]["method"] == "stepwise" and doc["selection"]["history"]
    assert all(isinstance(t["se"], float) for t in doc["terms"])


def broken(doc: dict, change) -> dict:
    doc = json.loads(json.dumps(doc))
    change(doc)
    return doc


@pytest.mark.parametrize(
    ("change", "fragment"),
    [
        (lambda d: d.update(format="nanodrift-model/9"), "format is 'nanodrift-model/9'"),
        (lambda d: d["terms"].append({"term": "sin(T1)", "coef": 1.0}), "unknown term 'sin(T1)'"),
        (lambda d: d["terms"][0].update(coef="1.0"), "'coef' must be a finite number"),
        (lambda d: d["terms"][0].update(coef=None), "'coef' must be a finite number"),
        (lambda d: d.update(terms=[]), "non-empty list"),
        (lambda d: d["training"]["channels"].pop("T1"), "training ranges missing for channel(s) T1"),
        (lambda d: d["training"].update(x_um=[5, 1]), "training range of x_um"),
        (lambda d: d.update(channels=["T9"]), "does not match the channels"),
        (lambda d: d["terms"].append(dict(d["terms"][0])), "duplicate terms"),
    ],
)
def test_corrupt_model_files_are_refused_clearly(tmp_path, change, fragment):
    good = model_of({"x": 1.0, "T1": -0.5, "T4": 0.2, "1": 3.0}).to_dict()
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(broken(good, change)))
    with pytest.raises(ModelFileError) as info:
        load_model(path)
    assert str(path) in str(info.value) and fragment in str(info.value)


def test_truncated_and_missing_model_files(tmp_path):
    path = tmp_path / "m.json"
    path.write_text('{"format": "nanodrift-model/1", "terms": [')
    with pytest.raises(ModelFileError, match="not valid JSON"):
        load_model(path)
    with pytest.raises(ModelFileError, match="no such model file"):
        load_model(tmp_path / "none.json")


def test_predict_refuses_data_lacking_a_channel():
    model = model_of({"x": 1.0, "T1": -0.5, "T4": 0.2, "1": 3.0})
    data = paper_run(cycles=1)
    del data.channels["T4"]
    with pytest.raises(MissingChannelError, match="lacks channel\\(s\\) T4"):
        model.predict(data)


def test_out_of_range_flags_extrapolation():
    model = model_of({"x": 1.0, "T1": -0.5, "T4": 0.2, "1": 3.0})
    assert model.out_of_range(240.0, {"T1": 20.0, "T4": 20.5}) == []
    assert model.out_of_range(490.0, {"T1": 21.7, "T4": 20.5}) == ["x", "T1"]


def test_builtin_terms_compute_the_expected_features():
    t, x = np.arange(3.0), np.array([0.0, 2.0, 3.0])
    ch = {"T1": np.array([20.0, 21.0, 22.0])}
    np.testing.assert_array_equal(Power(3).batch(t, x, ch), [0, 8, 27])
    np.testing.assert_array_equal(Bias().batch(t, x, ch), [1, 1, 1])
    np.testing.assert_array_equal(Channel("T1").batch(t, x, ch), [20, 21, 22])
    assert Lag("T1", 1.0).batch(t, x, ch)[0] == 20.0
