"""Recorded operation (``[health] record_dir``): every settled target appended to a daily CSV.

The files follow the data contract, so ``nanodrift fit cal.csv records/*.csv`` extends a
calibration with what the cell did in service. A row is one settled target: ``t_s`` (unix s),
``x_um`` the position the interferometer measured (mean over the window), ``q_um`` the command sent,
the reserved ``target_um``, ``residual_um`` (measured - target) and ``valid``, then every polled
temperature channel (not only the model's: a later refit may want one it left out) over the same window
(:class:`PolledChannels`); a channel not ok there makes the row ``valid = 0``, as an invalid calibration step
is kept: never a NaN.

The wall clock only labels: ``t_s`` and the day in the file name (on a simulated cell whose clock runs
faster, that clock labels instead, ``DriverContext.label_clock``: a simulated day is a day file). What
decides runs on the daemon's monotonic clock (:class:`nanodrift.drivers.base.MonotonicClock`): the settle timing (the
health unit's) and retention, so a step of the system clock (NTP, ``date -s``) neither stalls rows nor deletes files.

- One file per UTC day of the label, ``records-YYYY-MM-DD.csv``. A new file is created atomically
  (header in a temp file, fsync, rename): a crash never leaves a file without its header. Each row
  is one write, fsynced (:class:`nanodrift.calibration.dataset.CsvAppender`); a row that fails (a full
  disk) is cut back off, and a restart resumes the day's file, dropping a row a crash cut short.
- A file's columns never change: when the channels change (a reload polling other channels) or the
  label steps back (``t_s`` must increase), the day continues in ``records-YYYY-MM-DD.2.csv``, ``.3``...
- Retention: files of days more than ``keep_days`` before *today* are deleted (0 keeps all), today
  being the earlier of the daemon's clock's day and the row's: a wall clock stepped forward (a label
  months ahead) never deletes a file the daemon's clock would keep. Nor does a clock that was wrong
  when the daemon started (a bad RTC before NTP synchronised; the daemon's clock starts from it):
  :class:`RetentionClock` (event ``record_retention_held``).
- Recording is never on the answer's path: :class:`Recorder` queues rows for a writer thread. A
  full disk or a permission error is logged once per outage (``record_failed``), rows are lost until
  writing works again (``record_resumed`` says how many, once), and the daemon keeps serving.

One module of ~500 lines on purpose: one job, a settled target to a row of a day's file; the row's
columns (:func:`record_row`), the files' rules (parts, resume, retention: :class:`DayRecorder`, which
clock retention may believe: :class:`RetentionClock`) and the writer thread (:class:`Recorder`) change
together when the contract above does.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import math
import os
import queue
import re
import statistics
import threading
from collections import deque
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from nanodrift.atomic import atomic_write_text
from nanodrift.calibration.dataset import RESERVED, CsvAppender, DataError, WriteBytes
from nanodrift.calibration.residuals import Settled
from nanodrift.compensation import one_axis
from nanodrift.drivers.base import MonotonicClock

#: the columns before the channels, in this order
RECORD_COLUMNS = ("t_s", "x_um", "q_um", "target_um", "residual_um", "valid")
FILE_NAME = re.compile(r"^records-(?P<day>\d{4}-\d{2}-\d{2})(?:\.(?P<part>\d+))?\.csv$")
#: rows waiting for the writer thread; beyond this (a disk that stopped answering) rows are dropped
QUEUE_ROWS = 10_000
#: readings a channel keeps for the window of the next settled target (besides the time bound)
CHANNEL_READINGS = 4096
#: systemd-timesyncd creates this file once it has synchronised the system clock (/run is empty at boot)
TIMESYNC_FLAG = Path("/run/systemd/timesync/synchronized")
#: a day at most this far past the newest record file is believed without proof (a daemon off for a weekend)
CLOCK_AHEAD_MARGIN_DAYS = 2
#: a doubted clock that has run on this many days (with no time sync) is believed: the lab's clock is that one
CLOCK_RELEASE_DAYS = 2


def file_name(day: dt.date, part: int = 1) -> str:
    return f"records-{day.isoformat()}.csv" if part == 1 else f"records-{day.isoformat()}.{part}.csv"


def utc_day(unix_s: float) -> dt.date:
    return dt.datetime.fromtimestamp(unix_s, dt.UTC).date()


@dataclass(frozen=True)
class Polled:
    """Every polled temperature channel over a settled target's window: the row's channels."""

    values_c: Mapping[str, float] = field(default_factory=dict)
    valid: bool = True  # every channel had ok readings (or a fresh ok one) for the window


class PolledChannels:
    """The recent readings of every configured temperature channel, for the window of a settled target.

    A channel's value for a window is the mean of its ok readings inside it; with none inside (a poll
    slower than the window), its latest reading before the window if that is ok and fresh
    (``max_age_s``) at the window's end. A reading that is not ok inside the window, or no fresh ok
    reading, makes the row ``valid = 0`` with the channel's last ok value (else 0). Pure and cheap:
    it runs under the state lock on the loop.
    """

    def __init__(self, max_age_s: Mapping[str, float], keep_s: float) -> None:
        self.max_age_s = dict(max_age_s)
        self.keep_s = keep_s
        self._readings: dict[str, deque[tuple[float, float]]] = {
            name: deque(maxlen=CHANNEL_READINGS) for name in self.max_age_s}
        self._last_ok: dict[str, float] = {}

    def observe(self, name: str, t: float, value: float, ok: bool) -> None:
        """One reading of ``name`` taken at ``t`` (cell clock); ``ok``: the device said ok."""
        readings = self._readings.get(name)
        if readings is None:
            return
        good = ok and math.isfinite(value)
        while readings and readings[0][0] < t - self.keep_s:
            readings.popleft()
        readings.append((t, float(value) if good else math.nan))
        if good:
            self._last_ok[name] = float(value)

    def window(self, start: float, end: float) -> Polled:
        values: dict[str, float] = {}
        valid = True
        for name, readings in self._readings.items():
            inside: list[float] = []
            before: tuple[float, float] | None = None
            for t, v in reversed(readings):  # newest first (readings arrive in time order): stop before the window
                if t < start:
                    before = (t, v)
                    break
                if t <= end:
                    inside.append(v)
            good = [v for v in inside if not math.isnan(v)]
            value: float | None
            if inside:
                ok = len(good) == len(inside)
                value = statistics.fmean(good) if good else None
            else:
                ok = before is not None and not math.isnan(before[1]) and end - before[0] <= self.max_age_s[name]
                value = before[1] if ok and before is not None else None
            values[name] = value if value is not None else self._last_ok.get(name, 0.0)
            valid = valid and ok
        return Polled(values, valid)


def fixed_columns(axes: Mapping[str, Settled]) -> dict[str, float]:
    """A one-axis cell's ``x_um``, ``q_um``, ``target_um``, ``residual_um``; a cell of several's ``<axis>_um``
    measured, ``q_<axis>_um``, ``target_<axis>_um``, ``residual_<axis>_um`` (the CSV contract's columns;
    ``target_``/``residual_`` end in ``_um``, so no reader takes them for a channel)."""
    if one_axis(axes):
        s = axes["x"]
        return {"x_um": float(s.position_um), "q_um": float(s.q_um), "target_um": float(s.x_um),
                "residual_um": float(s.residual_um)}
    row = {f"{axis}_um": float(s.position_um) for axis, s in axes.items()}
    for prefix, attribute in (("q", "q_um"), ("target", "x_um"), ("residual", "residual_um")):
        row.update({f"{prefix}_{axis}_um": float(getattr(s, attribute)) for axis, s in axes.items()})
    return row


def record_row(axes: Mapping[str, Settled], unix_s: float, polled: Polled | None = None) -> dict[str, float]:
    """One settled target as a row of the data contract: ``axes`` every watched axis' :class:`Settled` of
    the same command (a one-axis cell's: ``{"x": settled}``); ``polled`` None: the command's channels, valid."""
    if not axes:
        raise DataError("a settled target of no axis")
    if polled is None:
        polled = Polled(next(iter(axes.values())).temperatures, True)
    row = {"t_s": float(unix_s), **fixed_columns(axes), "valid": 1.0 if polled.valid else 0.0}
    for channel, value in polled.values_c.items():
        if channel in RESERVED or (not one_axis(axes) and channel.endswith("_um")):
            raise DataError(f"channel {channel!r} has the name of a reserved column; it cannot be recorded")
        row[channel] = float(value)
    return row


#: in a records folder: the latest day the daemon saw its clock agree with the files (ISO date). A file written
#: on a doubted clock is dated by that clock, so at the next start the newest file cannot vouch for it: this can.
AGREED_DAY_FILE = ".retention-agreed-day"


def agreed_day(directory: Path) -> dt.date | None:
    """The day kept in ``directory``'s :data:`AGREED_DAY_FILE`, else its newest record file's day."""
    try:
        return dt.date.fromisoformat((directory / AGREED_DAY_FILE).read_text().strip())
    except (OSError, ValueError):
        return newest_file_day(directory)


def newest_file_day(directory: Path) -> dt.date | None:
    """The latest day of a record file in ``directory`` (None: no record file, or no folder)."""
    days: list[dt.date] = []
    with contextlib.suppress(OSError):
        for _, match in _record_files(directory):
            with contextlib.suppress(ValueError):
                days.append(dt.date.fromisoformat(match["day"]))
    return max(days, default=None)


def _record_files(directory: Path) -> Iterator[tuple[Path, re.Match[str]]]:
    """Each record file in ``directory`` (named as :data:`FILE_NAME` says) and its name's day and part."""
    for entry in directory.iterdir():
        if match := FILE_NAME.match(entry.name):
            yield entry, match


class RetentionClock:
    """The day retention may count from: the clock's, once the daemon has seen it agree with its files.

    A clock ahead of the newest record file found in a folder by more than :data:`CLOCK_AHEAD_MARGIN_DAYS`
    (the daemon started on a wrong RTC, NTP not synchronised yet) is doubted: retention counts from that
    newest day (the true day is that one at the earliest), so it deletes nothing the files' own timeline
    would keep. The doubt ends when ``synchronized()`` says the clock is synchronised (systemd-timesyncd's
    :data:`TIMESYNC_FLAG`), when the clock comes back within the margin (NTP stepped it), or when it has run
    on :data:`CLOCK_RELEASE_DAYS` days past the day it was doubted on (a lab without time sync still expires
    its files). Kept by the :class:`Recorder` across reloads, and the agreed day across restarts
    (:data:`AGREED_DAY_FILE`): files written on a doubted clock never vouch for it.
    """

    def __init__(self, log: Any = None, synchronized: Callable[[], bool] = TIMESYNC_FLAG.exists) -> None:
        self.log = log
        self.synchronized = synchronized
        self._agreed: dict[Path, dt.date | None] = {}  # per folder: the latest day the clock was seen to agree on
        self._doubted_since: dt.date | None = None
        self._kept: dict[Path, dt.date] = {}  # per folder: the agreed day this process wrote to AGREED_DAY_FILE

    def today(self, directory: Path, clock_day: dt.date) -> dt.date:
        """The day retention in ``directory`` counts from, for a clock that says ``clock_day``."""
        if directory not in self._agreed:
            self._agreed[directory] = agreed_day(directory)  # before this recorder writes any
        agreed = self._agreed[directory]
        margin = dt.timedelta(days=CLOCK_AHEAD_MARGIN_DAYS)
        released = (self._doubted_since is not None
                    and clock_day >= self._doubted_since + dt.timedelta(days=CLOCK_RELEASE_DAYS))
        if agreed is None or clock_day <= agreed + margin or released or self.synchronized():
            if self._doubted_since is not None and self.log is not None:
                self.log.info("record_retention_resumed", directory=str(directory), day=clock_day.isoformat())
            self._doubted_since = None
            now_agreed = max(clock_day, agreed) if agreed is not None else clock_day
            self._agreed[directory] = now_agreed
            self._keep(directory, now_agreed)
            return clock_day
        if self._doubted_since is None:
            self._doubted_since = clock_day
            if self.log is not None:
                self.log.warning(
                    "record_retention_held", directory=str(directory), clock_day=clock_day.isoformat(),
                    newest_file_day=agreed.isoformat(),
                    reason=(f"the clock says {clock_day.isoformat()}, {(clock_day - agreed).days} days past the newest "
                            f"record file ({agreed.isoformat()}), and is not known synchronised ({TIMESYNC_FLAG} "
                            "absent): no record is deleted by it"),
                    until=(f"the clock is synchronised, comes back within {CLOCK_AHEAD_MARGIN_DAYS} days of the files, "
                           f"or has run {CLOCK_RELEASE_DAYS} days on"))
        self._keep(directory, agreed)  # the files written on this clock will not vouch for it at the next start
        return agreed  # the true day is that one at the earliest

    def _keep(self, directory: Path, day: dt.date) -> None:
        """``day`` into ``directory``'s :data:`AGREED_DAY_FILE`, once per change."""
        if self._kept.get(directory) != day:
            with contextlib.suppress(OSError):  # no folder yet, or a full disk: the files' days then stand in
                atomic_write_text(directory / AGREED_DAY_FILE, day.isoformat() + "\n")
                self._kept[directory] = day


class DayRecorder:
    """Writes rows into the day's file; synchronous, used by one thread (see :class:`Recorder`).

    ``clock``: the daemon's time base, which retention decides on (default :class:`MonotonicClock`: real
    days even when a simulated cell's clock runs faster);
    ``write``: how bytes reach the file (``os.write``; a test injects a full disk);
    ``retention``: whether retention may believe that clock (:class:`RetentionClock`; the :class:`Recorder`
    keeps one across reloads).
    """

    def __init__(self, directory: str | os.PathLike[str], keep_days: int = 90, log: Any = None, *,
                 clock: Callable[[], float] | None = None, write: WriteBytes = os.write,
                 retention: RetentionClock | None = None) -> None:
        if keep_days < 0:
            raise ValueError(f"keep_days must be >= 0, got {keep_days}")
        self.directory = Path(directory)
        self.keep_days = keep_days
        self.log = log
        self.clock = clock or MonotonicClock().now
        self.write = write
        self.retention = retention or RetentionClock(log)
        self.path: Path | None = None
        self.rows_written = 0
        self.rows_lost = 0
        self._appender: CsvAppender | None = None
        self._day: dt.date | None = None
        self._columns: list[str] = []
        self._last_t = -math.inf
        self._expired_before: dt.date | None = None  # the "today" retention last ran for
        self._failure: str | None = None  # what was logged, until a row is written again
        self._lost_in_outage = 0

    def record(self, axes: Mapping[str, Settled], unix_s: float, polled: Polled | None = None) -> bool:
        """Append one row (:func:`record_row`); False (logged once per outage) when it could not be written.
        Never raises."""
        try:
            row = record_row(axes, unix_s, polled)
            bad = [name for name, value in row.items() if not math.isfinite(value)]
            if bad:
                raise DataError(f"not a finite number in {', '.join(bad)}")
            self._append(row)
        except (OSError, DataError, ValueError, TypeError, OverflowError) as err:
            self._failed(err)
            return False
        self.rows_written += 1
        if self._failure is not None:
            self._event("info", "record_resumed", path=str(self.path), rows_lost=self._lost_in_outage)
            self._failure, self._lost_in_outage = None, 0
        return True

    def close(self) -> None:
        if self._appender is not None:
            with contextlib.suppress(OSError):
                self._appender.close()
        self._appender = None

    # --- files ----------------------------------------------------------------------------------

    def _append(self, row: dict[str, float]) -> None:
        day = utc_day(row["t_s"])
        today = min(utc_day(self.clock()), day)  # a label stepped ahead is no reason to delete anything
        today = self.retention.today(self.directory, today)  # nor a clock that started ahead of the files
        if today != self._expired_before:
            self.directory.mkdir(parents=True, exist_ok=True)
            self._expire(today)
            self._expired_before = today
        fixed: Sequence[str] = RECORD_COLUMNS
        if "q_um" not in row:  # a multi-axis cell's row: its positions, commands, targets, residuals
            fixed = [c for c in row if c in RESERVED or c.endswith("_um")]
        same_columns = set(row) == set(self._columns)
        if self._appender is None or day != self._day or not same_columns or row["t_s"] <= self._last_t:
            self._open(day, [*fixed, *(c for c in row if c not in fixed)], row["t_s"])
        assert self._appender is not None
        self._appender.append(row)
        self._last_t = row["t_s"]

    def _open(self, day: dt.date, wanted: list[str], t_s: float) -> None:
        """The day's last file if it has the ``wanted`` columns (the fixed ones, then the channels) and a row at
        ``t_s`` comes after its rows; else a new one."""
        self.close()
        self.directory.mkdir(parents=True, exist_ok=True)
        last = max((int(m["part"] or 1) for _, m in _record_files(self.directory) if m["day"] == day.isoformat()),
                   default=0)
        if last:
            path = self.directory / file_name(day, last)
            header = _header(path)
            if header is not None and sorted(header) == sorted(wanted):
                appender = CsvAppender(path, header, write=self.write)  # drops a row a crash cut short
                last_t = _last_time(path)
                if last_t < t_s:
                    self._take(appender, path, day, header, last_t, "resumed")
                    return
                appender.close()  # the label stepped back: t_s must increase within a file
        path = self.directory / file_name(day, last + 1)
        atomic_write_text(path, ",".join(wanted) + "\n")
        self._take(CsvAppender(path, wanted, write=self.write), path, day, wanted, -math.inf, "created")

    def _take(self, appender: CsvAppender, path: Path, day: dt.date, columns: list[str], last_t: float,
              how: str) -> None:
        self._appender, self.path, self._day, self._columns, self._last_t = appender, path, day, columns, last_t
        if self._failure is None:  # during an outage, record_resumed names the file
            self._event("info", "record_file", path=str(path), how=how,
                        **({"dropped_partial_row": True} if appender.dropped_partial_row else {}))

    def _expire(self, today: dt.date) -> None:
        """Delete files of days more than ``keep_days`` before ``today`` (0: keep all)."""
        if self.keep_days == 0:
            return
        oldest = today - dt.timedelta(days=self.keep_days)
        for entry, match in _record_files(self.directory):
            try:
                if dt.date.fromisoformat(match["day"]) < oldest:
                    entry.unlink()
                    self._event("info", "record_expired", path=str(entry), keep_days=self.keep_days)
            except (OSError, ValueError) as err:
                self._event("warning", "record_expire_failed", path=str(entry), error=str(err))

    # --- failures -------------------------------------------------------------------------------

    def _failed(self, err: Exception) -> None:
        self.rows_lost += 1
        self._lost_in_outage += 1
        if self._appender is not None and not self._appender.intact:
            self.close()  # the failed row could not be cut back: reopening the file drops it
        if self._failure is None:
            self._failure = str(err)
            self._event("error", "record_failed", directory=str(self.directory), error=_describe(err),
                        note="recording stops until writing works again; the daemon keeps serving")

    def _event(self, level: str, event: str, **fields: Any) -> None:
        if self.log is not None:
            getattr(self.log, level)(event, **fields)


def _describe(err: Exception) -> str:
    if isinstance(err, OSError) and err.strerror:
        where = f": {err.filename}" if err.filename else ""
        return f"{err.strerror}{where}"
    return str(err)


def _header(path: Path) -> list[str] | None:
    try:
        with open(path, encoding="utf-8-sig") as handle:
            line = handle.readline()
    except (OSError, UnicodeDecodeError):
        return None
    if not line.endswith("\n"):
        return None
    return [h.strip() for h in line.strip().split(",")]


def _last_time(path: Path) -> float:
    """``t_s`` of the file's last complete row (-inf when it has none)."""
    with open(path, "rb") as handle:
        handle.seek(0, os.SEEK_END)
        size = handle.tell()
        handle.seek(max(0, size - 65536))
        lines = handle.read().split(b"\n")
    for line in reversed(lines[1:] if size > 65536 else lines):
        cell = line.split(b",", 1)[0].strip()
        if cell:
            try:
                return float(cell)
            except ValueError:
                return -math.inf  # the header: no rows yet
    return -math.inf


class RecordSettings(Protocol):
    """What the recorder reads of the running config: ``[health]``'s ``record_dir`` and ``record_keep_days``."""

    record_dir: str
    record_keep_days: int


@dataclass(frozen=True)
class _Retarget:
    directory: str
    keep_days: int


class Recorder:
    """The daemon's side: :meth:`on_settled` only queues (it runs on the health unit's path); a thread writes.

    ``settings()`` is read at every settled target, so a reload that sets, moves or clears
    ``record_dir`` takes effect at the next row (in order with the rows before it: one thread writes).
    """

    def __init__(self, settings: Callable[[], RecordSettings], log: Any = None, *, max_rows: int = QUEUE_ROWS) -> None:
        self.settings = settings
        self.log = log
        self.writer: DayRecorder | None = None  # the writer thread's
        self.dropped = 0
        self.retention = RetentionClock(log)
        self._target: tuple[str, int] | None = None
        self._queue: queue.Queue[tuple[Mapping[str, Settled], float, Polled | None] | _Retarget | None] = (
            queue.Queue(maxsize=max_rows))
        self._thread: threading.Thread | None = None

    def on_settled(self, axes: Mapping[str, Settled], unix_s: float, polled: Polled | None = None) -> None:
        """A ``settled_listeners`` entry: never blocks, never raises. ``axes``: every watched axis' settled
        window of one command; ``unix_s`` labels the row (wall clock)."""
        config = self.settings()
        target = (config.record_dir, config.record_keep_days)
        if target != self._target:
            self._target = target
            if not self._put(_Retarget(*target)):
                self._target = None  # try again at the next row
                return
        if target[0]:
            self._put((axes, unix_s, polled))

    def close(self, timeout_s: float = 5.0) -> None:
        """Write what is queued, then stop the thread (waiting at most ``timeout_s``)."""
        if self._thread is None:
            return
        with contextlib.suppress(queue.Full):
            self._queue.put(None, timeout=timeout_s)
        self._thread.join(timeout_s)

    @property
    def running(self) -> bool:
        return self._thread is not None and self._thread.is_alive()

    def _put(self, item: tuple[Mapping[str, Settled], float, Polled | None] | _Retarget) -> bool:
        if self._thread is None:
            self._thread = threading.Thread(target=self._run, name="nanodrift-recorder", daemon=True)
            self._thread.start()
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.dropped += 1
            if self.dropped == 1 and self.log is not None:
                self.log.error("record_queue_full", rows=self._queue.maxsize,
                               note="the disk is not keeping up; settled targets are not recorded")
            return False
        return True

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                break
            if isinstance(item, _Retarget):
                if self.writer is not None:
                    self.writer.close()
                self.writer = (DayRecorder(item.directory, item.keep_days, self.log, retention=self.retention)
                               if item.directory else None)
                if self.log is not None:
                    self.log.info("recording", record_dir=item.directory or None, keep_days=item.keep_days)
                continue
            if self.writer is not None:
                self.writer.record(*item)
        if self.writer is not None:
            self.writer.close()
