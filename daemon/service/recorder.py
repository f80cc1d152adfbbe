"""Recorded operation (``[health] record_dir``): every settled target appended to a daily CSV.

The files follow the data contract, so ``nanodrift fit cal.csv records/*.csv`` extends a
calibration with what the cell did in service. A row is one settled target: ``t_s`` (unix s),
``x_um`` the position the interferometer measured (mean over the window), ``q_um`` the command sent,
the reserved ``target_um`` and ``residual_um`` (measured - target), then the temperature channels the
command was computed from.

- One file per UTC day, ``records-YYYY-MM-DD.csv``. A new file is created atomically (header in a
  temp file, fsync, rename): a crash never leaves a file without its header. Each row is fsynced
  (:class:`daemon.calibration.dataset.CsvAppender`), and a restart resumes the day's file, dropping
  a row a crash cut short.
- A file's columns never change: when the channels change (a reload with another model) or the
  clock steps back (``t_s`` must increase), the day continues in ``records-YYYY-MM-DD.2.csv``, ``.3``...
- Retention: when a day's first file is opened, files of days more than ``keep_days`` before it
  are deleted (0 keeps all).
- Recording is never on the answer's path: :class:`Recorder` queues rows for a writer thread. A
  full disk or a permission error is logged once (``record_failed``), rows are lost until writing
  works again (``record_resumed`` says how many), and the daemon keeps serving.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import math
import os
import queue
import re
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from daemon.atomic import atomic_write_text
from daemon.calibration.dataset import RESERVED, CsvAppender, DataError
from daemon.calibration.health import Settled

#: the columns before the channels, in this order
RECORD_COLUMNS = ("t_s", "x_um", "q_um", "target_um", "residual_um")
FILE_NAME = re.compile(r"^records-(?P<day>\d{4}-\d{2}-\d{2})(?:\.(?P<part>\d+))?\.csv$")
#: rows waiting for the writer thread; beyond this (a disk that stopped answering) rows are dropped
QUEUE_ROWS = 10_000


def file_name(day: dt.date, part: int = 1) -> str:
    return f"records-{day.isoformat()}.csv" if part == 1 else f"records-{day.isoformat()}.{part}.csv"


def utc_day(unix_s: float) -> dt.date:
    return dt.datetime.fromtimestamp(unix_s, dt.UTC).date()


def record_row(settled: Settled, unix_s: float) -> dict[str, float]:
    """One settled target as a row of the data contract (channels in the order the command had them)."""
    row = {
        "t_s": float(unix_s),
        "x_um": float(settled.position_um),
        "q_um": float(settled.q_um),
        "target_um": float(settled.x_um),
        "residual_um": float(settled.residual_um),
    }
    for channel, value in settled.temperatures.items():
        if channel in RESERVED:
            raise DataError(f"channel {channel!r} has the name of a reserved column; it cannot be recorded")
        row[channel] = float(value)
    return row


class DayRecorder:
    """Writes rows into the day's file; synchronous, used by one thread (see :class:`Recorder`)."""

    def __init__(self, directory: str | os.PathLike[str], keep_days: int = 90, log: Any = None) -> None:
        if keep_days < 0:
            raise ValueError(f"keep_days must be >= 0, got {keep_days}")
        self.directory = Path(directory)
        self.keep_days = keep_days
        self.log = log
        self.path: Path | None = None
        self.rows_written = 0
        self.rows_lost = 0
        self._appender: CsvAppender | None = None
        self._day: dt.date | None = None
        self._columns: list[str] = []
        self._last_t = -math.inf
        self._failure: str | None = None  # what was logged, until a row is written again
        self._lost_in_outage = 0

    def record(self, settled: Settled, unix_s: float) -> bool:
        """Append one row; False (logged once per outage) when it could not be written. Never raises."""
        try:
            row = record_row(settled, unix_s)
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
        channels = [c for c in row if c not in RECORD_COLUMNS]
        same_columns = set(channels) == set(self._columns[len(RECORD_COLUMNS):])
        if self._appender is None or day != self._day or not same_columns or row["t_s"] <= self._last_t:
            self._open(day, channels, row["t_s"])
        assert self._appender is not None
        self._appender.append(row)
        self._last_t = row["t_s"]

    def _open(self, day: dt.date, channels: Sequence[str], t_s: float) -> None:
        """The day's last file if it has these columns and a row at ``t_s`` comes after its rows; else a new one."""
        self.close()
        self.directory.mkdir(parents=True, exist_ok=True)
        if day != self._day:
            self._expire(day)
        parts = self._parts(day)
        wanted = [*RECORD_COLUMNS, *channels]
        last = parts[-1] if parts else 0
        if last:
            path = self.directory / file_name(day, last)
            header = _header(path)
            if header is not None and sorted(header) == sorted(wanted):
                appender = CsvAppender(path, header)  # drops a row a crash cut short
                last_t = _last_time(path)
                if last_t < t_s:
                    self._take(appender, path, day, header, last_t, "resumed")
                    return
                appender.close()  # the clock stepped back: t_s must increase within a file
        path = self.directory / file_name(day, last + 1)
        atomic_write_text(path, ",".join(wanted) + "\n")
        self._take(CsvAppender(path, wanted), path, day, wanted, -math.inf, "created")

    def _take(self, appender: CsvAppender, path: Path, day: dt.date, columns: list[str], last_t: float,
              how: str) -> None:
        self._appender, self.path, self._day, self._columns, self._last_t = appender, path, day, columns, last_t
        self._event("info", "record_file", path=str(path), how=how,
                    **({"dropped_partial_row": True} if appender.dropped_partial_row else {}))

    def _parts(self, day: dt.date) -> list[int]:
        parts = []
        for entry in self.directory.iterdir():
            match = FILE_NAME.match(entry.name)
            if match and match["day"] == day.isoformat():
                parts.append(int(match["part"] or 1))
        return sorted(parts)

    def _expire(self, today: dt.date) -> None:
        """Delete files of days more than ``keep_days`` before ``today`` (0: keep all)."""
        if self.keep_days == 0:
            return
        oldest = today - dt.timedelta(days=self.keep_days)
        for entry in self.directory.iterdir():
            match = FILE_NAME.match(entry.name)
            if not match:
                continue
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
        self.close()  # reopened (resuming the file, a cut row dropped) at the next row
        self._day = None
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
        self._target: tuple[str, int] | None = None
        self._queue: queue.Queue[tuple[Settled, float] | _Retarget | None] = queue.Queue(maxsize=max_rows)
        self._thread: threading.Thread | None = None

    def on_settled(self, settled: Settled, unix_s: float) -> None:
        """A ``settled_listeners`` entry: never blocks, never raises."""
        config = self.settings()
        target = (config.record_dir, config.record_keep_days)
        if target != self._target:
            self._target = target
            if not self._put(_Retarget(*target)):
                self._target = None  # try again at the next row
                return
        if target[0]:
            self._put((settled, unix_s))

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

    def _put(self, item: tuple[Settled, float] | _Retarget) -> bool:
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
                self.writer = DayRecorder(item.directory, item.keep_days, self.log) if item.directory else None
                if self.log is not None:
                    self.log.info("recording", record_dir=item.directory or None, keep_days=item.keep_days)
                continue
            if self.writer is not None:
                self.writer.record(*item)
        if self.writer is not None:
            self.writer.close()
