"""Shared helpers for the simulated-cell, procedure and validation tests."""

from __future__ import annotations

import io
from functools import cache

import numpy as np

from daemon.calibration.dataset import Dataset
from daemon.calibration.procedure import calibration_plan
from daemon.model.identify import fit
from daemon.model.model import Model
from drivers.simulated.physics import THERMOCOUPLES, CellPhysics
from drivers.simulated.runs import simulate_steps


def run_dataset(scenario: str = "train", effects: object = None, seed: int = 0, cycles: int = 24,
                plan_fn=calibration_plan, **params: float) -> Dataset:
    physics = CellPhysics.create(scenario, effects, seed, **params)
    plan = plan_fn(cycles)
    out = simulate_steps(physics, [s.target_um for s in plan], [s.cycle for s in plan])
    return Dataset(t=out["t_s"], x=out["x_um"], q=out["q_um"], channels={c: out[c] for c in THERMOCOUPLES},
                   extra={"cycle": out["cycle"]})


@cache
def trained_model(seed: int = 0) -> Model:
    return fit(run_dataset("train", seed=seed)).model


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


class Capture(io.StringIO):
    """A non-TTY stream for progress output."""

    def isatty(self) -> bool:
        return False
