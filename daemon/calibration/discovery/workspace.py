"""The working model as per-block Gram matrices of standardised columns against its residual.

Every candidate is judged through these (so no large numbers cancel): one pass over the rows per
candidate column, which keeps 1e6 rows within seconds.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np


def standardise(cols: np.ndarray) -> np.ndarray:
    if cols.shape[1] == 1:  # the common case, without a second copy
        col = cols[:, 0]
        mean, scale = float(col.mean()), float(col.std())
        return ((col - mean) / (scale or 1.0))[:, None]
    mean = cols.mean(axis=0)
    scale = cols.std(axis=0)
    scale[scale == 0] = 1.0
    standard: np.ndarray = (cols - mean) / scale
    return standard


class Workspace:
    """The working model's columns on the data, as per-block Gram matrices against its residual.

    ``A = [1, Z, r]`` with Z the standardised working columns and r the residual of the working
    model fitted on all rows; blocks are contiguous time blocks (the held-out folds). Adding columns
    F needs only ``A_b' F_b`` and ``F_b' F_b``: one pass over the rows per candidate column.
    """

    def __init__(self, columns: np.ndarray, y: np.ndarray, folds: np.ndarray) -> None:
        n = y.shape[0]
        self.n = n
        starts = np.flatnonzero(np.diff(folds, prepend=folds[0] - 1) != 0)
        self.bounds = [(int(a), int(b)) for a, b in zip(starts, [*starts[1:], n], strict=True)]
        Z = standardise(columns) if columns.shape[1] else np.empty((n, 0))
        base = np.column_stack([np.ones(n), Z])
        coef, *_ = np.linalg.lstsq(base, y, rcond=None)
        self.coef = coef  # on [1, Z]: y = [1, Z] coef + residual
        self.residual = y - base @ coef
        self.A = np.column_stack([base, self.residual])
        self.G = np.stack([self.A[a:b].T @ self.A[a:b] for a, b in self.bounds])
        self.k = base.shape[1]  # columns incl. intercept

    @property
    def sse(self) -> float:
        return float(self.residual @ self.residual)

    def _augmented(self, F: np.ndarray | None, drop: Sequence[int]) -> tuple[np.ndarray, list[int]]:
        """Per-block Gram of [1, Z, F, r] and the regressor indices to use."""
        k = self.k
        m = 0 if F is None else F.shape[1]
        size = k + m + 1
        G = np.zeros((len(self.bounds), size, size))
        idx_old = [*range(k), k + m]  # positions of [1, Z] and r in the new matrix
        new = list(range(k, k + m))
        G[np.ix_(range(len(self.bounds)), idx_old, idx_old)] = self.G
        if m:
            assert F is not None
            for bi, (a, b) in enumerate(self.bounds):
                cross = self.A[a:b].T @ F[a:b]  # (k+1, m)
                g = G[bi]
                g[k:k + m, k:k + m] = F[a:b].T @ F[a:b]
                g[np.ix_(idx_old, new)] = cross
                g[np.ix_(new, idx_old)] = cross.T
        dropped = [1 + d for d in drop]
        if dropped:  # without those columns the target is r plus what they explained
            t = k + m
            b = self.coef[dropped]
            for g in G:
                col = g[:, t] + g[:, dropped] @ b
                col[t] = g[t, t] + 2.0 * b @ g[dropped, t] + b @ g[np.ix_(dropped, dropped)] @ b
                g[:, t] = col
                g[t, :] = col
        regressors = [i for i in range(k + m) if i not in dropped]
        return G, regressors

    @staticmethod
    def _solve(G: np.ndarray, S: list[int], target: int) -> np.ndarray:
        gss = G[np.ix_(S, S)]
        scale = np.sqrt(np.maximum(np.diag(gss), 1e-300))
        beta, *_ = np.linalg.lstsq(gss / np.outer(scale, scale), G[S, target] / scale, rcond=1e-12)
        solution: np.ndarray = beta / scale
        return solution

    def sse_with(self, F: np.ndarray) -> float:
        """Training SSE (all rows) of the working model plus columns F: one pass, no per-block split."""
        k, m = self.k, F.shape[1]
        total = np.zeros((k + m + 1, k + m + 1))
        old = [*range(k), k + m]
        total[np.ix_(old, old)] = self.G.sum(axis=0)
        cross = self.A.T @ F
        total[np.ix_(old, range(k, k + m))] = cross
        total[np.ix_(range(k, k + m), old)] = cross.T
        total[k:k + m, k:k + m] = F.T @ F
        S = list(range(k + m))
        beta = self._solve(total, S, k + m)
        return float(total[k + m, k + m] - beta @ total[S, k + m])

    def evaluate(self, F: np.ndarray | None, drop: Sequence[int] = ()) -> tuple[float, np.ndarray, int]:
        """(training SSE, held-out SSE per block, regressors incl. intercept)."""
        total, S, _, held = self._by_block(F, drop)
        target = total.shape[0] - 1
        beta = self._solve(total, S, target)
        sse = float(total[target, target] - beta @ total[S, target])
        return max(sse, 0.0), held, len(S)

    def fold_errors(self, F: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Per block: (training SSE of the fit on the other blocks, over those blocks; held-out SSE of the block)."""
        _, _, train_sse, held = self._by_block(F, ())
        return train_sse, held

    def _by_block(self, F: np.ndarray | None, drop: Sequence[int]
                  ) -> tuple[np.ndarray, list[int], np.ndarray, np.ndarray]:
        """The Gram over all rows, the regressors, and per block :meth:`fold_errors`' two SSEs."""
        G, S = self._augmented(F, drop)
        total = G.sum(axis=0)
        target = total.shape[0] - 1
        train_sse, held = np.empty(len(self.bounds)), np.empty(len(self.bounds))
        for bi in range(len(self.bounds)):
            train = total - G[bi]
            b = self._solve(train, S, target)
            train_sse[bi] = max(float(train[target, target] - b @ train[S, target]), 0.0)
            g = G[bi]
            held[bi] = max(float(g[target, target] - 2.0 * b @ g[S, target] + b @ g[np.ix_(S, S)] @ b), 0.0)
        return total, S, train_sse, held

    def residual_with(self, F: np.ndarray | None, drop: Sequence[int] = ()) -> np.ndarray:
        G, S = self._augmented(F, drop)
        total = G.sum(axis=0)
        beta = self._solve(total, S, total.shape[0] - 1)
        full = np.zeros(self.k + (0 if F is None else F.shape[1]))
        full[S] = beta
        out: np.ndarray = self.residual - self.A[:, : self.k] @ full[: self.k]
        if F is not None:
            out -= F @ full[self.k:]
        return out
