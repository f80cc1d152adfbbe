"""The first-order recurrence y_i = d_i·y_(i-1) + u_i over a million rows without a Python loop per row.

Why: the noise model's covariance (Σ·M in :mod:`nanodrift.model.uncertainty`) sums every row's
neighbours with weights exp(-|t_i - t_j|/τ), which is this recurrence run forwards and backwards. A
loop per row costs seconds per column at a season's million rows; here a run of equal factors goes
to ``scipy.signal.lfilter`` (the same recurrence in C) and unequal ones use the closed form
y_i = W_i (y_c + Σ_(j≤i) u_j / W_j), W_i = Π_(c<l≤i) d_l, in chunks short enough that 1/W stays finite.
"""

from __future__ import annotations

import numpy as np

#: a chunk of the closed form ends before Π d falls below exp(-this): 1/W then stays far from overflow
_MAX_LOG_SPAN = 500.0


def decayed_cumsum(values: np.ndarray, decay: np.ndarray) -> np.ndarray:
    """y_i = decay_i·y_(i-1) + values_i (y_(-1) = 0), down the rows of ``values`` (n,) or (n, m).

    ``decay``: one factor per row in [0, 1]; a 0 restarts the sum (a run's first row).
    """
    u = np.asarray(values, dtype=np.float64)
    d = np.asarray(decay, dtype=np.float64)
    if d.shape != u.shape[:1]:
        raise ValueError(f"decay has shape {d.shape}, expected one factor per row {u.shape[:1]}")
    out = np.empty_like(u)
    n = u.shape[0]
    starts = np.flatnonzero(d == 0.0).tolist()
    if not starts or starts[0] != 0:
        starts.insert(0, 0)
    for start, stop in zip(starts, [*starts[1:], n], strict=True):
        _restarted(u[start:stop], d[start:stop], out[start:stop])
    return out


def _restarted(u: np.ndarray, d: np.ndarray, out: np.ndarray) -> None:
    """One stretch that starts afresh (its first factor is ignored) and has no zero factor after it."""
    n = u.shape[0]
    if n == 0:
        return
    rest = d[1:]
    if rest.size == 0 or float(rest.max() - rest.min()) == 0.0:
        from scipy.signal import lfilter  # a second to import: only when a series is summed

        factor = float(rest[0]) if rest.size else 0.0
        out[...] = lfilter([1.0], [1.0, -factor], u, axis=0)
        return
    log_w = np.concatenate(([0.0], np.cumsum(np.log(rest))))
    start, carry = 0, np.zeros(u.shape[1:])
    while start < n:
        # the chunk keeps log W within _MAX_LOG_SPAN of its first row; at least one row
        stop = max(int(np.searchsorted(-log_w, -log_w[start] + _MAX_LOG_SPAN, side="right")), start + 1)
        w = np.exp(log_w[start:stop] - log_w[start])
        w_cols = w.reshape(-1, *([1] * (u.ndim - 1)))
        head = carry * (d[start] if start else 0.0)  # the state carried into the chunk's first row
        chunk = w_cols * (np.cumsum(u[start:stop] / w_cols, axis=0) + head)
        out[start:stop] = chunk
        carry = chunk[-1]
        start = stop
