"""The bar an effect must clear and the ranges searched: one frozen value passed through discovery."""

from __future__ import annotations

from dataclasses import dataclass

#: effects whose terms the daemon cannot apply online: named, fitted as nuisance, not written out
NOT_APPLIED_ONLINE = frozenset({"unmonitored_drift"})


@dataclass(frozen=True)
class Settings:
    """Thresholds and search ranges (the defaults are the documented bar)."""

    p_max: float = 0.01
    min_holdout_gain: float = 0.10  # held-out RMS must fall by at least 10 %
    exclusion_gain: float = 0.05  # leaving a channel out must cut the held-out RMS by 5 % ...
    exclusion_blocks: float = 0.8  # ... improving at least 80 % of the held-out blocks ...
    exclusion_p_iid: float = 1e-4  # ... though the stepwise keeps it with conviction (a barely kept one is not it)
    #: a trend in time (or a lag as long as the run) must cut the held-out RMS by half: over a few
    #: hours the interferometer's own slow wander (tens of nm) can look like a trend
    trend_gain: float = 0.50
    search_penalty: float = 0.02  # ranking: held-out RMS x (1 + 2 % per searched parameter)
    #: a searched time constant must be pinned by the run: the fit at τ x pin_factor and at τ / pin_factor
    #: must be worse than at τ by more than chance (chi-squared, 1 dof, 95 %: pin_chi2) on the run's
    #: effective rows. A lag of hours in a run where the room falls and rises once is not: there it
    #: fits the held-out blocks and still hurts a fresh run (benchmarks/discovery_fresh.py)
    pin_factor: float = 2.0
    pin_chi2: float = 3.84
    #: the τ range reported for a named time constant: the τ whose held-out blocks are not worse than at the
    #: named τ by a one-sided paired t-test over the blocks at this confidence
    tau_range_confidence: float = 0.95
    #: a drift in time is named only when its held-out RMS is below this fraction of the best thermal
    #: lag's (any channel, any τ): otherwise the run cannot tell an unmonitored source from a slow
    #: thermal one, and a model cleaned of a "drift" that was a lag is far worse on a fresh run
    drift_vs_lag: float = 0.75
    prefer_fastest_within: float = 0.05
    min_direction_share: float = 0.10
    max_steps: int = 4
    max_power: int = 6
    lag_tau_s: tuple[float, float] = (60.0, 8 * 3600.0)
    #: a lag shorter than this acts through the rate of change: named temperature_rate
    rate_tau_max_s: float = 900.0
    #: piezo creep settles in seconds to minutes; longer would only mimic slow thermal drift
    creep_tau_s: tuple[float, float] = (0.5, 600.0)
    grid_points: int = 10
    refine_evals: int = 10
    bins: int = 8
    rate_probe_tau_s: float = 600.0
    #: a named thermal_lag is flagged as alike an unmonitored drift when, beyond the working model's
    #: terms, the lag's column and a line in time correlate at least this much
    twin_correlation: float = 0.9


#: the documented bar (a module-level value, so that defaults of arguments share one frozen instance)
DEFAULT_SETTINGS = Settings()
