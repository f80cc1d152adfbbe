"""Logging: JSON lines for journald (stderr not a terminal), readable lines on a terminal.

When stderr is the journal's own stream (systemd sets ``JOURNAL_STREAM`` to its ``device:inode``),
each line starts with the record's syslog priority the sd-daemon(3) way (``<3>`` error, ``<4>``
warning, ``<6>`` info, ``<7>`` debug; journald strips it: ``SyslogLevelPrefix=yes``, the default),
so ``journalctl -p warning`` finds the warnings; what follows is the one JSON object. Anywhere else
(a file, a pipe to ``jq``, the tests) the lines stay plain JSON: a prefix there would only break
the parsers that read them.

Every line on stderr is one log record, whoever wrote it: the daemon's structlog events and the
standard ``logging`` of the libraries it runs on (pymodbus, asyncio, zenoh's Python side, warnings,
uncaught exceptions in threads) all go through one handler and structlog's ``ProcessorFormatter``,
so they come out as JSON objects with the same keys (``event``, ``level``, ``timestamp``; plus
``logger`` for a library's record). A traceback is one field (``exception``), never extra lines.

Device chatter is rate-limited: a library record repeating the same logger, level and message
(numbers ignored, so transaction ids do not make each line new) within :data:`CHATTER_WINDOW_S`
is written once; when the window is over, one more line carries ``suppressed`` (how many were
dropped). pymodbus' hex dumps of the last frames (``>>>>> send: 0x..``, appended to its error
messages) are cut, and its logger stays at WARNING unless ``--log-level debug``. pymodbus' own
report of a failed connection attempt (``Failed to connect ...``, then ``Repeating....``) is a
debug line: the daemon says it once per failure episode (``sensor_group_failed``, with when it
retries), and pymodbus would say it again at every attempt.

Refused targets are logged through a token bucket: a client flooding bad payloads costs a summary
line ("N suppressed") per interval instead of one line each, so it cannot fill the disk.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
import os
import re
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import Any, TextIO

import structlog
from structlog.typing import EventDict, Processor

#: a library message repeated within this many seconds is written once, then summarised
CHATTER_WINDOW_S = 10.0
#: distinct library messages tracked at once (beyond this, new ones pass unthrottled)
MAX_TRACKED_MESSAGES = 1024
PYMODBUS_FRAME_DUMP = "\n>>>>> "
#: pymodbus messages (their start) that repeat what the daemon's own failure line says: debug lines
PYMODBUS_CONNECT_NOISE = ("Failed to connect", "Repeating....")
_NUMBERS = re.compile(r"0x[0-9a-fA-F]+|\d+")
#: syslog priorities (sd-daemon(3)): the lowest logging level each one covers, most severe first
SYSLOG_PRIORITIES = ((logging.CRITICAL, 2), (logging.ERROR, 3), (logging.WARNING, 4), (logging.INFO, 6))
SYSLOG_DEBUG = 7


def syslog_priority(level_no: int) -> int:
    """The syslog priority of a ``logging`` level: 2 critical, 3 error, 4 warning, 6 info, 7 debug."""
    return next((priority for floor, priority in SYSLOG_PRIORITIES if level_no >= floor), SYSLOG_DEBUG)


def writes_to_journal(stream: TextIO) -> bool:
    """True when ``stream`` is the journal's stream: ``JOURNAL_STREAM`` names its device and inode.

    systemd sets the variable for a service whose stdout/stderr go to journald; a child process or a
    redirection (``2>file``) inherits the variable but not the stream, hence the comparison."""
    device, colon, inode = os.environ.get("JOURNAL_STREAM", "").partition(":")
    try:
        status = os.fstat(stream.fileno())
        return bool(colon) and (status.st_dev, status.st_ino) == (int(device), int(inode))
    except (OSError, ValueError, AttributeError):  # no descriptor (StringIO: io.UnsupportedOperation), bad value
        return False


def configure_logging(
    level: str = "info",
    json_lines: bool | None = None,
    *,
    stream: TextIO | None = None,
    window_s: float = CHATTER_WINDOW_S,
    clock: Callable[[], float] = time.monotonic,
    journal: bool | None = None,
) -> None:
    """Set up structlog and ``logging`` for the daemon.

    ``json_lines`` None means: JSON unless stderr is a tty. ``stream`` None writes to whatever
    ``sys.stderr`` is at the time of each line. ``journal`` (each line prefixed with its syslog
    priority) None means: when the stream is the journal's (:func:`writes_to_journal`). Calling it
    again replaces the previous setup.
    """
    if json_lines is None:
        json_lines = not sys.stderr.isatty()
    if journal is None:
        journal = writes_to_journal(stream if stream is not None else sys.stderr)
    level_no = logging.getLevelNamesMapping()[level.upper()]
    renderer: Any = structlog.processors.JSONRenderer() if json_lines else structlog.dev.ConsoleRenderer(
        colors=False
    )
    stamped: list[Processor] = [
        structlog.processors.add_log_level, structlog.processors.TimeStamper(fmt="iso", utc=True)
    ]
    structlog.configure(
        processors=[
            structlog.contextvars.merge_contextvars,
            *stamped,
            structlog.stdlib.ProcessorFormatter.wrap_for_formatter,
        ],
        wrapper_class=structlog.make_filtering_bound_logger(level_no),
        logger_factory=structlog.stdlib.LoggerFactory(),
        cache_logger_on_first_use=False,
    )
    handler = OneLineHandler(stream, ChatterLimiter(window_s, clock), priority_prefix=journal)
    handler.addFilter(_demote_connect_noise(level_no))
    handler.setFormatter(
        structlog.stdlib.ProcessorFormatter(
            foreign_pre_chain=[*stamped, _library_fields],
            processors=[
                structlog.stdlib.ProcessorFormatter.remove_processors_meta,
                structlog.processors.format_exc_info,
                renderer,
            ],
        )
    )
    root = logging.getLogger()
    for old in [h for h in root.handlers if isinstance(h, OneLineHandler)]:
        root.removeHandler(old)
        old.close()
    root.addHandler(handler)
    root.setLevel(level_no)
    # its hex dumps and per-request chatter are for debugging the wire, not for the journal
    logging.getLogger("pymodbus").setLevel(logging.DEBUG if level_no <= logging.DEBUG else logging.WARNING)
    logging.captureWarnings(True)
    threading.excepthook = _log_thread_exception
    sys.excepthook = _log_uncaught


def json_line(event: str, level: str, **fields: Any) -> str:
    """One log line in the daemon's JSON form (``event``, the fields, ``level``, ``timestamp``), for what
    is said before or after the logger runs: ``nanodrift run``'s start-up failure and usage errors,
    so that every line of its stderr parses as JSON when it is not a terminal (the journal, ``jq``)."""
    stamp = dt.datetime.now(dt.UTC).isoformat().replace("+00:00", "Z")
    line = json.dumps({"event": event, **fields, "level": level, "timestamp": stamp}, default=str)
    if writes_to_journal(sys.stderr):
        return f"<{syslog_priority(logging.getLevelNamesMapping()[level.upper()])}>{line}"
    return line


def get_logger(name: str = "nanodrift") -> Any:
    return structlog.get_logger(name)


def _library_fields(logger: Any, method: str, event_dict: EventDict) -> EventDict:
    """A library's record: which logger, and the count of a rate-limit summary."""
    record = event_dict["_record"]
    event_dict["logger"] = record.name
    suppressed = getattr(record, "suppressed", None)
    if suppressed:
        event_dict["suppressed"] = suppressed
        event_dict["window_s"] = getattr(record, "window_s", None)
    return event_dict


def _log_thread_exception(args: threading.ExceptHookArgs) -> None:
    if args.exc_type is SystemExit:
        return
    get_logger().error("thread_exception", thread=args.thread.name if args.thread is not None else None,
                       exc_info=(args.exc_type, args.exc_value, args.exc_traceback))


def _log_uncaught(exc_type: type[BaseException], exc: BaseException, tb: TracebackType | None) -> None:
    get_logger().critical("uncaught_exception", exc_info=(exc_type, exc, tb))


@dataclass
class _Window:
    ends: float
    first: logging.LogRecord
    suppressed: int = 0


class ChatterLimiter:
    """Same logger, level and message (numbers ignored) within ``window_s``: the first passes, the rest
    are counted; :meth:`due` gives one summary record per window that ended with something dropped."""

    def __init__(self, window_s: float = CHATTER_WINDOW_S, clock: Callable[[], float] = time.monotonic) -> None:
        self.window_s = window_s
        self._clock = clock
        self._windows: dict[tuple[str, int, str], _Window] = {}

    def admit(self, record: logging.LogRecord) -> bool:
        if self.window_s <= 0:
            return True
        first_line = record.getMessage().split("\n", 1)[0]
        key = record.name, record.levelno, _NUMBERS.sub("#", first_line)[:300]
        window = self._windows.get(key)
        now = self._clock()
        if window is not None and now < window.ends:
            window.suppressed += 1
            return False
        if window is None and len(self._windows) >= MAX_TRACKED_MESSAGES:
            return True
        self._windows[key] = _Window(now + self.window_s, record)
        return True

    def due(self, everything: bool = False) -> list[logging.LogRecord]:
        """Summaries of the windows that are over (all of them with ``everything``), forgetting those."""
        now = self._clock()
        out = []
        for key, window in list(self._windows.items()):
            if everything or now >= window.ends:
                del self._windows[key]
                if window.suppressed:
                    out.append(self._summary(window))
        return out

    def _summary(self, window: _Window) -> logging.LogRecord:
        first = window.first
        return logging.makeLogRecord({
            "name": first.name, "levelno": first.levelno, "levelname": first.levelname,
            "msg": first.getMessage().split("\n", 1)[0], "args": (),
            "pathname": first.pathname, "lineno": first.lineno,
            "suppressed": window.suppressed, "window_s": self.window_s,
        })


class OneLineHandler(logging.Handler):
    """Writes every record as one line (JSON has no raw newlines); rate-limits libraries' chatter.

    structlog's own records (their ``msg`` is the event dict) are never throttled: the daemon's events
    are written as they happen. With ``priority_prefix`` each line starts with ``<N>``, the record's
    syslog priority, for journald.
    """

    def __init__(self, stream: TextIO | None = None, limiter: ChatterLimiter | None = None, *,
                 priority_prefix: bool = False) -> None:
        super().__init__()
        self._stream = stream
        self.limiter = limiter or ChatterLimiter()
        self.priority_prefix = priority_prefix

    def emit(self, record: logging.LogRecord) -> None:
        try:
            for summary in self.limiter.due():
                self._write(summary)
            if not isinstance(record.msg, dict):
                _cut_frame_dump(record)
                if not self.limiter.admit(record):
                    return
            self._write(record)
        except RecursionError:
            raise
        except Exception:
            self.handleError(record)

    def _write(self, record: logging.LogRecord) -> None:
        stream = self._stream if self._stream is not None else sys.stderr
        prefix = f"<{syslog_priority(record.levelno)}>" if self.priority_prefix else ""
        stream.write(prefix + self.format(record) + "\n")
        stream.flush()

    def close(self) -> None:
        """Say what was still being suppressed, then close."""
        self.acquire()
        try:
            for summary in self.limiter.due(everything=True):
                try:
                    self._write(summary)
                except (OSError, ValueError):  # stderr already closed at interpreter exit
                    break
        finally:
            self.release()
        super().close()


def _demote_connect_noise(level_no: int) -> Callable[[logging.LogRecord], bool]:
    """A handler filter: pymodbus' per-attempt connection lines become debug lines, dropped unless the daemon
    logs debug (``level_no``)."""

    def keep(record: logging.LogRecord) -> bool:
        if (record.name.startswith("pymodbus") and record.levelno > logging.DEBUG and isinstance(record.msg, str)
                and record.getMessage().startswith(PYMODBUS_CONNECT_NOISE)):
            if level_no > logging.DEBUG:
                return False
            record.levelno, record.levelname = logging.DEBUG, "DEBUG"
        return True

    return keep


def _cut_frame_dump(record: logging.LogRecord) -> None:
    """pymodbus appends the last frames as ``\\n>>>>> send: 0x..`` lines to its errors: drop them."""
    if record.name.startswith("pymodbus") and not record.args and isinstance(record.msg, str):
        if PYMODBUS_FRAME_DUMP in record.msg:
            record.msg = record.msg.split(PYMODBUS_FRAME_DUMP, 1)[0]


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
