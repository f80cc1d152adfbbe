"""Shift the wall clock of one process (the daemon under test), never the machine's.

Put this directory on the process' ``PYTHONPATH`` and name a file in ``NANODRIFT_WALL_SHIFT_FILE``:
``time.time()`` and ``time.time_ns()`` then read the real wall clock plus the number of seconds the
file holds (0 when it is empty or missing). A test writes the file to step the clock (an NTP step,
an operator's ``date -s``) while the daemon runs; ``time.monotonic()`` is left alone, as a real
step leaves it. See :class:`helpers.wall_clock.WallShift`.
"""

import os
import time

_PATH = os.environ.get("NANODRIFT_WALL_SHIFT_FILE")

if _PATH:
    _real_time = time.time
    _real_time_ns = time.time_ns
    _cache: dict = {"key": None, "offset_s": 0.0}

    def _offset_s() -> float:
        try:
            stat = os.stat(_PATH)
        except OSError:
            return 0.0
        key = (stat.st_ino, stat.st_mtime_ns)  # an atomic rewrite is a new inode, even within one mtime tick
        if key != _cache["key"]:
            try:
                with open(_PATH) as handle:
                    _cache["offset_s"] = float(handle.read().strip() or 0.0)
            except (OSError, ValueError):
                _cache["offset_s"] = 0.0
            _cache["key"] = key
        return _cache["offset_s"]

    def _shifted_time() -> float:
        return _real_time() + _offset_s()

    def _shifted_time_ns() -> int:
        return _real_time_ns() + int(_offset_s() * 1e9)

    time.time = _shifted_time
    time.time_ns = _shifted_time_ns
