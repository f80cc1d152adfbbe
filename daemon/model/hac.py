"""Newey-West (HAC) covariance of least-squares coefficients: standard errors that survive correlated residuals.

Why: a calibration's residual is not white (the interferometer wanders over tens of minutes, the
temperatures drift slowly), so the textbook iid covariance sigma²(AᵀA)⁻¹ understates the coefficients'
uncertainty ten-fold on the simulated cell, and p-values built on it call channels significant that the
data cannot separate. The heteroskedasticity-and-autocorrelation-consistent sandwich

    C = n/(n-k) · (AᵀA)⁻¹ S (AᵀA)⁻¹,   S = Σ_{l=-L..L} (1 - |l|/(L+1)) Σ_t u_t u_{t-l}ᵀ,  u_t = a_t e_t

(Bartlett kernel, k columns of A including the intercept) is the same as statsmodels'
``cov_type="HAC"`` with ``kernel="bartlett"``, ``use_correction=True``. Rows of different runs (several
data files fitted together) are independent: their cross products are left out of S.

The lag L follows Andrews (1991)'s AR(1) plug-in for the Bartlett kernel, L = floor(1.1447·(α·n)^(1/3)),
α = 4ρ²/((1-ρ)²(1+ρ)²), ρ the residual's lag-1 autocorrelation (:func:`andrews_lag`), stated in every
printout and model file that uses it. Why not Newey & West's fixed floor(4(n/100)^(2/9)): on the
simulated cell's 408-row calibration it gives L = 5 while the residual's lag-1 autocorrelation is
0.92-0.97 (the interferometer's wander lasts tens of steps), and over 12 seeds the spread of T1's
coefficient was 2.8x the standard error it printed; with the plug-in (L = 43-79) 1.2x.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from scipy import fft, special

#: frequency bins multiplied at once by :func:`hac_meat` (bounds its temporaries for a season of rows)
_BINS_PER_BLOCK = 65536
#: |ρ| is clipped here so a residual that barely changes row to row still gives a finite lag (then capped at n - 1)
MAX_ABS_RHO = 0.99


def lag1_autocorrelation(resid: np.ndarray, run_id: np.ndarray | None = None) -> float:
    """The residual's lag-1 autocorrelation over pairs of consecutive rows of the same run (0 if undefined)."""
    e = np.asarray(resid, dtype=np.float64)
    if e.size < 2:
        return 0.0
    ahead, behind = e[1:], e[:-1]
    if run_id is not None:
        same = run_id[1:] == run_id[:-1]
        ahead, behind = ahead[same], behind[same]
    denominator = float(e @ e)
    return float(ahead @ behind) / denominator if denominator > 0 else 0.0


def andrews_lag(resid: np.ndarray, run_id: np.ndarray | None = None) -> int:
    """Andrews (1991)'s AR(1) plug-in bandwidth for the Bartlett kernel, from the residual itself."""
    n = int(np.asarray(resid).shape[0])
    if n < 2:
        return 0
    rho = float(np.clip(lag1_autocorrelation(resid, run_id), -MAX_ABS_RHO, MAX_ABS_RHO))
    alpha = 4.0 * rho**2 / ((1.0 - rho) ** 2 * (1.0 + rho) ** 2)
    return int(min(n - 1, math.floor(1.1447 * (alpha * n) ** (1.0 / 3.0))))


def describe(lag: int) -> str:
    """How the standard errors were computed, as printouts and the model file say it."""
    return f"Newey-West HAC, Bartlett kernel, L={lag} (Andrews AR(1) plug-in)"


def hac_meat(scores: np.ndarray, lag: int, run_id: np.ndarray | None = None) -> np.ndarray:
    """S = Γ₀ + Σ_{l=1..L} w_l (Γ_l + Γ_lᵀ) of the per-row scores (n x k), Bartlett weights; pairs across runs left out.

    Computed in the frequency domain, O(n log n · k + n k²) whatever L (a season of rows has L in the
    thousands, where the sum over lags would take minutes): Σ_l v_l Γ_l = (1/N) Re Σ_f F(f) K(f) F(f)ᴴ with
    F the columns' DFT, zero-padded to N >= n + L so no product wraps around, and K the DFT of the weights
    (v₀ = 1/2). Runs are kept apart by L zero rows between them, which no lag can span.
    """
    u = np.asarray(scores, dtype=np.float64)
    if u.ndim == 1:
        u = u[:, None]
    lag = max(0, min(int(lag), u.shape[0] - 1))
    if run_id is not None and lag > 0:
        starts = np.flatnonzero(np.diff(run_id)) + 1
        u = np.insert(u, np.repeat(starts, lag), 0.0, axis=0)
    n, _ = u.shape
    size = fft.next_fast_len(n + lag + 1, real=True)
    weights = np.zeros(size)
    weights[: lag + 1] = 1.0 - np.arange(lag + 1) / (lag + 1.0)
    weights[0] = 0.5
    kernel = np.conj(fft.rfft(weights))  # Σ_l v_l e^{+2πi f l / N}
    # a column at a time, and the products a block of bins at a time: a season's rows hold one spectrum
    # and no padded or weighted copy of it
    spectrum = np.empty((size // 2 + 1, u.shape[1]), dtype=np.complex128)
    for j in range(u.shape[1]):
        spectrum[:, j] = fft.rfft(u[:, j], n=size)
    share = np.full(spectrum.shape[0], 2.0)  # the rfft's bins stand for themselves and their mirror image
    share[0] = 1.0
    if size % 2 == 0:
        share[-1] = 1.0
    weight = share * kernel
    half = np.zeros((u.shape[1], u.shape[1]))
    for start in range(0, spectrum.shape[0], _BINS_PER_BLOCK):
        block = spectrum[start:start + _BINS_PER_BLOCK]
        half += np.real((block * weight[start:start + _BINS_PER_BLOCK, None]).T @ np.conj(block))
    half /= size
    return np.asarray(half + half.T, dtype=np.float64)


def hac_covariance(A: np.ndarray, resid: np.ndarray, lag: int, *, n_params: int | None = None,
                   run_id: np.ndarray | None = None) -> np.ndarray:
    """HAC covariance of the least-squares coefficients of the columns of A (intercept among them or
    centred out: ``n_params`` counts it for the small-sample factor n/(n - n_params); default A's columns)."""
    n, k = A.shape
    n_params = k if n_params is None else n_params
    bread = np.linalg.pinv(A.T @ A)
    cov = bread @ hac_meat(A * resid[:, None], lag, run_id) @ bread.T
    if n > n_params:
        cov *= n / (n - n_params)
    return np.asarray(0.5 * (cov + cov.T), dtype=np.float64)


def run_ids(n_rows: int, run_slices: Sequence[slice]) -> np.ndarray | None:
    """A run number per row, or None for one run (every pair of rows may correlate)."""
    if len(run_slices) <= 1:
        return None
    ids = np.zeros(n_rows, dtype=np.int64)
    for i, part in enumerate(run_slices):
        ids[part] = i
    return ids


def t_p_values(coef: np.ndarray, se: np.ndarray, dof: int | np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two-sided t-test of each coefficient against 0 with ``dof`` (> 0; one for all, or per coefficient)
    residual degrees of freedom."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(se > 0, coef / se, np.where(coef == 0, 0.0, np.copysign(np.inf, coef)))
    p = np.minimum(2.0 * special.stdtr(dof, -np.abs(t)), 1.0)
    return t, p
