"""The population of cells ``benchmarks/coverage.py --cells population`` judges σ over: each seed's bracket
bending drawn reproducibly, and the drawn bending is what that seed's simulated cell does."""

from __future__ import annotations

import math

import numpy as np
import pytest

from nanodrift.assembly import simulated_drivers
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import REALISTIC_PARAMS, CellPhysics
from nanodrift.drivers.simulated.plugin import shared_cell
from nanodrift.drivers.simulated.population import BENDING_FIELD, drawn_cell

OWN_K2 = REALISTIC_PARAMS.k2_bracket_um_per_c2
SD = 0.76  # about the median κ of the tuning calibrations


def test_the_draw_is_reproducible_per_seed_and_spreads_about_the_cells_own_bending():
    assert drawn_cell(7, SD) == drawn_cell(7, SD)  # the same seed: the same cell, in any process
    expected = OWN_K2 + SD * float(np.random.default_rng(7).standard_normal())
    assert math.isclose(drawn_cell(7, SD)[BENDING_FIELD], expected, rel_tol=0, abs_tol=1e-12)
    assert drawn_cell(7, 0.0) == {BENDING_FIELD: OWN_K2}
    k2 = np.array([drawn_cell(seed, SD)[BENDING_FIELD] for seed in range(400)])
    assert len(set(k2.tolist())) == k2.size  # every seed its own cell
    # 400 draws: the mean within ~4 standard errors (0.15), the SD within ~15 %
    assert abs(k2.mean() - OWN_K2) < 0.15 and 0.85 * SD < k2.std() < 1.15 * SD
    with pytest.raises(ValueError, match=r"bending_sd_um_per_c2: expected a finite number >= 0, got -0.1"):
        drawn_cell(0, -0.1)


def test_the_drawn_bending_reaches_the_simulated_data_in_proportion():
    """The recorded position is linear in k2 (same seed: same room, noise and landings), so a seed's cell moves
    its data by (k2 - own)/own times the cell's own bending: the draw reaches the physics, whole."""
    drawn = drawn_cell(3, SD)
    k2 = drawn[BENDING_FIELD]
    assert abs(k2 - OWN_K2) > 0.1  # a draw that differs enough to show

    def x_um(**overrides: float) -> np.ndarray:
        return simulate_dataset("test5", cycles=1, seed=305, cell="realistic", **overrides).x

    own, flat, cell = x_um(), x_um(**{BENDING_FIELD: 0.0}), x_um(**drawn)
    own_bending = own - flat
    assert np.max(np.abs(own_bending)) > 0.05  # test 5 (1.5 °C above training): the bending shows
    assert np.max(np.abs(cell - own)) > 0.05  # the seed's cell is not the one cell
    # each recorded sample is rounded to the interferometer's 0.3 nm: 1 nm holds three datasets' rounding
    np.testing.assert_allclose(cell - flat, (k2 / OWN_K2) * own_bending, rtol=0, atol=1e-3)


def test_the_validation_drivers_simulate_the_drawn_cell():
    drawn = drawn_cell(3, SD)
    physics = shared_cell(simulated_drivers("test5", seed=305, cell="realistic", params=drawn).context).physics
    assert physics.params.k2_bracket_um_per_c2 == drawn[BENDING_FIELD]
    own = CellPhysics.create("test5", seed=305, cell="realistic")
    flat = CellPhysics.create("test5", seed=305, cell="realistic", **{BENDING_FIELD: 0.0})
    t = np.linspace(0.0, 4 * 3600.0, 9)
    expected = flat.drift(t)["x"] + (drawn[BENDING_FIELD] / OWN_K2) * (own.drift(t)["x"] - flat.drift(t)["x"])
    np.testing.assert_allclose(physics.drift(t)["x"], expected, rtol=0, atol=1e-9)
    assert np.max(np.abs(physics.drift(t)["x"] - own.drift(t)["x"])) > 0.02
