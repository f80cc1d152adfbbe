"""Shared helpers for the simulated-cell, procedure and validation tests."""

from __future__ import annotations

import io
from functools import cache

import numpy as np

from daemon.calibration.dataset import Dataset
from daemon.model.identify import fit
from daemon.model.model import Model
from drivers.simulated.datasets import simulate_dataset


def run_dataset(scenario: str = "train", effects: object = None, seed: int = 0, cycles: int = 24,
                bidirectional: bool = False, **params: float) -> Dataset:
    return simulate_dataset(scenario, effects, cycles=cycles, seed=seed, bidirectional=bidirectional, **params)


@cache
def trained_model(seed: int = 0) -> Model:
    return fit(run_dataset("train", seed=seed)).model


def rms(a: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(a))))


class Capture(io.StringIO):
    """A non-TTY stream for progress output."""

    def isatty(self) -> bool:
        return False
