"""Recorded data per the CSV contract: ``t_s``, ``x_um``, ``q_um`` and one column per temperature channel.

Every column that is not reserved is a temperature channel in °C named by its header. Reserved
columns the project adds (documented in the README):

- ``q_pred_um``: the command the model gives for the row (``nanodrift predict``);
- ``q_sigma_um``: its standard uncertainty (``nanodrift predict``);
- ``cycle``: 0-based calibration/validation cycle, so held-out blocks are whole cycles;
- ``valid``: 1/0; a step that could not be measured cleanly (a sensor faulted) is kept with 0;
- ``target_um``: the target a client asked for (recorded operation: ``x_um`` is where the stage was
  measured, ``q_um`` the command sent);
- ``residual_um``: measured position minus target (recorded operation).

Multi-axis files (an XY or XYZ stage: ARCHITECTURE.md "Multi-axis cells") have one position column
per axis, ``<axis>_um`` (``x_um``, ``y_um``, ``z_um``; the axis is one lowercase letter and ``x`` is always
one of them), and commands ``q_<axis>_um`` instead of ``q_um``. No column ending in ``_um`` is ever a
temperature channel: ``<axis>_true_um``, ``q_pred_<axis>_um`` and the like are kept as reserved columns.

Files are refused with a message naming the file, the row (1-based line number as an editor shows
it) and the column. Several files fitted together (:func:`concat`) stay separate runs: each
row knows its file (``Dataset.segment``), so stateful terms restart and held-out blocks stay inside
one file.

One module of ~400 lines on purpose: the contract's reader, its writer and its row-by-row appender
(:class:`CsvAppender`, recorded runs) live together, so what is written is what is read.
"""

from __future__ import annotations

import csv
import errno
import io
import math
import os
import re
import warnings
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from nanodrift.atomic import atomic_writer
from nanodrift.model.segments import segment_slices

REQUIRED = ("t_s", "x_um")
RESERVED = ("t_s", "x_um", "q_um", "q_pred_um", "q_sigma_um", "cycle", "valid", "target_um", "residual_um")
CHANNEL_NAME = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
#: names a channel may not take because a model term would read them as something else
FORBIDDEN_CHANNELS = frozenset({"x", "dir", "t", "1"})
#: a position column of a multi-axis file: ``<axis>_um``, the axis one lowercase letter but q (``q_um`` is the
#: one-axis command)
AXIS_COLUMN = re.compile(r"^(?P<axis>[a-pr-z])_um$")
#: a command column of a multi-axis file: ``q_<axis>_um``
COMMAND_COLUMN = re.compile(r"^q_(?P<axis>[a-pr-z])_um$")


def position_column(axis: str) -> str:
    return f"{axis}_um"


def command_column(axis: str) -> str:
    return f"q_{axis}_um"


def is_reserved(name: str) -> bool:
    """A column that is not a temperature channel: the contract's reserved names and anything ending in ``_um``."""
    return name in RESERVED or name.endswith("_um")


class DataError(ValueError):
    """A data file that does not follow the CSV contract; the message says where and why."""


@dataclass
class Dataset:
    """A time series of samples: positions, commands and temperature channels."""

    t: np.ndarray
    x: np.ndarray
    q: np.ndarray | None = None
    channels: dict[str, np.ndarray] = field(default_factory=dict)
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    source: str = "<memory>"
    #: the 0-based index of the file each row came from when several were read together; None: one run
    segment: np.ndarray | None = None
    #: a multi-axis run: position per axis in the cell's axis order (``x`` is also :attr:`x`); empty for one axis
    positions: dict[str, np.ndarray] = field(default_factory=dict)
    #: a multi-axis run: the command sent per axis (``q_<axis>_um``), when recorded; empty for one axis
    commands: dict[str, np.ndarray] = field(default_factory=dict)
    #: the axis whose command ``q`` is (:meth:`axis_view`); ``x`` for a one-axis run
    axis: str = "x"

    def __len__(self) -> int:
        return int(self.t.shape[0])

    @property
    def axes(self) -> tuple[str, ...]:
        """The axes the rows position: ``("x",)`` for a one-axis file."""
        return tuple(self.positions) or ("x",)

    @property
    def multi_axis(self) -> bool:
        return len(self.positions) > 1

    @property
    def own_position(self) -> np.ndarray:
        """The position of :attr:`axis` (``x`` for a one-axis run): what its own motion terms read."""
        return self.positions[self.axis] if self.multi_axis else self.x

    def alone(self, axis: str) -> Dataset:
        """``axis`` as a one-axis run (its position as ``x``, its command as ``q``, the other axes dropped):
        what a one-axis cell on that axis would have recorded."""
        extra = {k: v for k, v in self.extra.items() if k in ("cycle", "valid")}
        return Dataset(t=self.t, x=self.positions[axis], q=self.commands.get(axis), channels=self.channels,
                       extra=extra, source=f"{self.source} ({axis} alone)", segment=self.segment)

    def axis_view(self, axis: str) -> Dataset:
        """The rows as identification of ``axis`` sees them: its command as ``q``, every axis' position kept.

        ``x`` stays the x axis' position (a term named ``x`` is always that axis); the other axes'
        positions reach the terms that read them through :attr:`positions`.
        """
        if axis not in self.axes:
            raise KeyError(f"{self.source} has no axis {axis!r} (axes: {', '.join(self.axes)})")
        if not self.multi_axis:
            return self
        return replace(self, q=self.commands.get(axis), source=f"{self.source} (axis {axis})", axis=axis)

    @property
    def channel_names(self) -> tuple[str, ...]:
        return tuple(self.channels)

    def select(self, rows: np.ndarray | slice) -> Dataset:
        """The rows picked by a boolean mask, an index array or a slice, as a new dataset."""
        return Dataset(
            t=self.t[rows],
            x=self.x[rows],
            q=None if self.q is None else self.q[rows],
            channels={k: v[rows] for k, v in self.channels.items()},
            extra={k: v[rows] for k, v in self.extra.items()},
            source=self.source,
            segment=None if self.segment is None else self.segment[rows],
            positions={k: v[rows] for k, v in self.positions.items()},
            commands={k: v[rows] for k, v in self.commands.items()},
            axis=self.axis,
        )

    def valid_rows(self) -> Dataset:
        """Only the rows not marked ``valid = 0``."""
        if "valid" not in self.extra:
            return self
        return self.select(self.extra["valid"] != 0)

    def cycles(self) -> np.ndarray:
        """Cycle index per row: the ``cycle`` column, else a new cycle wherever x steps back down.

        A step back of more than half the x span marks the start of a new sweep, which is how the
        paper's forward-only trajectory repeats. Rows of several files: each file's own cycles,
        numbered on after the previous file's, so no cycle spans two files.
        """
        if self.segment is not None:
            out = np.zeros(len(self), dtype=np.int64)
            first = 0
            for part in segment_slices(self.segment):
                own = Dataset(self.t[part], self.x[part], extra={k: v[part] for k, v in self.extra.items()}).cycles()
                out[part] = np.unique(own, return_inverse=True)[1] + first
                first = int(out[part].max()) + 1
            return out
        if "cycle" in self.extra:
            return self.extra["cycle"].astype(np.int64)
        if len(self) < 2:
            return np.zeros(len(self), dtype=np.int64)
        span = float(np.ptp(self.x)) or 1.0
        starts = np.diff(self.x) < -0.5 * span
        return np.concatenate(([0], np.cumsum(starts))).astype(np.int64)

    def columns(self, extra_columns: Mapping[str, np.ndarray] | None = None) -> dict[str, np.ndarray]:
        """All columns in contract order, for writing."""
        cols: dict[str, np.ndarray] = {"t_s": self.t, "x_um": self.x}
        if self.multi_axis:
            cols.update({position_column(a): v for a, v in self.positions.items()})
            cols.update({command_column(a): v for a, v in self.commands.items()})
        elif self.q is not None:
            cols["q_um"] = self.q
        cols.update(self.extra)
        cols.update(self.channels)
        if extra_columns:
            cols.update(extra_columns)
        return cols


def check_channel_name(name: str, where: str) -> None:
    if not CHANNEL_NAME.match(name) or name in FORBIDDEN_CHANNELS:
        raise DataError(
            f"{where}: {name!r} is not usable as a temperature channel name "
            "(expected letters, digits, '_', '.', '-', starting with a letter; not x, t, dir or 1)"
        )


def read_csv(path: str | os.PathLike[str]) -> Dataset:
    """Read a data file of the CSV contract (README, *Data files*) into a :class:`Dataset` (``nanodrift.read_csv``).

    Columns: ``t_s`` (s, increasing), ``x_um`` (and ``y_um``, ``z_um`` in a file of several axes),
    optionally ``q_um`` (``q_<axis>_um``); every other column not reserved is a temperature channel in °C
    named by its header (``data.channels``), the reserved ones land in ``data.extra``. A bad file
    (missing column, non-numeric cell, time not increasing, empty) raises :class:`DataError` naming the
    file, the row and the column."""
    path = Path(path)
    header = _parse_header(path, _read_text(path))
    values = _parse_body(path, header)
    return _to_dataset(path, header, values)


def _read_text(path: Path, *, body: bool = False) -> str:
    """The file's first line (with ``body``: all after it) as UTF-8 text; a file that cannot be read is a
    :class:`DataError`."""
    try:
        # utf-8-sig: a spreadsheet's byte-order mark is not part of the first column's name
        with open(path, encoding="utf-8-sig", newline="") as handle:
            first = handle.readline()
            return handle.read() if body else first
    except FileNotFoundError:
        raise DataError(f"{path}: no such file") from None
    except UnicodeDecodeError as err:
        raise DataError(f"{path}: not a UTF-8 text file ({err.reason} at byte {err.start})") from None
    except OSError as err:
        raise DataError(f"{path}: cannot read ({err.strerror})") from None


def _parse_header(path: Path, line: str) -> list[str]:
    if not line.strip():
        raise DataError(f"{path}: empty file (expected a header row with t_s, x_um and channel columns)")
    try:
        header = [h.strip() for h in next(csv.reader([line]))]
    except csv.Error as err:
        raise DataError(f"{path}, row 1: not a CSV header row ({err})") from None
    for required in REQUIRED:
        if required not in header:
            raise DataError(f"{path}, row 1: missing column {required!r} (header is {','.join(header)})")
    seen: set[str] = set()
    for col, name in enumerate(header, start=1):
        if name in seen:
            raise DataError(f"{path}, row 1, column {col}: duplicate column {name!r}")
        seen.add(name)
        if not is_reserved(name):
            check_channel_name(name, f"{path}, row 1, column {col}")
    axes = [m["axis"] for name in header if (m := AXIS_COLUMN.match(name))]
    commanded = [m["axis"] for name in header if (m := COMMAND_COLUMN.match(name))]
    if len(axes) > 1 and "q_um" in header:
        raise DataError(f"{path}, row 1: a multi-axis file ({', '.join(a + '_um' for a in axes)}) names its commands "
                        f"{', '.join(command_column(a) for a in axes)}, not q_um")
    clash = [name for name in header if len(axes) > 1 and name in axes]
    if clash:
        raise DataError(f"{path}, row 1, column {header.index(clash[0]) + 1}: {clash[0]!r} is an axis of this "
                        "multi-axis file; a temperature channel may not take an axis' name")
    stray = [command_column(a) for a in commanded if a not in axes]
    if stray:
        raise DataError(f"{path}, row 1: column {stray[0]} commands an axis with no position column "
                        f"(axes: {', '.join(a + '_um' for a in axes)})")
    if commanded and len(commanded) != len(axes):
        missing = [command_column(a) for a in axes if a not in commanded]
        raise DataError(f"{path}, row 1: missing column {missing[0]!r} (every axis needs its command when one has)")
    return header


def _parse_body(path: Path, header: list[str]) -> np.ndarray:
    """Fast path through numpy's C parser, straight from the file (a season's rows are never one string);
    on any failure a slow pass finds the exact row and column."""
    try:
        with warnings.catch_warnings():  # "input contained no data": the slow pass says it with the file's name
            warnings.simplefilter("ignore", UserWarning)
            # comments=None: numpy would drop a row from a "#" on (a cell "#" or "1#2"), which the slow pass refuses
            values = np.loadtxt(path, delimiter=",", dtype=np.float64, ndmin=2, skiprows=1, encoding="utf-8",
                                comments=None)
        if values.shape[0] and values.shape[1] == len(header) and np.isfinite(values).all():
            return values
    except (ValueError, UnicodeDecodeError):
        pass
    body = _read_text(path, body=True)
    if not body.strip():
        raise DataError(f"{path}: no data rows after the header")
    reader = csv.reader(io.StringIO(body))
    try:
        rows = [_parse_row(path, header, row, reader.line_num + 1) for row in reader]
    except csv.Error as err:  # e.g. a quoted field longer than the csv module's limit
        raise DataError(f"{path}, row {reader.line_num + 1}: not a CSV row ({err})") from None
    rows = [r for r in rows if r]
    if not rows:  # only blank cells, e.g. a line of ""
        raise DataError(f"{path}: no data rows after the header")
    return np.asarray(rows, dtype=np.float64).reshape(-1, len(header))


def _parse_row(path: Path, header: list[str], row: list[str], line_no: int) -> list[float]:
    """One row's numbers ([] for a blank line); DataError naming the row and column otherwise."""
    if not row or all(not cell.strip() for cell in row):
        return []
    if len(row) != len(header):
        raise DataError(f"{path}, row {line_no}: {len(row)} cells, expected {len(header)} (one per column)")
    parsed = []
    for name, cell in zip(header, row, strict=True):
        try:
            value = float(cell)
        except ValueError:
            raise DataError(f"{path}, row {line_no}, column {name}: {cell.strip()!r} is not a number") from None
        if not math.isfinite(value):
            raise DataError(f"{path}, row {line_no}, column {name}: {cell.strip()!r} is not a finite number")
        parsed.append(value)
    return parsed


def _to_dataset(path: Path, header: list[str], values: np.ndarray) -> Dataset:
    cols = {name: np.ascontiguousarray(values[:, i]) for i, name in enumerate(header)}
    t = cols["t_s"]
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        i = int(bad[0]) + 1
        raise DataError(
            f"{path}, row {i + 2}, column t_s: time {t[i]:g} s is not after the previous row's {t[i - 1]:g} s "
            "(t_s must increase)"
        )
    for name in ("cycle", "valid"):
        if name in cols and not np.array_equal(cols[name], np.round(cols[name])):
            i = int(np.flatnonzero(cols[name] != np.round(cols[name]))[0])
            raise DataError(f"{path}, row {i + 2}, column {name}: expected a whole number, got {cols[name][i]:g}")
    axes = [m["axis"] for name in header if (m := AXIS_COLUMN.match(name))]
    multi = len(axes) > 1
    taken = {"t_s", *map(position_column, axes), *map(command_column, axes)} if multi else {"t_s", "x_um", "q_um"}
    return Dataset(
        t=t, x=cols["x_um"], q=None if multi else cols.get("q_um"),
        channels={n: cols[n] for n in header if not is_reserved(n)},
        extra={n: cols[n] for n in header if is_reserved(n) and n not in taken},
        source=str(path),
        positions={a: cols[position_column(a)] for a in axes} if multi else {},
        commands={a: cols[command_column(a)] for a in axes if command_column(a) in cols} if multi else {},
    )


def common_channels(datasets: Sequence[Dataset]) -> list[str]:
    """The channels every dataset has, in the first one's order."""
    return [c for c in datasets[0].channels if all(c in d.channels for d in datasets[1:])]


def concat(datasets: Sequence[Dataset], channels: Sequence[str] | None = None) -> Dataset:
    """Several runs as one dataset whose rows remember their run (``segment``); one run is returned as is.

    ``channels`` (default: the first run's) must be in every run: a :class:`DataError` names the
    run that lacks one. ``q`` is kept when every run has it. Reserved columns every run has are
    kept; ``valid`` is 1 where a run lacks it, and ``cycle`` is each run's own cycles where a run
    lacks it (so the runs keep their cycles apart: see :meth:`Dataset.cycles`).
    """
    if not datasets:
        raise DataError("no data files given")
    wanted = list(datasets[0].channels if channels is None else channels)
    for ds in datasets:
        missing = [c for c in wanted if c not in ds.channels]
        if missing:
            raise DataError(
                f"{ds.source}: lacks channel(s) {', '.join(missing)} that {datasets[0].source} has "
                f"(its channels: {', '.join(ds.channels) or 'none'})"
            )
    axes = datasets[0].axes
    for ds in datasets[1:]:
        if ds.axes != axes:
            raise DataError(f"{ds.source}: positions axes {', '.join(ds.axes)}, but {datasets[0].source} "
                            f"positions {', '.join(axes)} (runs fitted together must be of one cell)")
    if len(datasets) == 1:
        ds = datasets[0]
        if list(ds.channels) == wanted:
            return ds
        return replace(ds, channels={c: ds.channels[c] for c in wanted})
    commands = [d.q for d in datasets if d.q is not None]
    extra: dict[str, np.ndarray] = {}
    names = [n for n in datasets[0].extra if all(n in d.extra for d in datasets[1:])]
    names += [n for n in ("valid", "cycle") if n not in names and any(n in d.extra for d in datasets)]
    for name in names:
        parts = []
        for ds in datasets:
            if name in ds.extra:
                parts.append(ds.extra[name])
            elif name == "valid":
                parts.append(np.ones(len(ds)))
            else:
                parts.append(ds.cycles().astype(np.float64))
        extra[name] = np.concatenate(parts)
    return Dataset(
        t=np.concatenate([d.t for d in datasets]),
        x=np.concatenate([d.x for d in datasets]),
        q=None if len(commands) < len(datasets) else np.concatenate(commands),
        channels={c: np.concatenate([d.channels[c] for d in datasets]) for c in wanted},
        extra=extra,
        source=", ".join(d.source for d in datasets),
        segment=np.concatenate([np.full(len(d), i, dtype=np.int64) for i, d in enumerate(datasets)]),
        positions={a: np.concatenate([d.positions[a] for d in datasets]) for a in datasets[0].positions},
        commands=({a: np.concatenate([d.commands[a] for d in datasets]) for a in datasets[0].commands}
                  if all(d.commands for d in datasets) else {}),
    )


def _csv_chunks(columns: Mapping[str, np.ndarray], rows_per_chunk: int = 50_000) -> Iterator[str]:
    """CSV text in chunks, so a million rows never sit in memory as one string.

    Floats are written ``repr``-exact (a round trip loses nothing); ``cycle`` and ``valid`` as
    whole numbers. A chunk is formatted a column at a time (``map`` over a list runs in C, a
    format string per row would not) and its rows joined from those cells.
    """
    names = list(columns)
    yield ",".join(names) + "\n"
    if not names:
        return
    arrays = [np.asarray(columns[n], dtype=np.float64) for n in names]
    n_rows = arrays[0].shape[0]
    for start in range(0, n_rows, rows_per_chunk):
        cells = [map(str, map(int, a[start:start + rows_per_chunk].tolist())) if n in ("cycle", "valid")
                 else map(repr, a[start:start + rows_per_chunk].tolist()) for n, a in zip(names, arrays, strict=True)]
        yield "\n".join(map(",".join, zip(*cells, strict=True))) + "\n"


def write_csv(
    ds: Dataset, path: str | os.PathLike[str], extra_columns: Mapping[str, np.ndarray] | None = None
) -> None:
    """Write ``ds`` as a CSV of the contract (``nanodrift.write_csv``), its columns in contract order, then
    ``extra_columns`` (name -> one value per row, e.g. ``{"q_pred_um": model.predict(ds)}``). Written
    atomically (a temporary file renamed over ``path``); floats round-trip exactly through :func:`read_csv`.
    Columns of different lengths are a :class:`ValueError`."""
    columns = ds.columns(extra_columns)
    lengths = {name: np.shape(values)[0] for name, values in columns.items()}
    if len(set(lengths.values())) > 1:
        raise ValueError(f"columns differ in length: {lengths}")
    with atomic_writer(path) as handle:
        for chunk in _csv_chunks(columns):
            handle.write(chunk)


#: writes bytes to a file descriptor and says how many it wrote (``os.write``; a test injects a full disk)
WriteBytes = Callable[[int, bytes], int]


class CsvAppender:
    """Append rows one at a time, each flushed and fsynced: an interrupted run keeps every row written.

    Used by the calibration procedure, where a row is one completed step of hours of work, and by the
    daemon's recorder. Opening an existing file checks that its header matches, so a resumed run
    continues the same table. A row that cannot be written whole (a full disk: an error or a short
    write, also at the fsync) is cut back off before the error is raised, so the file never ends
    inside a row and the appender can go on when writing works again.
    """

    def __init__(self, path: str | os.PathLike[str], columns: Sequence[str], *, write: WriteBytes = os.write) -> None:
        self.path = Path(path)
        self.columns = list(columns)
        self.dropped_partial_row = False
        #: False when a failed row could not be cut back off (reopen the file: that drops it)
        self.intact = True
        self._write = write
        for col, name in enumerate(self.columns, start=1):
            if not is_reserved(name):
                check_channel_name(name, f"{self.path}, column {col}")
        self.path.parent.mkdir(parents=True, exist_ok=True)
        exists = self.path.exists() and self.path.stat().st_size > 0
        if exists:
            with open(self.path, encoding="utf-8-sig") as handle:
                found = [h.strip() for h in handle.readline().strip().split(",")]
            if found != self.columns:
                raise DataError(
                    f"{self.path}: cannot append, its columns {found} differ from {self.columns}"
                )
            self.dropped_partial_row = _drop_partial_last_line(self.path)
        self._fd: int | None = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o666)
        if not exists:
            self._write_line(",".join(self.columns))

    def append(self, row: Mapping[str, float]) -> None:
        missing = [c for c in self.columns if c not in row]
        if missing:
            raise KeyError(f"row lacks columns {missing}")
        cells = [str(int(row[c])) if c in ("cycle", "valid") else repr(float(row[c])) for c in self.columns]
        self._write_line(",".join(cells))

    def _write_line(self, line: str) -> None:
        if self._fd is None:
            raise ValueError(f"{self.path}: appender is closed")
        data = (line + "\n").encode("utf-8")
        start = os.fstat(self._fd).st_size  # where the row begins: cut back to it if it fails
        try:
            while data:
                written = self._write(self._fd, data)
                if written <= 0:
                    raise OSError(errno.ENOSPC, "no space left on device (short write)", str(self.path))
                data = data[written:]
            os.fsync(self._fd)
        except OSError:
            try:
                os.ftruncate(self._fd, start)
            except OSError:
                self.intact = False
            raise

    def close(self) -> None:
        if self._fd is not None:
            fd, self._fd = self._fd, None
            os.close(fd)

    def __enter__(self) -> CsvAppender:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _drop_partial_last_line(path: Path) -> bool:
    """Cut an unterminated last line (a write interrupted by a crash): that step never completed."""
    with open(path, "rb+") as handle:
        data = handle.read()
        if data.endswith(b"\n"):
            return False
        handle.truncate(data.rfind(b"\n") + 1)
        return True


def read_runs(paths: Sequence[str], purpose: str = "to fit") -> list[Dataset]:
    """Read every file; a bad one, or one without ``q_um``, is refused by name."""
    runs = [read_csv(p) for p in paths]
    for ds in runs:
        if ds.multi_axis and not ds.commands:
            raise DataError(f"{ds.source}: no {', '.join(command_column(a) for a in ds.axes)} columns "
                            f"(the commands sent to the stage's axes) {purpose}")
        if ds.q is None and not ds.multi_axis:
            raise DataError(f"{ds.source}: no q_um column (the command sent to the stage) {purpose}")
    return runs
