"""The daemon's logging set up in-process into a buffer, and everything it changed put back afterwards."""

from __future__ import annotations

import io
import json
import logging
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any

import structlog

from nanodrift.logs import configure_logging


@contextmanager
def captured_logging(level: str = "info", clock: Callable[[], float] = time.monotonic) -> Iterator[io.StringIO]:
    """:func:`nanodrift.logs.configure_logging` writing JSON lines into the yielded buffer."""
    stream = io.StringIO()
    root = logging.getLogger()
    saved = (list(root.handlers), root.level, logging.getLogger("pymodbus").level, threading.excepthook,
             sys.excepthook)
    configure_logging(level, json_lines=True, stream=stream, clock=clock)
    try:
        yield stream
    finally:
        for handler in root.handlers:
            if handler not in saved[0]:
                root.removeHandler(handler)
        root.setLevel(saved[1])
        logging.getLogger("pymodbus").setLevel(saved[2])
        threading.excepthook, sys.excepthook = saved[3], saved[4]
        logging.captureWarnings(False)
        structlog.reset_defaults()


def json_lines(stream: io.StringIO) -> list[dict[str, Any]]:
    """Every line written so far, each parsed as the one JSON object it must be."""
    out = []
    for line in stream.getvalue().splitlines():
        doc = json.loads(line)
        assert isinstance(doc, dict), line
        out.append(doc)
    return out
