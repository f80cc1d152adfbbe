"""What a named effect promises a fresh run, and how far the run pins its time constant.

Held-out blocks of the run an effect was chosen on flatter it: the blocks share the run's room
history and slow interferometer wander, and the blocks at the run's ends make the given model
extrapolate its missing effect. A fresh run of the same kind errs, for each model, by its in-sample
error plus an optimism ω: what fitting the run hid of its own slow noise and what the coefficients'
errors add on new data. ω is measured where the residual is mostly noise, on the model with the effect
(``held-out MSE - in-sample MSE``, a searched time constant chosen without each held-out block: the
search confirmed on blocks it did not see), and charged to the model without it in proportion to its
fitted parameters. ``benchmarks/discovery_fresh.py`` checks the estimate against fresh runs of every
effect. A named time constant also gets the range of τ the held-out blocks cannot tell from it.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy import special

from nanodrift.calibration.discovery.settings import Settings

#: how the expected fresh-run gain is estimated (the report and ``--json`` carry it beside the figure)
EXPECTED_METHOD = ("expected RMS on a fresh run of the same kind = sqrt(in-sample MSE + ω), ω = held-out MSE minus "
                   "in-sample MSE of the model with the effect (what fitting hides of the run's own slow noise; a "
                   "searched time constant chosen without each held-out block), charged to the model without it in "
                   "proportion to its fitted parameters")
NUISANCE_METHOD = EXPECTED_METHOD + ("; for a drift not applied online: on a fresh run without it (its source fixed "
                                     "or sensed), where the model without the effect errs by its residual less the "
                                     "fitted drift (its coefficients absorbed the drift)")
MEASURED_METHOD = "measured on the fresh run given (--fresh): RMS of q - q_pred with and without the step"


@dataclass(frozen=True)
class FreshGain:
    """The RMS of a fresh run without and with an effect (µm), expected or measured, and how it was found."""

    rms_before_um: float
    rms_after_um: float
    method: str

    @property
    def ratio(self) -> float:
        """RMS after / before: below 1 the effect helps a fresh run; 1 - ratio is the share of the error removed."""
        return self.rms_after_um / self.rms_before_um if self.rms_before_um > 0 else 1.0


def round_sig(value: float, digits: int = 3) -> float:
    return float(f"{value:.{digits}g}")


def hidden_by_fit_um2(in_sample_um: float, held_out_um: float) -> float:
    """ω: the MSE a fit hides of its own run (held-out MSE - in-sample MSE; 0 when held-out is better by chance)."""
    return max(held_out_um**2 - in_sample_um**2, 0.0)


def expected_fresh(in_before_um: float, in_after_um: float, omega_after_um2: float, params_before: int,
                   params_after: int, method: str = EXPECTED_METHOD) -> FreshGain:
    """Expected fresh-run RMS without and with an effect: each model's in-sample MSE plus its ω.

    ``in_*``: RMS on all rows of the model fitted on all rows; ``omega_after_um2``: ω of the model with
    the effect (:func:`hidden_by_fit_um2`); the model without it is charged ω in proportion to the
    fitted parameters (``params_*``: intercept and searched time constants included).
    """
    omega_before = omega_after_um2 * params_before / max(params_after, 1)
    return FreshGain(math.sqrt(in_before_um**2 + omega_before), math.sqrt(in_after_um**2 + omega_after_um2), method)


@dataclass(frozen=True)
class TauRange:
    """The time constants the run supports: held-out blocks not significantly worse than at the τ named."""

    lo_s: float
    hi_s: float
    pinned_lo: bool  # False: the run predicts as well down to the bottom of the searched range
    pinned_hi: bool  # False: ... up to the top of it (a lag as long as the run is a trend)

    @property
    def pinned(self) -> bool:
        return self.pinned_lo and self.pinned_hi

    def words(self) -> str:
        lo, hi = _duration(self.lo_s), _duration(self.hi_s)
        if self.pinned:
            return f"the run supports τ from {lo} to {hi}"
        if self.pinned_lo:
            return (f"the run pins τ only from below: from {lo} up to the longest searched ({hi}), held-out blocks "
                    "are predicted as well")
        if self.pinned_hi:
            return (f"the run pins τ only from above: up to {hi}, down to the shortest searched ({lo}), held-out "
                    "blocks are predicted as well")
        return (f"the run cannot pin τ: over the whole searched range ({lo} to {hi}) held-out blocks are predicted "
                "as well")


def _duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.3g} s"
    return f"{seconds / 60:.0f} min" if seconds < 3 * 3600 else f"{seconds / 3600:.1f} h"


FoldErrors = Callable[[float], tuple[np.ndarray, np.ndarray]]


def nested_held_out(fold_errors: FoldErrors, tau: float, bounds: tuple[float, float]) -> np.ndarray:
    """Held-out SSE per block with the time constant chosen without that block.

    The named τ was searched on all rows, so its held-out blocks helped choose it; here each block's
    τ minimises the training SSE of the other blocks (over a log grid of the searched range, finer
    around τ), and the block is predicted with it: the search itself confirmed on unseen data.
    """
    lo, hi = bounds
    fine = [tau * 1.15**k for k in range(-8, 9)]
    grid = sorted({*np.geomspace(lo, hi, 12).tolist(), *(t for t in fine if lo <= t <= hi)})
    train, held = (np.array(e) for e in zip(*(fold_errors(t) for t in grid), strict=True))  # (τ, block) each
    pick = np.argmin(train, axis=0)
    chosen: np.ndarray = held[pick, np.arange(held.shape[1])]
    return chosen


def worse_than(fold_errors: FoldErrors, tau: float, block_rows: np.ndarray,
               settings: Settings) -> Callable[[float], bool]:
    """Whether held-out blocks are predicted significantly worse at τ' than at ``tau``.

    ``fold_errors(τ)[1]``: the held-out SSE of each block (each predicted by a fit on the others). The
    blocks are the run's independent units (whole cycles, apart in time), so the test is a one-sided
    paired t-test over them of the per-row error increase, at ``1 - tau_range_confidence``.
    """
    reference = fold_errors(tau)[1] / block_rows
    critical = float(special.stdtrit(max(block_rows.size - 1, 1), settings.tau_range_confidence))

    def worse(other: float) -> bool:
        increase = fold_errors(other)[1] / block_rows - reference
        mean = float(np.mean(increase))
        spread = float(np.std(increase, ddof=1)) if increase.size > 1 else 0.0
        if spread == 0.0:
            return mean > 0.0
        return mean / (spread / math.sqrt(increase.size)) > critical

    return worse


def tau_range(worse: Callable[[float], bool], tau: float, bounds: tuple[float, float]) -> TauRange:
    """The interval of τ around ``tau`` not significantly worse (``worse``), within the searched ``bounds``.

    Each edge is walked out from τ in steps of 25 % then bisected on log τ; an edge that reaches the
    searched range's end without getting worse is not pinned.
    """
    lo, pinned_lo = _edge(worse, tau, bounds[0])
    hi, pinned_hi = _edge(worse, tau, bounds[1])
    return TauRange(round_sig(lo), round_sig(hi), pinned_lo, pinned_hi)


def _edge(worse: Callable[[float], bool], tau: float, bound: float) -> tuple[float, bool]:
    """(the farthest τ toward ``bound`` not worse, whether it got worse before reaching the bound)."""
    up = bound > tau
    if bound == tau:
        return bound, False
    inside = tau
    while True:
        step = inside * (1.25 if up else 0.8)
        if (step >= bound) if up else (step <= bound):
            if not worse(bound):
                return bound, False
            outside = bound
            break
        if worse(step):
            outside = step
            break
        inside = step
    for _ in range(6):  # bisect on log τ: the edge to within ~0.4 % of the 25 % step
        mid = math.sqrt(inside * outside)
        if worse(mid):
            outside = mid
        else:
            inside = mid
    return inside, True
