"""An extended model from discovery carries the covariance block, like a fitted one."""

from __future__ import annotations

import numpy as np
from helpers.discovery_helpers import cell_run, paper_model

from nanodrift.calibration.discovery import discover


def test_the_extended_model_has_a_covariance_over_its_own_terms() -> None:
    data = cell_run("creep:c=0.01,tau_s=15", seed=7)
    given = paper_model(data)
    result = discover(data, given)
    assert [s.effect for s in result.steps] == ["creep"], result.summary
    cov = result.model.covariance
    assert cov is not None and cov.size == len(result.model.terms)
    assert cov.curvature is not None and set(cov.curvature.channels) <= set(result.model.channels)
    fresh = cell_run("creep:c=0.01,tau_s=15", seed=107)
    sigma_after, sigma_before = result.model.q_sigma(fresh), given.q_sigma(fresh)
    assert np.all(np.isfinite(sigma_after))
    # the creep the given model lacked was in its residual: the extended model is surer of what a fresh
    # run will measure (q_sigma with the residual's slow part, which the block keeps apart as wander_um)
    assert cov.wander_um is not None and given.covariance is not None and given.covariance.wander_um is not None
    measured_after = np.hypot(np.median(sigma_after), cov.wander_um)
    measured_before = np.hypot(np.median(sigma_before), given.covariance.wander_um)
    assert measured_after < 0.8 * measured_before
