"""Fixtures of the tests that drive a daemon against an emulated Modbus output module (helpers.edge_cell)."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

import pytest
from helpers.edge_cell import OutputModule


@pytest.fixture
def module() -> Iterator[OutputModule]:
    """The emulated output module on 127.0.0.1, closed after the test."""
    out = OutputModule()
    yield out
    out.close()


@pytest.fixture
def cells() -> Iterator[list[Any]]:
    """The daemons a test starts (any cell harness with ``close()``), each closed after it."""
    made: list[Any] = []
    yield made
    for cell in made:
        cell.close()
