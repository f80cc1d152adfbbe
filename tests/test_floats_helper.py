"""The tolerant comparison the "unchanged output" pins use (tests/helpers/floats.py) still catches a change."""

from __future__ import annotations

import pytest
from helpers.floats import assert_same, differences, last_digit_unit


def test_the_last_bits_of_a_float_do_not_count() -> None:
    assert_same(b'{"q_um":176.62999999999997,"id":"k"}', b'{"q_um":176.63,"id":"k"}')
    assert_same("q = 6.004324686872055e-09", "q = 6.004324686877132e-09")
    # a value printed rounded may flip its last digit
    assert_same("coef 6.004e-09 rms 22.3 nm", "coef 6.005e-09 rms 22.4 nm", rounded=True)
    assert_same(b'{"x_um":1e-17}', b'{"x_um":0.0}')  # a sum that cancels


@pytest.mark.parametrize(("actual", "expected"), [
    (b'{"q_um":176.64,"id":"k"}', b'{"q_um":176.63,"id":"k"}'),       # a real change of a full-precision number
    (b'{"q_um":176.63,"id":"m-735e979167ad"}', b'{"q_um":176.63,"id":"m-735e979167ac"}'),  # a string, digits inside
    (b'{"id":"k","q_um":176.63}', b'{"q_um":176.63,"id":"k"}'),       # the keys' order
    (b'{"q_um": 176.63}', b'{"q_um":176.63}'),                         # a separator
    ("coef 6.007e-09", "coef 6.005e-09"),                              # two units of the last printed digit
    ("51 rows", "52 rows"),                                            # an integer is exact
    ("x 1.0 y", "x 1.0"),                                              # something missing
])
def test_a_real_change_is_reported(actual: str | bytes, expected: str | bytes) -> None:
    assert differences(actual, expected)
    with pytest.raises(AssertionError):
        assert_same(actual, expected)


def test_the_unit_of_the_last_printed_digit() -> None:
    assert last_digit_unit("6.004e-09") == pytest.approx(1e-12)
    assert last_digit_unit("22.063") == pytest.approx(1e-3)
    assert last_digit_unit("51") == 1.0


def test_an_identifier_is_a_word_not_a_number() -> None:
    """A model id such as m-05e578fbc20d holds "-05e578", which read as a number overflowed the comparison."""
    assert differences("model m-05e578fbc20d -> m.json", "model m-05e578fbc20d -> m.json", rounded=True) == []
    assert differences("model m-05e578fbc20d", "model m-05e578fbc20e")  # another id is another model
    assert differences("T1 1.0", "T2 1.0")
