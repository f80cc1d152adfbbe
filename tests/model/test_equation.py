"""The model as one readable equation (issue 13, item 6): signs joined, superscripts, bare bias."""

from daemon.model.equation import equation
from daemon.model.model import FittedTerm, Model, Training
from daemon.model.terms import parse_term


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
