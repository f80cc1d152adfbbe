"""How long the long-running tests run: short by default, as long as a release wants with one variable.

``NANODRIFT_LONG_TESTS=1`` runs the chaos machines and the repeated-race tests at their release sizes (tens
of minutes); the default keeps the suite within the README's figure on two cores. Each suite's own variables
(``NANODRIFT_CHAOS_EXAMPLES``, ...) still override both.
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
