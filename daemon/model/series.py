"""The one shape of recorded data the pure core reads: fit, predict and discovery take a ``Series``.

:class:`daemon.calibration.dataset.Dataset` (a CSV of the data contract) is one; so is anything with
these arrays. Defined here, beside the model, so the model never depends on file I/O.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol

import numpy as np


class Series(Protocol):
    t: np.ndarray  # s, increasing
    x: np.ndarray  # um: measured position (calibration) or target (request)
    q: np.ndarray | None  # um: the command sent, when recorded
    channels: Mapping[str, np.ndarray]  # degC per temperature channel

    def __len__(self) -> int: ...
