"""A population of simulated cells: per seed, one cell whose bracket bending is drawn.

Why: a σ that one calibration computes must cover every bending that calibration cannot exclude, so
judged over calibrations of ONE cell (whose own bending is the same on every seed) it cannot be
calibrated, only wide. Judged over cells whose bending is drawn from what one calibration cannot rule
out, it can (issue 27; ``benchmarks/coverage.py --cells population``).

The draw is the cell's magnitudes as overrides (``CellParams`` fields): pass them to
``simulate_dataset(..., **overrides)`` and ``simulated_drivers(..., params=overrides)`` so a seed's
calibration and its validation runs see the same cell.
"""

from __future__ import annotations

import numpy as np

from nanodrift.drivers.simulated.physics import cell_variant

#: the one magnitude drawn: the bracket's bending (the part no calibration over 0.5 °C sees)
BENDING_FIELD = "k2_bracket_um_per_c2"


def drawn_cell(seed: int, bending_sd_um_per_c2: float, cell: str = "realistic") -> dict[str, float]:
    """Seed ``seed``'s cell of the population: ``{BENDING_FIELD: k2}``, k2 ~ N(``cell``'s own k2, sd²) from
    ``numpy.random.default_rng(seed)`` (reproducible; the simulator's own streams are seeded ``[seed, n]``)."""
    if not (np.isfinite(bending_sd_um_per_c2) and bending_sd_um_per_c2 >= 0):
        raise ValueError(f"bending_sd_um_per_c2: expected a finite number >= 0, got {bending_sd_um_per_c2!r}")
    own = getattr(cell_variant(cell).params, BENDING_FIELD)
    k2 = own + bending_sd_um_per_c2 * float(np.random.default_rng(seed).standard_normal())
    return {BENDING_FIELD: k2}
