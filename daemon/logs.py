"""Logging: JSON lines for journald (stderr not a terminal), readable lines on a terminal.

Refused targets are logged through a token bucket: a client flooding bad payloads costs a summary
line ("N suppressed") per interval instead of one line each, so it cannot fill the disk.
"""

from __future__ import annotations

import logging
import sys
import time
from collections.abc import Callable
from typing import Any

import structlog


def configure_logging(level: str = "info", json_lines: bool | None = None) -> None:
    """Set up structlog for the daemon; ``json_lines`` None means: JSON unless stderr is a tty."""
    if json_lines is None:
        json_lines = not sys.stderr.isatty()
    renderer: Any = structlog.processors.JSONRenderer() if json_lines else structlog.dev.ConsoleRenderer(
        colors=False
    )
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            structlog.processors.add_log_level,
            structlog.processors.TimeStamper(fmt="iso", utc=True),
            structlog.processors.format_exc_info,
            renderer,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(logging.getLevelNamesMapping()[level.upper()]),
        logger_factory=structlog.PrintLoggerFactory(file=sys.stderr),
        cache_logger_on_first_use=False,
    )


def get_logger(name: str = "nanodrift") -> Any:
    return structlog.get_logger(name)


class RateLimiter:
    """Token bucket: ``rate`` events per second, bursts of ``burst``; counts what it suppressed."""

    def __init__(self, rate: float = 5.0, burst: int = 20, clock: Callable[[], float] = time.monotonic) -> None:
        self.rate = rate
        self.burst = burst
        self._clock = clock
        self._tokens = float(burst)
        self._last = clock()
        self.suppressed = 0

    def allow(self) -> bool:
        now = self._clock()
        self._tokens = min(self.burst, self._tokens + (now - self._last) * self.rate)
        self._last = now
        if self._tokens >= 1.0:
            self._tokens -= 1.0
            return True
        self.suppressed += 1
        return False

    def take_suppressed(self) -> int:
        count, self.suppressed = self.suppressed, 0
        return count


class RateLimitedLog:
    """Log an event through a :class:`RateLimiter`; the next allowed line (or ``flush``) says how
    many were dropped in between."""

    def __init__(self, logger: Any, event: str, limiter: RateLimiter | None = None, level: str = "warning") -> None:
        self._log = getattr(logger, level)
        self._event = event
        self.limiter = limiter or RateLimiter()

    def __call__(self, **fields: Any) -> None:
        if self.limiter.allow():
            dropped = self.limiter.take_suppressed()
            if dropped:
                fields["suppressed_before"] = dropped
            self._log(self._event, **fields)

    def flush(self) -> None:
        """Report suppressed lines (called periodically so a flood that stops is still summarised)."""
        dropped = self.limiter.take_suppressed()
        if dropped:
            self._log(f"{self._event}_suppressed", suppressed=dropped)
