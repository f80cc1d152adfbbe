"""The durable record of what the daemon last wrote to each output: how a restart proves where the stage is.

A device's read-back is a claim. Across a restart (a crash, ``kill -9``, a power cut of the PC) the only
thing that can confirm it is what the daemon itself wrote, so that is kept on disk before every write,
one small JSON file per cell and axis in the state directory (``$STATE_DIRECTORY``, which systemd's
``StateDirectory=`` sets, else ``[daemon] state_dir``). Each file holds the last value the device
confirmed and the value being written now: a kill at any instant leaves the device holding one of the
two. Written atomically with fsync (:func:`nanodrift.atomic.atomic_writer`): a reader sees the old record
or the new one. ``nanodrift confirm-output`` writes the same file when an operator has checked where an
output is.
"""

from __future__ import annotations

import json
import math
import os
import time
from pathlib import Path

from nanodrift.atomic import atomic_writer

RECORD_FORMAT = "nanodrift-output/1"
#: the environment variable systemd sets from ``StateDirectory=`` (a colon-separated list: the first is ours)
STATE_DIRECTORY_ENV = "STATE_DIRECTORY"


def state_directory(configured: Path | None) -> Path | None:
    """Where the daemon keeps its state: ``$STATE_DIRECTORY`` when systemd set it, else ``[daemon] state_dir``
    (None: nowhere, and every start is a first start)."""
    from_systemd = os.environ.get(STATE_DIRECTORY_ENV, "").split(":")[0]
    return Path(from_systemd) if from_systemd else configured


class RecordError(ValueError):
    """A record that cannot be read (names the file and what is wrong): nothing in it is believed."""


class OutputRecords:
    """Read and write the last written value of each axis' output of one cell (``directory`` None: kept nowhere)."""

    def __init__(self, directory: Path | None, cell: str) -> None:
        self.directory = directory
        self.cell = cell
        self._last_v: dict[str, float] = {}  # what :meth:`note_written` recorded last, per axis

    def note_written(self, axis: str, device: str, written_v: float) -> None:
        """A procedure's write (calibrate, validate: one writer at a time, each write awaited): recorded, before
        it is written, with the value written before it as the one the device confirmed."""
        self.save(axis, device, self._last_v.get(axis), written_v)
        self._last_v[axis] = written_v

    def path(self, axis: str) -> Path | None:
        return None if self.directory is None else self.directory / f"output-{self.cell}-{axis}.json"

    def read(self, axis: str, device: str) -> tuple[tuple[float, ...], str]:
        """The voltages ``device`` may hold by what was last written to it (the last confirmed, then the one
        being written; empty when nothing is on record for this axis and device), and who wrote the record:
        ``"daemon"`` (a write of the daemon's or a procedure's) or ``"operator"`` (``nanodrift confirm-output``).
        RecordError: unreadable."""
        path = self.path(axis)
        if path is None or not path.exists():
            return (), "daemon"
        try:
            doc = json.loads(path.read_text(encoding="utf-8"))
            if not isinstance(doc, dict) or doc.get("format") != RECORD_FORMAT:
                raise ValueError(f"not a {RECORD_FORMAT} record")
            values = [doc["confirmed_v"], doc["written_v"]]
            if any(isinstance(v, bool) or not isinstance(v, (int, float, type(None))) for v in values):
                raise ValueError("confirmed_v and written_v must be numbers or null")
        except (OSError, ValueError, KeyError) as error:
            raise RecordError(f"{path}: {error}") from None
        if doc.get("device") != device:
            return (), "daemon"  # another device's record says nothing of this one
        by = "operator" if doc.get("by") == "operator" else "daemon"
        return tuple(float(v) for v in values if v is not None and math.isfinite(v)), by

    def save(self, axis: str, device: str, confirmed_v: float | None, written_v: float, *,
             by: str = "daemon") -> None:
        """Record, before it is written, that ``device`` gets ``written_v`` and held ``confirmed_v`` (fsynced);
        ``by`` "operator": an operator measured it (``nanodrift confirm-output``), nothing was written."""
        path = self.path(axis)
        if path is None:
            return
        doc = {"format": RECORD_FORMAT, "cell": self.cell, "axis": axis, "device": device,
               "confirmed_v": confirmed_v, "written_v": written_v, "by": by, "t": time.time()}
        with atomic_writer(path) as handle:
            json.dump(doc, handle)
