"""A synthetic calibration run whose true inverse model is known (for the model's own tests).

The paper's trajectory (0..480 um in 30 um steps, 29 s per step, N cycles), four temperature
channels with different histories, and q generated from a chosen eq.-3 model plus noise.
"""

from __future__ import annotations

import numpy as np

from nanodrift.calibration.dataset import Dataset

TRUE_TERMS = {"x^3": 3.0e-9, "x^2": -4.0e-6, "x": 1.0012, "T1": -0.6, "T2": -0.5, "T4": 0.2, "1": 22.0}
STEPS_UM = np.arange(0.0, 481.0, 30.0)


def paper_run(
    cycles: int = 24, seed: int = 0, noise_um: float = 0.02, terms: dict[str, float] | None = None
) -> Dataset:
    rng = np.random.default_rng(seed)
    terms = TRUE_TERMS if terms is None else terms
    n = cycles * STEPS_UM.size
    t = np.arange(n) * 29.0
    x = np.tile(STEPS_UM, cycles) + rng.normal(0.0, 0.01, n)
    cycle = np.repeat(np.arange(cycles), STEPS_UM.size)
    phase = t / t[-1]
    air = 20.0 - 0.5 * np.sin(np.pi * phase) + 0.05 * np.sin(7 * np.pi * phase)
    channels = {
        "T1": air + 0.1 * np.sin(3 * np.pi * phase) + rng.normal(0, 0.005, n),
        "T2": air - 0.08 * np.cos(5 * np.pi * phase) + rng.normal(0, 0.005, n),
        "T3": air + 0.02 + rng.normal(0, 0.005, n),
        "T4": air + 0.06 * np.sin(11 * np.pi * phase) + rng.normal(0, 0.005, n),
    }
    q = np.full(n, terms.get("1", 0.0))
    for name, coef in terms.items():
        if name == "1":
            continue
        if name.startswith("x"):
            k = 1 if name == "x" else int(name.split("^")[1])
            q += coef * x**k
        else:
            q += coef * channels[name]
    q += rng.normal(0.0, noise_um, n)
    return Dataset(t=t, x=x, q=q, channels=channels, extra={"cycle": cycle.astype(float)}, source="synthetic")


#: the true inverse model of :func:`xy_run`, per axis (q of each axis from both positions and T1, T2)
XY_TRUE_TERMS = {
    "x": {"x^3": 3.0e-9, "x^2": -4.0e-6, "x": 1.0012, "y": -0.0043, "x*y": -2.0e-6, "T1": -0.6, "1": 13.0},
    "y": {"y^3": -2.0e-9, "y^2": 3.0e-6, "y": 0.9990, "x": 0.0021, "x*y": 1.5e-6, "T2": 0.45, "1": -9.0},
}


def xy_run(cycles: int = 4, seed: int = 0, noise_um: float = 0.02,
           terms: dict[str, dict[str, float]] | None = None) -> Dataset:
    """An XY calibration run: a 9 x 9 grid visited in a fresh random order each cycle, 29 s a step.

    The measured positions are the targets plus noise; each axis' command follows ``terms`` (the
    cross terms of a multi-axis cell: crosstalk ``y``, coupled bending ``x*y``) plus noise.
    """
    rng = np.random.default_rng(seed)
    terms = XY_TRUE_TERMS if terms is None else terms
    grid = [(a, b) for a in np.arange(0.0, 481.0, 60.0) for b in np.arange(0.0, 481.0, 60.0)]
    order = np.concatenate([rng.permutation(len(grid)) for _ in range(cycles)])
    n = order.size
    t = np.arange(n) * 29.0
    positions = {"x": np.array([grid[i][0] for i in order]) + rng.normal(0.0, 0.01, n),
                 "y": np.array([grid[i][1] for i in order]) + rng.normal(0.0, 0.01, n)}
    phase = t / t[-1]
    channels = {"T1": 21.0 - 0.5 * np.sin(np.pi * phase) + rng.normal(0, 0.005, n),
                "T2": 21.0 + 0.4 * np.cos(2 * np.pi * phase) + rng.normal(0, 0.005, n)}
    values = {**positions, **channels, "x*y": positions["x"] * positions["y"]}
    commands = {}
    for axis, axis_terms in terms.items():
        q = np.zeros(n)
        for name, coef in axis_terms.items():
            if name == "1":
                q += coef
            elif "^" in name:
                base, k = name.split("^")
                q += coef * values[base] ** int(k)
            else:
                q += coef * values[name]
        commands[axis] = q + rng.normal(0.0, noise_um, n)
    cycle = np.repeat(np.arange(cycles), len(grid)).astype(float)
    return Dataset(t=t, x=positions["x"], q=None, channels=channels, extra={"cycle": cycle}, source="synthetic xy",
                   positions=positions, commands=commands)
