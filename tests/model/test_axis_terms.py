"""Multi-axis terms: parsed only for a multi-axis cell, and batch == stream as for every term."""

from __future__ import annotations

import numpy as np
import pytest
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.calibration.dataset import Dataset
from nanodrift.model.axis_terms import AxisProduct
from nanodrift.model.effect_terms import Creep, PositionCoupling
from nanodrift.model.segments import features
from nanodrift.model.terms import Channel, Direction, Power, UnknownTermError, parse_term

XY = ("x", "y")
XYZ = ("x", "y", "z")
NAMES = ["y", "y^2", "z^3", "x*y", "y*z", "y*T1", "dir(y)", "dir(z, 2 um)", "creep(y, 15 s)",
         "creep(z, 40 s, 1 um)", "x^3", "x*T1", "T1", "dir", "creep(15 s)", "lag(T1, 100 s)", "1"]


def _xyz_run(seed: int, n: int = 300) -> Dataset:
    rng = np.random.default_rng(seed)
    t = np.cumsum(rng.uniform(20.0, 40.0, n))
    positions = {a: rng.choice(np.arange(0.0, 481.0, 60.0), n) for a in XYZ}
    return Dataset(t=t, x=positions["x"], q=None, channels={"T1": 22.0 + 0.3 * np.sin(t / 3000.0)},
                   positions=positions, commands={a: v + 0.1 for a, v in positions.items()})


@pytest.mark.parametrize("name", NAMES)
def test_every_name_round_trips_and_streams_as_it_batches(name: str) -> None:
    data = _xyz_run(1)
    term = parse_term(name, XYZ)
    assert term.name == name
    batch = features(term, data)
    stream = term.stream()
    streamed = []
    for i in range(len(data)):
        stream.observe(float(data.t[i]), {"T1": float(data.channels["T1"][i])})
        stream.targets({a: float(data.positions[a][i]) for a in XYZ})
        streamed.append(stream.value(float(data.t[i]), float(data.x[i])))
        stream.moved(float(data.t[i]), float(data.x[i]))
    np.testing.assert_allclose(streamed, batch, rtol=1e-9, atol=1e-9)


def test_axis_names_are_axis_terms_only_in_a_multi_axis_cell() -> None:
    # a one-axis model file may have a channel named y: its names parse exactly as before
    assert isinstance(parse_term("y"), Channel)
    assert isinstance(coupling := parse_term("x*y"), PositionCoupling) and coupling.axis == "x"
    assert isinstance(power := parse_term("x^2"), Power) and power.axis == "x" and power.axes == ()
    # the other axis' terms are the same kinds of term, on that axis
    assert isinstance(power := parse_term("y", XY), Power) and power.axis == "y" and power.axes == ("y",)
    assert isinstance(parse_term("x*y", XY), AxisProduct)
    assert isinstance(coupling := parse_term("y*T2", XY), PositionCoupling) and coupling.axes == ("y",)
    assert isinstance(direction := parse_term("dir(y)", XY), Direction) and direction.axes == ("y",)
    assert isinstance(creep := parse_term("creep(y, 5 s)", XY), Creep) and creep.axes == ("y",)
    # an axis the cell does not have is not an axis term: z in an XY cell stays a channel name
    assert isinstance(parse_term("z", XY), Channel)
    with pytest.raises(UnknownTermError):
        parse_term("dir(z)", XY)


def test_the_other_axes_position_is_what_the_feature_reads() -> None:
    data = _xyz_run(2, n=50)
    np.testing.assert_array_equal(features(Power(2, "y"), data), data.positions["y"] ** 2)
    np.testing.assert_array_equal(features(AxisProduct("z", "x"), data), data.positions["x"] * data.positions["z"])
    assert AxisProduct("z", "x").name == "x*z"


def test_a_series_without_the_axis_is_refused_naming_it() -> None:
    one_axis = Dataset(t=np.arange(3.0), x=np.zeros(3), q=np.zeros(3), channels={}, source="one.csv")
    with pytest.raises(KeyError, match=r"one\.csv has no position of axis 'y'"):
        features(Power(1, "y"), one_axis)


@settings(max_examples=examples(60), deadline=None)
@given(st.text(alphabet="xyzq*^()0123456789, .smuT", max_size=14))
def test_no_text_breaks_the_parser_with_anything_but_a_clear_error(text: str) -> None:
    for axes in (("x",), XY, XYZ):
        try:
            term = parse_term(text, axes)
        except (UnknownTermError, ValueError):
            continue
        assert parse_term(term.name, axes).name == term.name  # canonical names parse back to themselves
