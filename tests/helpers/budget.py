"""How long the long-running tests run: short by default, as long as a release wants with one variable.

``NANODRIFT_LONG_TESTS=1`` runs the chaos machines, the repeated-race tests and the property tests at their
release sizes (tens of minutes); the default keeps the suite within the README's figure on two cores. Each
suite's own variables (``NANODRIFT_CHAOS_EXAMPLES``, ...) still override both.
"""

from __future__ import annotations

import os

LONG_TESTS = os.environ.get("NANODRIFT_LONG_TESTS", "") == "1"


def sized(name: str, quick: int, long: int) -> int:
    """The environment's ``name`` if set, else ``long`` with NANODRIFT_LONG_TESTS=1, else ``quick``."""
    value = os.environ.get(name)
    if value is not None:
        return int(value)
    return long if LONG_TESTS else quick


#: the share of a property test's release examples the default run draws: every property still meets random
#: input on every run (the shrinker and hypothesis' database keep what failed), at about a third of the CPU
CI_SHARE = 3
CI_MIN_EXAMPLES = 25


def examples(release: int) -> int:
    """Hypothesis examples for a property test written with ``release`` examples: all of them with
    NANODRIFT_LONG_TESTS=1, else a third (at least :data:`CI_MIN_EXAMPLES`, never more than ``release``)."""
    if LONG_TESTS:
        return release
    return min(release, max(CI_MIN_EXAMPLES, release // CI_SHARE))
