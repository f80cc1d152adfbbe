"""The answer latency the target path measures for the metrics (:mod:`nanodrift.service.metrics` exposes it).

Apart from the metrics so that the daemon imports prometheus_client (and the http, email and urllib modules it
loads) only when ``[metrics] listen`` is set: the runner imports :mod:`nanodrift.service.metrics_server` then.
"""

from __future__ import annotations

import bisect
import itertools
import threading

#: answer latency buckets (seconds): the daemon answers in tens to hundreds of µs on a loaded machine
LATENCY_BUCKETS_S = (25e-6, 50e-6, 100e-6, 200e-6, 500e-6, 1e-3, 2e-3, 5e-3, 10e-3, 50e-3, 0.25, 1.0)


class AnswerLatency:
    """Answer latencies counted into :data:`LATENCY_BUCKETS_S` (non-cumulative; the last slot is +Inf)."""

    __slots__ = ("_counts", "_lock", "_sum_s")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts = [0] * (len(LATENCY_BUCKETS_S) + 1)
        self._sum_s = 0.0

    def observe(self, seconds: float) -> None:
        index = bisect.bisect_left(LATENCY_BUCKETS_S, seconds)  # the first bucket with le >= seconds
        with self._lock:
            self._counts[index] += 1
            self._sum_s += seconds

    def snapshot(self) -> tuple[list[int], float]:
        """Cumulative counts per bucket (ending with +Inf, the total) and the sum."""
        with self._lock:
            counts, total = list(self._counts), self._sum_s
        return list(itertools.accumulate(counts)), total
