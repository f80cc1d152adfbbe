"""The one shape of recorded data the pure core reads: fit, predict and discovery take a ``Series``.

:class:`nanodrift.calibration.dataset.Dataset` (a CSV of the data contract) is one; so is anything with
these arrays and methods. Defined here, beside the model, so the model never depends on file I/O.
Everything the core reads is declared here, so the core never asks ``getattr(data, ...)``.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import numpy as np


class Series(Protocol):
    # read-only members (properties): the core never writes them, and a read-only member lets a
    # ``Dataset`` whose ``channels`` is a ``dict`` (a ``Mapping``) be a ``Series``
    @property
    def t(self) -> np.ndarray:  # s, increasing
        ...

    @property
    def x(self) -> np.ndarray:  # um: measured position (calibration) or target (request)
        ...

    @property
    def q(self) -> np.ndarray | None:  # um: the command sent, when recorded
        ...

    @property
    def channels(self) -> Mapping[str, np.ndarray]:  # degC per temperature channel
        ...

    @property
    def source(self) -> str:  # where the rows came from (a file name), for messages
        ...

    @property
    def segment(self) -> np.ndarray | None:  # per row, the run (file) it came from when several were read together
        ...

    def __len__(self) -> int: ...

    def select(self, rows: np.ndarray | slice) -> Series:
        """The rows picked by a boolean mask, an index array or a slice."""
        ...

    def valid_rows(self) -> Series:
        """Only the rows measured cleanly (all of them when nothing is marked invalid)."""
        ...

    def cycles(self) -> np.ndarray:
        """Calibration cycle index per row (held-out blocks are whole cycles)."""
        ...


class CellSeries(Series, Protocol):
    """A multi-axis run (an XY or XYZ stage): every axis' position and, when recorded, command."""

    @property
    def axes(self) -> tuple[str, ...]: ...

    @property
    def positions(self) -> Mapping[str, np.ndarray]:  # um per axis, the cell's axis order
        ...

    @property
    def commands(self) -> Mapping[str, np.ndarray]:  # um per axis: q_<axis>_um
        ...

    def axis_view(self, axis: str) -> Series:
        """The rows as ``axis``' identification sees them: its command as ``q``."""
        ...
