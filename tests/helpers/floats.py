"""Comparing outputs that carry floats, with tolerances another CPU, BLAS or numpy release respects.

A pin of "unchanged" behaviour (a payload's bytes, a command's printout, a fitted model) must fail when
the behaviour changes, and must not fail because a different machine rounds the last bit of a sum
differently (another OpenBLAS kernel, numpy's SIMD paths for exp/log). So the text is compared exactly
except for its numbers: JSON strings are compared as they are, every number within a tolerance, and
everything between them (keys, order, separators, words) byte for byte.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterator

#: a JSON string (taken whole, digits inside included), a word (an identifier such as ``m-05e578fbc20d`` or
#: ``T1``, taken whole: its digits are no number), or a number
_TOKEN = re.compile(r'("(?:[^"\\]|\\.)*")|([A-Za-z_][\w-]*)|([-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)')

#: relative tolerance on a number printed in full (``repr``): far above rounding, far below a real change
REL_TOL = 1e-9
#: absolute floor (the outputs' unit is µm, V or °C): a sum that cancels to ~0 keeps no relative digits
ABS_TOL = 1e-12


def _parts(text: str) -> Iterator[tuple[str, str]]:
    """("text" | "string" | "word" | "number", the characters), in order, covering all of ``text``."""
    end = 0
    for match in _TOKEN.finditer(text):
        if match.start() > end:
            yield "text", text[end:match.start()]
        if match[1] is not None:
            yield "string", match[1]
        elif match[2] is not None:
            yield "word", match[2]
        else:
            yield "number", match[3]
        end = match.end()
    if end < len(text):
        yield "text", text[end:]


def last_digit_unit(token: str) -> float:
    """The value of one unit in the last printed digit: ``6.004e-09`` -> 1e-12, ``22.063`` -> 0.001."""
    mantissa, _, exponent = token.lower().partition("e")
    decimals = len(mantissa.partition(".")[2])
    return 10.0 ** (int(exponent or 0) - decimals)


def close(actual: str, expected: str, rel: float = REL_TOL, *, rounded: bool = False) -> bool:
    """Two printed numbers agree: within ``rel`` of their size (or ``ABS_TOL``); ``rounded`` (a human
    printout, not ``repr``): or within one unit of the coarser printed digit, which another machine's
    last bits may flip."""
    a, b = float(actual), float(expected)
    slack = max(rel * max(abs(a), abs(b)), ABS_TOL)
    if rounded:
        slack = max(slack, last_digit_unit(actual), last_digit_unit(expected))
    if "." not in actual + expected and "e" not in (actual + expected).lower():
        slack = 0.0  # integers (counts, indices, ids) are exact
    return math.isclose(a, b, rel_tol=0.0, abs_tol=slack)


def differences(actual: str | bytes, expected: str | bytes, rel: float = REL_TOL, *,
                rounded: bool = False) -> list[str]:
    """Where ``actual`` differs from ``expected`` beyond the tolerance (empty: the same)."""
    if isinstance(actual, bytes):
        actual = actual.decode()
    if isinstance(expected, bytes):
        expected = expected.decode()
    got, want = list(_parts(actual)), list(_parts(expected))
    found = []
    for index, ((kind_a, a), (kind_b, b)) in enumerate(zip(got, want, strict=False)):
        same = close(a, b, rel, rounded=rounded) if kind_a == kind_b == "number" else (kind_a, a) == (kind_b, b)
        if not same:
            context = "".join(p for _, p in want[max(0, index - 3):index])
            found.append(f"after {context[-60:]!r}: got {a!r}, expected {b!r}")
    if len(got) != len(want):
        found.append(f"{len(got)} parts against {len(want)} expected")
    return found


def assert_same(actual: str | bytes, expected: str | bytes, rel: float = REL_TOL, *,
                rounded: bool = False) -> None:
    """``actual`` is ``expected`` but for its numbers' last bits (see the module's docstring); ``rounded``:
    its numbers were printed rounded for people (see :func:`close`)."""
    problems = differences(actual, expected, rel, rounded=rounded)
    assert not problems, "\n".join(problems[:10])
