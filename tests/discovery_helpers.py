"""Runs of the simulated cell for the discovery tests, in process (no subprocess, no CSV).

A calibration run is the paper's stepped trajectory (forward sweeps 0..480 um, or alternating
up/down sweeps for direction-dependent effects) through ``drivers.simulated.runs.simulate_steps``,
returned as a :class:`Dataset` exactly as ``nanodrift simulate`` would write it.
"""

from __future__ import annotations

import numpy as np

from daemon.calibration.dataset import Dataset
from daemon.model.identify import fit
from daemon.model.model import Model
from drivers.simulated.physics import CellPhysics
from drivers.simulated.runs import simulate_steps

POINTS_UM = np.arange(0.0, 481.0, 30.0)


def targets(cycles: int, bidirectional: bool) -> tuple[np.ndarray, np.ndarray]:
    sweeps = [POINTS_UM if (c % 2 == 0 or not bidirectional) else POINTS_UM[::-1] for c in range(cycles)]
    return np.concatenate(sweeps), np.repeat(np.arange(cycles), POINTS_UM.size)


def cell_run(effects: str = "", seed: int = 0, cycles: int = 24, scenario: str = "train",
             bidirectional: bool = False) -> Dataset:
    """A recorded calibration run of the simulated cell with ``effects`` hidden."""
    physics = CellPhysics.create(scenario, effects or None, seed=seed)
    x, cycle = targets(cycles, bidirectional)
    cols = simulate_steps(physics, x, cycle)
    channels = {c: cols[c] for c in ("T1", "T2", "T3", "T4")}
    return Dataset(t=cols["t_s"], x=cols["x_um"], q=cols["q_um"], channels=channels,
                   extra={"cycle": cols["cycle"]}, source=f"sim:{scenario}:{effects or 'none'}:{seed}")


def paper_model(data: Dataset) -> Model:
    """The paper's identification (eq. 3, order chosen on held-out cycles)."""
    return fit(data, order=3).model
