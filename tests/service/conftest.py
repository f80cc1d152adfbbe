"""Fixtures of the tests that drive a daemon against an emulated Modbus output module (helpers.edge_cell)."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from helpers.edge_cell import Cell, OutputModule


@pytest.fixture
def module() -> Iterator[OutputModule]:
    """The emulated output module on 127.0.0.1, closed after the test."""
    out = OutputModule()
    yield out
    out.close()


@pytest.fixture
def cells() -> Iterator[list[Cell]]:
    """The daemons a test starts, each closed after it (a file with a Cell of its own defines its own)."""
    made: list[Cell] = []
    yield made
    for cell in made:
        cell.close()
