"""Runs of the simulated cell for the discovery tests, in process (no subprocess, no CSV).

A calibration run comes from :func:`nanodrift.drivers.simulated.datasets.simulate_dataset`, the code path of
``nanodrift simulate``, so what discovery is tested on is exactly what a user's CSV holds.
"""

from __future__ import annotations

import numpy as np

from nanodrift.calibration.dataset import Dataset
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.model.identify import fit
from nanodrift.model.model import Model


def cell_run(effects: str = "", seed: int = 0, cycles: int = 24, scenario: str = "train",
             bidirectional: bool = False) -> Dataset:
    """A recorded calibration run of the simulated cell with ``effects`` hidden (their defaults unless given)."""
    return simulate_dataset(scenario, effects or None, cycles=cycles, seed=seed, bidirectional=bidirectional)


def paper_model(data: Dataset) -> Model:
    """The paper's identification (eq. 3 with MATLAB's stepwise selection, order 3): the baseline the discovery
    scenarios were designed on (the product's default selection, ``coherent``, is tested from the CLI)."""
    return fit(data, order=3, selection="paper").model


def rms(data: Dataset, model: Model) -> float:
    """The model's RMS error (µm) on a run's recorded q."""
    assert data.q is not None
    return float(np.sqrt(np.mean((data.q - model.predict(data)) ** 2)))
