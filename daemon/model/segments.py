"""Several recorded runs fitted together (a calibration plus days of recorded operation).

Each run keeps its own time: the runs are not one continuous series, so a stateful term (a lag, the
direction of motion, creep) starts afresh at each run's first row, and anything measured in time
(a drift, a span) is measured within a run. A series made of several runs says which run each row
came from with an optional ``segment`` array (:class:`nanodrift.calibration.dataset.Dataset` has one;
rows of one run are contiguous); without it the series is one run and nothing changes.
"""

from __future__ import annotations

import itertools
from collections.abc import Mapping, Sequence

import numpy as np

from nanodrift.model.series import Series
from nanodrift.model.terms import Term, position_key


def segment_slices(segment: np.ndarray | None, n: int | None = None) -> list[slice]:
    """The row ranges of consecutive equal ``segment`` values (one range of ``n`` rows when None)."""
    if segment is None:
        return [slice(0, int(n or 0))]
    segment = np.asarray(segment)
    if segment.size == 0:
        return [slice(0, 0)]
    cuts = (np.flatnonzero(segment[1:] != segment[:-1]) + 1).tolist()
    edges = [0, *cuts, int(segment.size)]
    return [slice(a, b) for a, b in itertools.pairwise(edges)]


def runs(data: Series) -> list[slice]:
    """The row range of each run in ``data`` (one range for a single run)."""
    return segment_slices(getattr(data, "segment", None), len(data))


def _inputs(term: Term, data: Series) -> Mapping[str, np.ndarray]:
    """The channels ``term.batch`` reads: a multi-axis term also gets the axes' positions (``<axis>_um``)."""
    if not term.axes:
        return data.channels
    positions = getattr(data, "positions", None) or {}
    missing = [a for a in term.axes if a not in positions]
    if missing:
        raise KeyError(f"{data.source} has no position of axis {missing[0]!r} that term {term.name} reads")
    return {**data.channels, **{position_key(a): positions[a] for a in term.axes}}


def features(term: Term, data: Series) -> np.ndarray:
    """``term.batch`` over ``data``, restarted at each run's first row."""
    parts = runs(data)
    inputs = _inputs(term, data)
    if len(parts) == 1:
        return term.batch(data.t, data.x, inputs)
    t, x = np.asarray(data.t), np.asarray(data.x)
    return np.concatenate([
        np.asarray(term.batch(t[p], x[p], {c: np.asarray(v)[p] for c, v in inputs.items()}),
                   dtype=np.float64)
        for p in parts
    ])


def design_matrix(terms: Sequence[Term], data: Series) -> np.ndarray:
    """The :func:`features` of ``terms`` as the columns of one (rows, terms) float64 array.

    Column-major and filled a column at a time: a season of rows never holds the features twice, and
    each column is written where it lies.
    """
    X = np.empty((len(data), len(terms)), order="F")
    for j, term in enumerate(terms):
        X[:, j] = features(term, data)
    return X


def first_rows(data: Series) -> np.ndarray:
    """For every row, the index of its run's first row."""
    out = np.zeros(len(data), dtype=np.int64)
    for p in runs(data):
        out[p] = p.start
    return out


def run_time_s(data: Series) -> np.ndarray:
    """Time since the start of each row's run (s)."""
    t = np.asarray(data.t, dtype=np.float64)
    return t - t[first_rows(data)] if t.size else t


def spans_s(data: Series) -> list[float]:
    """How long each run lasted (s): its last row's time minus its first's."""
    t = np.asarray(data.t, dtype=np.float64)
    return [float(t[p.stop - 1] - t[p.start]) for p in runs(data) if p.stop > p.start]
