"""How uncertain a command is: the model file's ``covariance`` block, batch and streaming.

``q_sigma`` is the standard uncertainty of the TRUE error a command leaves (true attained position
minus target, when the command is the model's prediction). For a row with features f (the model's
terms in order, bias included)

    q_sigma = sqrt(f·C·f + s² + (κ·g)²)

How the parts are estimated from one calibration run, and why:

- The residual of a calibration is not white: the interferometer wanders (tens of nm over tens of
  minutes) besides its fast noise and the stage's landing error. It is modelled as white noise
  (sd ``s``) plus an Ornstein-Uhlenbeck wander (a continuous-time AR(1): sd w, time constant τ),
  independent between runs. (s, w, τ) are found by restricted maximum likelihood
  (:func:`fit_noise`, a Kalman filter whitens the rows): REML scores a noise model on what the
  regression leaves *accounting for what it absorbed*. That matters: the temperature terms and the
  bias soak up much of a slow wander, so neither the residual's RMS nor its lag-1 autocorrelation
  shows it, and the old AR(1) inflation (1 + ρ)/(1 - ρ) from the lag-1 ρ, diluted by the white part,
  understated the coefficients' uncertainty.
- The wander's variance beyond what a run shows is not measured: REML never sees a run's mean (the
  bias absorbs it), so the OU form extrapolates it, and most where τ is as long as the run (where
  the likelihood hardly tells τ apart: the realistic cell's calibrations land at the grid's top).
  Each weighed noise model's wander is therefore cut to its variance *within* the runs
  (:func:`within_runs`: 1 minus a run's mean correlation of rows, times w²); the calibration's
  offset then comes through C. Taken whole it booked each calibration an offset about twice what
  16 calibrations show (sqrt(f·C·f) 87 nm against a 39 nm SD of test 2's run offsets; ±2σ held
  99.8 % in range, RMS(e/σ) 0.55, tuning seeds 1000-1015, paper selection).
- ``f·C·f``: C is the covariance of the least-squares coefficients under that noise (the sandwich
  (AᵀA)⁻¹AᵀΣA(AᵀA)⁻¹). It is what the calibration's wander did to the bias and the temperature
  coefficients, which on a fresh run shows as an offset of the whole run (the between-calibration
  component: one run's steps share it), and it grows with the distance from the training data.
- ``s``: what a fresh run's steps carry again besides the offset C gives: the residual's white part
  AND its wander within a run, s² = white² + w². One instrument cannot tell its own wander from a
  slow effect no term models (a heat source no thermocouple sees, bending that is not the model's
  form, hysteresis the calibration's forward sweeps never showed). The stage's share recurs in a
  fresh run's TRUE error, so it is booked as the stage's. The block also keeps w (``wander_um``):
  an error *measured* by the interferometer is judged against sqrt(q_sigma² + w²), a conservative
  allowance for the instrument's own part (``validate`` on hardware), and the bias tracker's σ
  leaves it.
- ``κ·g``: the curvature a linear thermal model cannot see inside a narrow training range (the
  bracket's bending, which makes the paper's test 5 degrade). κ is the standard error, under the
  same noise model, of a quadratic term in the mean temperature T̄ of the model's channels fitted
  beside the model's terms: how much curvature the training data cannot rule out. g = (T̄ - lo)(T̄ -
  hi) outside the training range [lo, hi] of T̄ (the gap between a parabola and its chord), 0 inside.
  It stays wide on the realistic cell: a wander as slow as its calibration fakes a quadratic there
  (the fitted coefficient spreads 1.5 µm/°C² over the tuning calibrations, paper selection), while
  test 5's true error per °C² of g spreads 0.15 about the cell's own -0.32. Narrower choices that
  held the realistic cell failed the ideal one: the quadratic's Newey-West standard error
  (short-memory noise only) held 98.2 % of the realistic cell's test 5 (seeds 0-15, RMS(e/σ) 0.92)
  and 0 of 42 steps of the ideal cell's (whose calibration does see its bending:
  tests/calibration/test_uncertainty_truth.py), as a share of κ tuned on seeds 1000-1015 held 79.6 % on seeds 0-15: what
  a cell bends is not in one calibration. So κ is wide over calibrations of ONE cell (its own bending
  on every seed) and calibrated over the cells one calibration cannot tell apart: with each seed's
  bending drawn from N(-0.40, 0.763²) (0.763 the tuning calibrations' median κ), test 5's RMS(e/σ) is
  0.97 static and adaptive over seeds 0-47, where the one cell gives 0.48 and 0.78.

Nothing is scaled to make a benchmark pass: ``benchmarks/coverage.py`` measures ±2 q_sigma's coverage and
RMS(e/σ) over 48 calibrations against the true position, static and adaptive, over that population of
cells (the one cell's table beside), and exits 1 where it misses: in range over steps (90-98 %, 0.8-1.25),
out of range over runs, where a run's e/σ is one value (RMS(e/σ) 0.8-1.25 and the runs beyond 2σ within
the binomial interval of a calibrated σ; README, "Uncertainty of a command"). The block layout is
unchanged but for the optional ``wander_um`` (files without it load with their ids).

:func:`estimate` computes all of it from the final fit; :class:`SigmaStream` evaluates it per target
in the daemon. Kept apart from :mod:`nanodrift.model.model` so the block's checks, its estimation and
the streaming shortcut are read in one place.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from operator import mul
from typing import Any, TypeGuard

import numpy as np

from nanodrift.model.recurrence import decayed_cumsum
from nanodrift.model.terms import Term, TermStream, is_x_power

#: the largest relative asymmetry |C_ij - C_ji| / sqrt(C_ii C_jj) a file may carry (rounding of a symmetric matrix)
SYMMETRY_TOLERANCE = 1e-9
#: the most negative eigenvalue allowed of the correlation matrix (rounding of a positive semi-definite one)
PSD_TOLERANCE = 1e-8

Fail = Callable[[str], Exception]


@dataclass(frozen=True)
class Curvature:
    """The curvature allowance: κ (µm/°C²) on the mean of ``channels``, 0 inside ``range_c``."""

    channels: tuple[str, ...]
    range_c: tuple[float, float]
    sd_um_per_c2: float

    def gap(self, mean_c: np.ndarray | float) -> np.ndarray | float:
        """g = (T̄ - lo)(T̄ - hi) outside [lo, hi], else 0 (°C²)."""
        lo, hi = self.range_c
        return np.maximum((mean_c - lo) * (mean_c - hi), 0.0)

    def to_dict(self) -> dict[str, Any]:
        return {"channels": list(self.channels), "range_c": [float(v) for v in self.range_c],
                "sd_um_per_c2": float(self.sd_um_per_c2)}

    @classmethod
    def from_dict(cls, raw: Any, model_channels: Sequence[str], fail: Fail) -> Curvature:
        where = "covariance.curvature"
        if not isinstance(raw, dict):
            raise fail(f"{where} must be an object with channels, range_c and sd_um_per_c2, got {_kind(raw)}")
        unknown = sorted(set(raw) - {"channels", "range_c", "sd_um_per_c2"})
        if unknown:
            raise fail(f"{where}: unknown key(s) {', '.join(repr(k) for k in unknown)}")
        channels = raw.get("channels")
        if (not isinstance(channels, list) or not channels or not all(isinstance(c, str) for c in channels)
                or len(set(channels)) != len(channels) or not set(channels) <= set(model_channels)):
            raise fail(f"{where}.channels must be distinct channels the model reads ({list(model_channels)}), "
                       f"got {channels!r}")
        bounds = raw.get("range_c")
        if not (isinstance(bounds, list) and len(bounds) == 2 and all(_finite_number(v) for v in bounds)
                and bounds[0] <= bounds[1]):
            raise fail(f"{where}.range_c must be [low, high] in °C, got {bounds!r}")
        sd = raw.get("sd_um_per_c2")
        if not _finite_number(sd) or sd < 0:
            raise fail(f"{where}.sd_um_per_c2 must be a finite number >= 0, got {sd!r}")
        return cls(tuple(channels), (float(bounds[0]), float(bounds[1])), float(sd))


@dataclass(frozen=True, eq=False)
class Covariance:
    """The ``covariance`` block: C in the model's term order, s, and the optional curvature allowance."""

    matrix: np.ndarray  # (k, k), symmetric positive semi-definite, µm² per feature unit²
    residual_rms_um: float  # s
    curvature: Curvature | None = None
    #: the slow wander of the calibration residual (optional; files before it have none): the position
    #: sensor's, as far as one instrument can tell. A fresh run's error measured by that sensor carries
    #: it besides q_sigma; the true error does not.
    wander_um: float | None = None

    def __post_init__(self) -> None:
        m = np.array(self.matrix, dtype=np.float64)
        if m.ndim != 2 or m.shape[0] != m.shape[1]:
            raise ValueError(f"a covariance matrix must be square, got shape {m.shape}")
        m = 0.5 * (m + m.T)  # exactly symmetric: what is hashed and written is what is checked
        m.setflags(write=False)
        object.__setattr__(self, "matrix", m)
        object.__setattr__(self, "residual_rms_um", float(self.residual_rms_um))
        if self.wander_um is not None:
            object.__setattr__(self, "wander_um", float(self.wander_um))

    @property
    def size(self) -> int:
        return int(self.matrix.shape[0])

    def variance(self, features: np.ndarray, channels: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """``q_sigma²`` for every row of ``features`` (n, k); ``channels`` feed the curvature part."""
        f = np.atleast_2d(np.asarray(features, dtype=np.float64))
        s = np.float64(self.residual_rms_um)
        with np.errstate(over="ignore", invalid="ignore"):
            v: np.ndarray = np.maximum(np.einsum("ij,jk,ik->i", f, self.matrix, f), 0.0) + s * s
            if self.curvature is not None:
                if channels is None:
                    raise ValueError("the curvature part of q_sigma needs the temperature channels")
                mean = np.mean([np.asarray(channels[c], dtype=np.float64) for c in self.curvature.channels], axis=0)
                allowance = self.curvature.sd_um_per_c2 * self.curvature.gap(mean)
                v = v + allowance * allowance
        return v

    def content(self) -> dict[str, Any]:
        """What the model's id hashes and the file's block holds (besides the term names)."""
        out: dict[str, Any] = {"matrix": [[float(v) for v in row] for row in self.matrix],
                               "residual_rms_um": float(self.residual_rms_um)}
        if self.curvature is not None:
            out["curvature"] = self.curvature.to_dict()
        if self.wander_um is not None:
            out["wander_um"] = float(self.wander_um)
        return out

    def to_dict(self, names: Sequence[str]) -> dict[str, Any]:
        return {"terms": list(names), **self.content()}

    @classmethod
    def from_dict(cls, raw: Any, names: Sequence[str], channels: Sequence[str], fail: Fail) -> Covariance:
        """The file's ``covariance`` block, checked; ``fail(message)`` builds the error naming the file."""
        if not isinstance(raw, dict):
            raise fail(f"'covariance' must be an object with terms, matrix and residual_rms_um, got {_kind(raw)}")
        unknown = sorted(set(raw) - {"terms", "matrix", "residual_rms_um", "curvature", "wander_um"})
        if unknown:
            raise fail(f"covariance: unknown key(s) {', '.join(repr(k) for k in unknown)}")
        terms = raw.get("terms")
        if terms != list(names):
            raise fail(f"covariance.terms must list the model's terms in order {list(names)}, got {terms!r}")
        m = _matrix(raw.get("matrix"), names, fail)
        rms = raw.get("residual_rms_um")
        if not _finite_number(rms) or rms < 0:
            raise fail(f"covariance.residual_rms_um must be a finite number >= 0, got {rms!r}")
        curvature = None if raw.get("curvature") is None else Curvature.from_dict(raw["curvature"], channels, fail)
        wander = raw.get("wander_um")
        if wander is not None and (not _finite_number(wander) or wander < 0):
            raise fail(f"covariance.wander_um must be a finite number >= 0 (or absent), got {wander!r}")
        return cls(m, float(rms), curvature, None if wander is None else float(wander))


def _matrix(rows: Any, names: Sequence[str], fail: Fail) -> np.ndarray:
    k = len(names)
    if not isinstance(rows, list) or len(rows) != k:
        got = f"{len(rows)} rows" if isinstance(rows, list) else _kind(rows)
        raise fail(f"covariance.matrix must be {k} rows of {k} numbers (one per term), got {got}")
    for i, row in enumerate(rows):
        if not isinstance(row, list) or len(row) != k:
            got = f"{len(row)} numbers" if isinstance(row, list) else _kind(row)
            raise fail(f"covariance.matrix[{i}] must be {k} numbers, got {got}")
        for j, v in enumerate(row):
            if not _finite_number(v):
                raise fail(f"covariance.matrix[{i}][{j}] must be a finite number, got {v!r}")
    m = np.array(rows, dtype=np.float64)
    diag = np.diag(m)
    for i in range(k):
        if diag[i] < 0:
            raise fail(f"covariance.matrix[{i}][{i}] ({names[i]}) is a variance and must be >= 0, got {diag[i]!r}")
    with np.errstate(over="ignore", invalid="ignore", divide="ignore"):
        scale = np.sqrt(diag)
        scale = np.where(scale > 0, scale, 1.0)
        correlation = m / np.outer(scale, scale)
    if not np.all(np.isfinite(correlation)):
        raise fail("covariance.matrix overflows when scaled by its variances: not a covariance")
    asym = np.abs(correlation - correlation.T)
    row, col = np.unravel_index(int(np.argmax(asym)), asym.shape)
    i, j = int(row), int(col)
    if asym[i, j] > SYMMETRY_TOLERANCE:
        raise fail(f"covariance.matrix is not symmetric: [{i}][{j}] = {m[i, j]!r} but [{j}][{i}] = {m[j, i]!r}")
    if float(np.linalg.eigvalsh(0.5 * (correlation + correlation.T))[0]) < -PSD_TOLERANCE:
        raise fail("covariance.matrix is not positive semi-definite: some combination of the terms would "
                   "have a negative variance")
    return m


def _finite_number(value: Any) -> TypeGuard[int | float]:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)


def _kind(value: Any) -> str:
    return "null" if value is None else type(value).__name__


# --- estimation from the final fit ------------------------------------------------------------


@dataclass(frozen=True)
class Noise:
    """The calibration residual as white noise plus a wander (Ornstein-Uhlenbeck: a continuous AR(1)).

    ``white_um`` and ``wander_um`` are standard deviations, ``tau_s`` the wander's correlation time.
    """

    white_um: float
    wander_um: float
    tau_s: float


#: the grid :func:`fit_noise` searches: the wander's share of the residual variance, and τ in row spacings
_SHARES = np.array([0.0, 0.05, 0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.85, 0.9, 0.95, 0.98, 0.995])
_TAU_ROWS = np.geomspace(0.5, 400.0, 28)


def _row_decay(t_s: np.ndarray, run_slices: Sequence[slice], tau_s: np.ndarray) -> np.ndarray:
    """exp(-Δt/τ) from each row's predecessor in its run (0 at a run's first row): (rows, len(tau_s))."""
    dt = np.diff(np.asarray(t_s, dtype=np.float64), prepend=-np.inf)
    for part in run_slices:
        if part.stop > part.start:
            dt[part.start] = np.inf
    with np.errstate(invalid="ignore"):
        out: np.ndarray = np.nan_to_num(np.exp(-np.maximum(dt, 0.0)[:, None] / tau_s[None, :]), nan=0.0)
    return out


#: rows of whitened columns summed into the Gram matrices at once by :func:`_whitened_gram`
_GRAM_BLOCK_ROWS = 64


def _whitened_gram(M: np.ndarray, decay: np.ndarray, share: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gram matrices of the Kalman-whitened columns of ``M`` (rows, m) under unit-variance noise models.

    One model per entry of ``share`` (the wander's share of the variance) and column of ``decay``
    (exp(-Δt/τ) per row): the prediction errors of a scalar Kalman filter, each divided by its
    standard deviation, are Σ^(-1/2)·M. Returns Σ_rows z zᵀ (models, m, m) and each log det Σ.
    """
    n, m = M.shape
    g = share.size
    state = np.zeros((g, m))
    p = np.zeros(g)  # variance of the filter's estimate of the wander
    logdet = np.zeros(g)
    gram = np.zeros((g, m, m))
    white = 1.0 - share
    # the whitened rows are summed into the Gram matrices a block at a time (one batched matrix product, not
    # an outer product per row: most of the time a fit spends here); the filter itself is row by row
    block = np.empty((g, m, _GRAM_BLOCK_ROWS))
    for i in range(n):
        a = decay[i]
        p_pred = a * a * p + share * (1.0 - a * a)
        f = p_pred + white
        pred = a[:, None] * state
        e = M[i][None, :] - pred
        gain = p_pred / f
        state = pred + gain[:, None] * e
        p = (1.0 - gain) * p_pred
        logdet += np.log(f)
        filled = i % _GRAM_BLOCK_ROWS
        block[:, :, filled] = e / np.sqrt(f)[:, None]
        if filled == _GRAM_BLOCK_ROWS - 1 or i == n - 1:
            rows = block[:, :, : filled + 1]
            gram += rows @ rows.transpose(0, 2, 1)
    return gram, logdet


#: rows beyond which :func:`fit_noise` scores the noise models on windows of the rows (:func:`reml_rows`)
REML_MAX_ROWS = 16384
#: rows per window: five times the grid's longest time constant (400 row spacings)
REML_WINDOW_ROWS = 2048


def reml_rows(n: int, run_slices: Sequence[slice]) -> tuple[np.ndarray | None, list[slice]]:
    """The rows :func:`fit_noise` scores on, and their runs: all of them (None) up to :data:`REML_MAX_ROWS`,
    else REML_MAX_ROWS / REML_WINDOW_ROWS evenly spaced windows of consecutive rows, split where a run
    ends; each piece is a run of its own (the wander restarts), numbered in the rows picked."""
    if n <= REML_MAX_ROWS:
        return None, list(run_slices)
    windows = REML_MAX_ROWS // REML_WINDOW_ROWS
    starts = np.linspace(0, n - REML_WINDOW_ROWS, windows).round().astype(np.int64)
    picked: list[np.ndarray] = []
    pieces: list[slice] = []
    taken = 0
    for start in starts.tolist():
        for part in run_slices:
            low, high = max(start, part.start), min(start + REML_WINDOW_ROWS, part.stop)
            if high > low:
                picked.append(np.arange(low, high))
                pieces.append(slice(taken, taken + high - low))
                taken += high - low
    return np.concatenate(picked), pieces


def fit_noise(A: np.ndarray, y: np.ndarray, t_s: np.ndarray, run_slices: Sequence[slice]) -> list[tuple[float, Noise]]:
    """Noise models (white plus wander) for the residual of y on A, each with its weight.

    REML (restricted maximum likelihood) judges a noise model on what the regression leaves,
    accounting for what it absorbed: a wander slow enough to look like the temperatures is partly
    fitted away, so the residual alone (its RMS, its lag-1 autocorrelation) understates it. A few
    hours of calibration pin how the variance splits into white and wander, but hardly the wander's
    time constant (the likelihood is flat over a factor of ten in τ, and a short τ makes the bias
    look better known than a long one). So for each τ the split is the most likely one (profile
    likelihood), and the τs are kept with their likelihoods as weights (a flat prior in log τ)
    rather than betting on the best one. The grid spans the wander's share of the variance
    (0..99.5 %) and τ from half a row spacing to 400 of them. The weights sum to 1; models under
    0.1 % of the best one's weight are dropped.

    Beyond :data:`REML_MAX_ROWS` rows (a season of records) the likelihood is that of
    :func:`reml_rows`' evenly spaced windows, each its own run: the filter runs row by row over every
    model of the grid, and a few thousand rows pin the noise as well as a million.
    """
    rows, run_slices = reml_rows(y.shape[0], run_slices)
    if rows is not None:
        A, y, t_s = A[rows], y[rows], np.asarray(t_s)[rows]
    n = y.shape[0]
    basis, _ = np.linalg.qr(A)  # the same column space, well conditioned: REML depends on nothing else
    p = basis.shape[1]
    if n <= p + 2:
        r = y - basis @ (basis.T @ y)
        return [(1.0, Noise(float(np.sqrt(r @ r / max(n - p, 1))), 0.0, 0.0))]
    t = np.asarray(t_s, dtype=np.float64)
    spacing = float(np.median(np.diff(t)))
    spacing = spacing if math.isfinite(spacing) and spacing > 0 else 1.0
    share = np.repeat(_SHARES, _TAU_ROWS.size)
    tau = np.tile(_TAU_ROWS * spacing, _SHARES.size)
    y_scale = float(np.std(y)) or 1.0
    gram, logdet = _whitened_gram(np.column_stack([basis, y / y_scale]), _row_decay(t, run_slices, tau), share)
    score = np.full(share.size, np.inf)
    variance = np.zeros(share.size)
    for k in range(share.size):
        g_aa, g_ay, g_yy = gram[k, :p, :p], gram[k, :p, p], gram[k, p, p]
        sign, log_gram = np.linalg.slogdet(g_aa)
        rss = float(g_yy - g_ay @ np.linalg.solve(g_aa, g_ay)) if sign > 0 else math.nan
        if rss > 0:  # False for nan
            score[k] = (n - p) * math.log(rss / (n - p)) + float(logdet[k]) + log_gram  # -2 log likelihood
            variance[k] = rss / (n - p) * y_scale * y_scale
    if not np.isfinite(score).any():
        return [(1.0, Noise(0.0, 0.0, 0.0))]
    # per τ the best share (profile likelihood), then every τ weighted by its likelihood
    by_tau = score.reshape(_SHARES.size, _TAU_ROWS.size)
    profile = np.full(score.size, np.inf)
    best_share = np.argmin(by_tau, axis=0)
    for j, i in enumerate(best_share):
        profile[i * _TAU_ROWS.size + j] = by_tau[i, j]
    weight = np.exp(-0.5 * (profile - score.min()))
    keep = np.flatnonzero(weight >= 1e-3)
    total = float(weight[keep].sum())
    return [(float(weight[k]) / total,
             Noise(math.sqrt(variance[k] * (1.0 - share[k])), math.sqrt(variance[k] * share[k]),
                   float(tau[k]) if share[k] > 0 else 0.0))
            for k in keep]


def noise_gram(M: np.ndarray, t_s: np.ndarray, run_slices: Sequence[slice], noise: Noise) -> np.ndarray:
    """Mᵀ·Σ·M, a column of Σ·M at a time: a season's rows never hold Σ·M whole."""
    M = np.asarray(M, dtype=np.float64)
    times = _NoiseTimes(t_s, run_slices, noise)
    gram = np.empty((M.shape[1], M.shape[1]))
    for j in range(M.shape[1]):
        gram[:, j] = M.T @ times(M[:, j])
    return gram


class _NoiseTimes:
    """Σ·m for one column m. The wander's part sums exp(-|t_i - t_j|/τ)·m_j over the rows j of i's run: a
    forward and a backward :func:`~nanodrift.model.recurrence.decayed_cumsum` (no loop over rows)."""

    def __init__(self, t_s: np.ndarray, run_slices: Sequence[slice], noise: Noise) -> None:
        self.noise = noise
        self.wander = noise.wander_um > 0 and noise.tau_s > 0 and np.asarray(t_s).shape[0] > 0
        if self.wander:
            self.decay = _row_decay(t_s, run_slices, np.array([noise.tau_s]))[:, 0]  # 0 at each run's first row
            self.backward_decay = np.concatenate(([0.0], self.decay[:0:-1]))  # the successor's factor, read backwards

    def __call__(self, column: np.ndarray) -> np.ndarray:
        out = self.noise.white_um**2 * column
        if self.wander:
            summed = decayed_cumsum(column, self.decay)  # Σ_j<=i exp(-(t_i - t_j)/τ) m_j, within the run
            summed += decayed_cumsum(column[::-1], self.backward_decay)[::-1]  # + Σ_j>=i exp(-(t_j - t_i)/τ) m_j
            summed -= column  # m_i was counted twice
            out += self.noise.wander_um**2 * summed
        return out


def _sandwich(gram: np.ndarray, meat: np.ndarray) -> np.ndarray:
    """(AᵀA)⁻¹ (AᵀΣA) (AᵀA)⁻¹ from AᵀA and AᵀΣA, on unit-norm columns (x³ and a bias differ by 10⁸)."""
    scale = np.sqrt(np.diag(gram))
    scale[scale == 0] = 1.0
    outer = np.outer(scale, scale)
    bread = np.linalg.pinv(gram / outer)
    cov = bread @ (meat / outer) @ bread / outer
    return np.asarray(0.5 * (cov + cov.T))


def estimate(X: np.ndarray, y: np.ndarray, t_s: np.ndarray, run_slices: Sequence[slice],
             temperatures: Mapping[str, np.ndarray]) -> tuple[np.ndarray, float, Curvature | None, Noise]:
    """The block's parts for a least-squares fit of ``y`` on ``X`` (plus intercept).

    ``t_s`` the rows' times and ``run_slices`` the runs (the wander restarts at each); ``temperatures``
    the channels the model reads (none: no curvature part). Returns (C, s, curvature, noise): C in
    the fit's order (the columns, then the intercept) and s (white part and wander), averaged over the
    noise models :func:`fit_noise` weighs (variances averaged), each model's wander cut to what varies
    within the runs (:func:`within_runs`), and the curvature's κ under the same noise; that average
    noise. The noise is what neither the model's terms nor the curvature explain.
    """
    n, k = y.shape[0], X.shape[1] + 1
    bounds = None
    if temperatures:
        mean = np.mean([np.asarray(v, dtype=np.float64) for v in temperatures.values()], axis=0)
        lo, hi = float(mean.min()), float(mean.max())
        if hi > lo and n > k + 2:
            bounds = (lo, hi)
    # B = [X, 1, (T̄ - centre)²]: the model's columns A = B[:, :k] and, with a curvature part, the quadratic
    B = np.empty((n, k + (bounds is not None)), order="F")
    B[:, :k - 1] = X
    B[:, k - 1] = 1.0
    if bounds is not None:
        B[:, k] = (mean - 0.5 * (bounds[0] + bounds[1])) ** 2
    gram = B.T @ B
    cov = np.zeros((k, k))
    white2 = wander2 = tau = var_quad = 0.0
    for weight, fitted in fit_noise(B, y, t_s, run_slices):
        noise = within_runs(fitted, t_s, run_slices)
        meat = noise_gram(B, t_s, run_slices, noise)  # BᵀΣB once; its first k rows and columns are AᵀΣA
        cov += weight * _sandwich(gram[:k, :k], meat[:k, :k])  # C and κ² averaged over the weighed models
        if bounds is not None:
            var_quad += weight * float(_sandwich(gram, meat)[-1, -1])
        white2 += weight * noise.white_um**2
        wander2 += weight * noise.wander_um**2
        tau += weight * noise.tau_s
    curvature = None
    if bounds is not None:  # κ: the standard error of a quadratic term in T̄ fitted beside the model's
        curvature = Curvature(tuple(temperatures), bounds, math.sqrt(max(var_quad, 0.0)))
    # s: the white part and the wander within a run, both recurring in a fresh run as far as one instrument can tell
    return cov, math.sqrt(white2 + wander2), curvature, Noise(math.sqrt(white2), math.sqrt(wander2), tau)


def within_run_share(t_s: np.ndarray, run_slices: Sequence[slice], tau_s: float) -> float:
    """The share of a unit wander's variance (time constant ``tau_s``) that varies within the runs: 1 minus the
    mean correlation of a run's rows with each other, averaged over the runs by their rows (0 for one row)."""
    n = np.asarray(t_s).shape[0]
    if n == 0 or not tau_s > 0:
        return 1.0
    correlated = _NoiseTimes(t_s, run_slices, Noise(0.0, 1.0, tau_s))(np.ones(n))  # R·1, R the correlation
    mean_correlation: float = sum(float(correlated[part].sum()) / (part.stop - part.start)
                                  for part in run_slices if part.stop > part.start)
    return float(max(0.0, 1.0 - mean_correlation / n))


def within_runs(noise: Noise, t_s: np.ndarray, run_slices: Sequence[slice]) -> Noise:
    """``noise`` with the wander's variance cut to what the calibration's runs show varying within them: what the
    data measured (why: the module docstring; README, σ over calibrations)."""
    if noise.wander_um <= 0 or noise.tau_s <= 0:
        return noise
    share = within_run_share(t_s, run_slices, noise.tau_s)
    return Noise(noise.white_um, noise.wander_um * math.sqrt(share), noise.tau_s)


# --- streaming ---------------------------------------------------------------------------------


class SigmaStream:
    """``q_sigma`` per target in a few additions, for :class:`nanodrift.model.model.Evaluator`.

    The terms split three ways: *static* ones depend only on temperatures and time (channels, lags,
    rates, the bias), *powers* of x, and *other* target- or motion-dependent ones (``dir``,
    ``creep``, ``x*T1``). After a temperature sample the static features s are fixed, so ``s·C·s``,
    ``C·s`` and the curvature part are computed once (lazily, at the first target after the
    sample), and what depends on x through powers is folded into one polynomial in x: a target
    costs a Horner evaluation plus a few products per *other* term.
    """

    __slots__ = ("_c_oo", "_c_so", "_c_ss", "_cross", "_curvature", "_dirty", "_latest", "_others", "_poly",
                 "_powers_k", "_pp_poly", "_sp", "_static", "_var0", "_var_o")

    def __init__(self, terms: Sequence[Term], streams: Sequence[TermStream], covariance: Covariance) -> None:
        c = covariance.matrix
        static = [i for i, t in enumerate(terms) if not t.uses_x]
        powers = [i for i, t in enumerate(terms) if is_x_power(t)]
        others = [i for i, t in enumerate(terms) if t.uses_x and not is_x_power(t)]
        self._static = [streams[i] for i in static]
        self._others = [streams[i] for i in others]
        self._powers_k = [t.k for t in terms if is_x_power(t)]
        degree = max(self._powers_k, default=0)
        pp = [0.0] * (2 * degree + 1)  # power x power: constant in time
        for a, i in enumerate(powers):
            for b, j in enumerate(powers):
                pp[self._powers_k[a] + self._powers_k[b]] += float(c[i, j])
        self._pp_poly = pp
        self._c_ss = [[float(c[i, j]) for j in static] for i in static]
        self._sp = [[float(c[i, j]) for i in static] for j in powers]  # per power: its column over static
        self._c_so = [[float(c[i, j]) for i in static] for j in others]  # per other: its column over static
        self._c_oo = [[float(c[i, j]) for j in others] for i in others]
        self._cross = []  # other x power: per other term, a polynomial in x (highest power first)
        for o in others:
            poly = [0.0] * (degree + 1)
            for a, j in enumerate(powers):
                poly[self._powers_k[a]] += float(c[o, j])
            self._cross.append(tuple(reversed(poly)))
        self._var0 = covariance.residual_rms_um * covariance.residual_rms_um
        self._curvature = covariance.curvature
        self._latest: dict[str, float] = {}
        self._poly: tuple[float, ...] = ()
        self._var_o: list[float] = []
        self._dirty = True

    def observe(self, temps: Mapping[str, float]) -> None:
        """A temperature sample arrived: the static part is recomputed at the next target."""
        if self._curvature is not None:
            self._latest.update(temps)
        self._dirty = True

    def _refresh(self) -> None:
        s = [stream.value(0.0, 0.0) for stream in self._static]
        ss = sum(map(mul, s, [sum(map(mul, row, s)) for row in self._c_ss]))
        poly = list(self._pp_poly)
        poly[0] += ss + self._var0
        cv = self._curvature
        if cv is not None:
            latest = self._latest
            mean = sum(latest.get(ch, math.nan) for ch in cv.channels) / len(cv.channels)
            lo, hi = cv.range_c
            gap = (mean - lo) * (mean - hi)
            if gap > 0.0 or gap != gap:  # outside the range (or unknown: nan)
                allowance = cv.sd_um_per_c2 * gap
                poly[0] += allowance * allowance
        for k, column in zip(self._powers_k, self._sp, strict=True):
            poly[k] += 2.0 * sum(map(mul, column, s))
        self._poly = tuple(reversed(poly))
        self._var_o = [sum(map(mul, column, s)) for column in self._c_so]
        self._dirty = False

    def sigma(self, t: float, x: float) -> float:
        if self._dirty:
            self._refresh()
        var = 0.0
        for coef in self._poly:
            var = var * x + coef
        if self._others:
            v = [stream.value(t, x) for stream in self._others]
            for o, vo in enumerate(v):
                cross = 0.0
                for coef in self._cross[o]:
                    cross = cross * x + coef
                row = self._c_oo[o]
                var += vo * (2.0 * (self._var_o[o] + cross) + sum(row[p] * vp for p, vp in enumerate(v)))
        return math.sqrt(max(var, 0.0))  # nan stays nan (a channel never observed)
