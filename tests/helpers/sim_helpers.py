"""Shared helpers for the simulated-cell, procedure and validation tests."""

from __future__ import annotations

import io
from functools import cache

import numpy as np

from nanodrift.calibration.dataset import Dataset
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.model.identify import fit
from nanodrift.model.model import Model


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
