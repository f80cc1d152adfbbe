"""A synthetic calibration run whose true inverse model is known (for the model's own tests).

The paper's trajectory (0..480 um in 30 um steps, 29 s per step, N cycles), four temperature
channels with different histories, and q generated from a chosen eq.-3 model plus noise.
"""

from __future__ import annotations

import numpy as np

from daemon.calibration.dataset import Dataset

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
