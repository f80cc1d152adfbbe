"""The model as one readable equation (issue 13, item 6): signs joined, superscripts, bare bias."""

import itertools

import pytest
from helpers.budget import examples
from hypothesis import given, settings
from hypothesis import strategies as st

from nanodrift.model.equation import coefficient_digits, equation, feature_bound
from nanodrift.model.model import FittedTerm, Model, Training
from nanodrift.model.terms import parse_term


def test_the_paper_model_reads_as_written():
    model = Model(
        terms=[FittedTerm(parse_term(n), c) for n, c in [("x^3", 6.671e-09), ("x^2", -5.177e-06), ("x", 1.001),
                                                            ("T1", -1.478), ("T4", 0.25), ("1", -27.95)]],
        training=Training((0.0, 480.0), {}, 10, 100.0),
    )
    assert equation(model) == "q = 6.671e-09·x³ − 5.177e-06·x² + 1.001·x − 1.478·T1 + 0.25·T4 − 27.95"


def test_first_term_negative_products_and_named_terms():
    model = Model(terms=[FittedTerm(parse_term("x*T1"), -0.002), FittedTerm(parse_term("lag(T4, 2100 s)"), 0.5),
                         FittedTerm(parse_term("dir"), 0.075), FittedTerm(parse_term("1"), 3.0)],
                  training=Training((0.0, 480.0), {}, 10, 100.0))
    text = equation(model)
    assert text == "q = −0.002·x·T1 + 0.5·lag(T4, 2100 s) + 0.075·dir + 3"
    assert "+ -" not in text and "*" not in text


def test_a_channels_square_reads_as_a_square_about_its_exact_centre():
    model = Model(terms=[FittedTerm(parse_term("(T2 - 21.5937)^2"), 0.3991),
                         FittedTerm(parse_term("(T-1 + 5)^2"), -0.1), FittedTerm(parse_term("1"), 3.0)],
                  training=Training((0.0, 480.0), {}, 10, 100.0))
    assert equation(model) == "q = 0.3991·(T2 − 21.5937)² − 0.1·(T-1 + 5)² + 3"


# --- rounding never hides more than a nanometre (issue 13 follow-up: 1.00049 printed "1·x") -------------

TRAINED = Training((0.0, 480.0), {"T1": (21.5, 22.1), "T2": (21.6, 22.0)}, 100, 3600.0)


def printed_terms(text: str) -> dict[str, float]:
    """{label: coefficient} read back from an equation (the bias under "1")."""
    body = text.split(" = ", 1)[1].replace(" − ", " + -").replace("−", "-")
    out = {}
    for part in body.split(" + "):
        number, _, label = part.partition("·")
        out[label or "1"] = float(number)
    return out


def test_a_gain_just_above_one_is_printed_with_the_digits_that_matter():
    model = Model(terms=[FittedTerm(parse_term("x"), 1.00049), FittedTerm(parse_term("T1"), -1.4784),
                         FittedTerm(parse_term("T2"), 0.50003), FittedTerm(parse_term("1"), -27.95312)],
                  training=TRAINED)
    # was "1·x − 1.478·T1 + 0.5·T2 − 27.95": 235, 9, 0.7 and 3 nm hidden at the box's far corner
    assert equation(model) == "q = 1.00049·x − 1.4784·T1 + 0.5·T2 − 27.953"


def test_digits_grow_only_as_far_as_a_nanometre_needs():
    assert coefficient_digits(1.00049, 480.0, 4) == 6  # 1.00049 (0 nm); 1.000 would hide 235 nm
    assert coefficient_digits(6.671234e-09, 480.0**3, 4) == 4  # 6.671e-09·x³: 0.03 nm at 480 µm
    assert coefficient_digits(0.075, 1.0, 4) == 4
    assert coefficient_digits(1.00049, None, 4) == 4  # nothing known about the feature: the default
    assert feature_bound(parse_term("x^2"), TRAINED) == 480.0**2
    assert feature_bound(parse_term("x*T1"), TRAINED) == pytest.approx(480.0 * 22.1)
    assert feature_bound(parse_term("T3"), TRAINED) is None  # not in the training ranges


@settings(max_examples=examples(200), deadline=None)
@given(gain=st.floats(0.98, 1.02), t1=st.floats(-5.0, 5.0), t2=st.floats(-5.0, 5.0), bias=st.floats(-200.0, 200.0),
       cubic=st.floats(-1e-7, 1e-7), square=st.floats(-1e-4, 1e-4))
def test_the_printed_equation_computes_the_model_within_a_nanometre_per_term(gain, t1, t2, bias, cubic, square):
    coefs = {"x^3": cubic, "x^2": square, "x": gain, "T1": t1, "T2": t2, "1": bias}
    model = Model(terms=[FittedTerm(parse_term(n), c) for n, c in coefs.items()], training=TRAINED)
    printed = printed_terms(equation(model))
    labels = {"x^3": "x³", "x^2": "x²", "x": "x", "T1": "T1", "T2": "T2", "1": "1"}
    for x, a, b in itertools.product((0.0, 480.0), (21.5, 22.1), (21.6, 22.0)):
        feature = {"x^3": x**3, "x^2": x**2, "x": x, "T1": a, "T2": b, "1": 1.0}
        for name, coef in coefs.items():
            shown = printed.get(labels[name], 0.0)  # a zero coefficient prints as "0·x"
            assert abs(shown - coef) * abs(feature[name]) < 1e-3, (name, coef, shown)
