"""A serial port read by a thread, its lines handed to the event loop.

Why a thread: pyserial is blocking. One reader thread per port blocks in ``read`` (0.1 s timeout,
so it notices a stop request) and hands each complete line to the loop with
``call_soon_threadsafe``, time-stamped on arrival there; the loop never waits on the port. Writes
(a query of a few bytes) go through ``asyncio.to_thread`` with pyserial's ``write_timeout``; a
request's write first discards what is waiting (a fragment of a line in the reader's buffer, bytes
in the OS buffer, which the thread empties as they come): nothing that arrived before a request can
begin its answer.
A read error (device unplugged, EIO) ends the thread and is handed to the loop the same way.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable
from typing import Any

import serial

READ_TIMEOUT_S = 0.1
MAX_LINE_BYTES = 4096  # a device that never sends the terminator must not grow memory


class SerialLineReader:
    """An open port and the thread that splits what it receives into lines."""

    def __init__(
        self,
        port: serial.SerialBase,
        loop: asyncio.AbstractEventLoop,
        terminator: bytes,
        on_line: Callable[[bytes], None],
        on_error: Callable[[BaseException], None],
    ) -> None:
        self.port = port
        self._loop = loop
        self._terminator = terminator
        self._on_line = on_line
        self._on_error = on_error
        self._stop = threading.Event()
        self._buffer = b""  # the line being received
        self._buffer_lock = threading.Lock()  # the reader thread's appends vs. a request's discard
        self._thread = threading.Thread(target=self._run, name=f"serial-reader {port.name}", daemon=True)
        self._thread.start()

    @classmethod
    def open(cls, url: str, settings: dict[str, Any], **kwargs: Any) -> SerialLineReader:
        """Open ``url`` (blocking: call it from a worker thread) and start reading."""
        port = serial.serial_for_url(url, timeout=READ_TIMEOUT_S, **settings)
        return cls(port, **kwargs)

    def _hand_over(self, callback: Callable[..., None], *args: Any) -> bool:
        try:
            self._loop.call_soon_threadsafe(callback, *args)
        except RuntimeError:  # the loop is closed: nobody is listening any more
            return False
        return True

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                chunk = self.port.read(1)
                if chunk and self.port.in_waiting:
                    chunk += self.port.read(self.port.in_waiting)
            except Exception as error:  # SerialException, OSError, or pyserial's TypeError on a closed fd
                if not self._stop.is_set():
                    self._hand_over(self._on_error, error)
                return
            if not chunk:
                continue
            with self._buffer_lock:
                self._buffer += chunk
                *lines, self._buffer = self._buffer.split(self._terminator)
                if len(self._buffer) > MAX_LINE_BYTES:
                    lines.append(self._buffer)
                    self._buffer = b""
            for line in lines:
                if not self._hand_over(self._on_line, line):
                    return

    @property
    def pending(self) -> int:
        """Bytes of a line received but not yet ended (what a request's write would discard)."""
        with self._buffer_lock:
            return len(self._buffer)

    def write(self, data: bytes, *, discard: bool = False) -> int:
        """Blocking write (bounded by the port's write_timeout): call it from a worker thread.

        ``discard``: first drop the reader's partial line, so an answer to ``data`` cannot start with a
        fragment of something older. Returns how many bytes were dropped. The OS input buffer is not
        flushed: the reader thread empties it as bytes arrive, and flushing it from this thread while the
        reader is in ``read`` makes pyserial fail that read ("readiness to read but returned no data"),
        which closed the shared line (found by the serial chaos suite). A chunk the reader thread took from
        the OS in the very instant of the discard may still be appended after it: the window is the few
        instructions between its ``read`` and its lock.
        """
        dropped = 0
        if discard:
            with self._buffer_lock:
                dropped = len(self._buffer)
                self._buffer = b""
        self.port.write(data)
        self.port.flush()
        return dropped

    def close(self) -> None:
        """Stop the thread and close the port (blocking, at most ~READ_TIMEOUT_S)."""
        self._stop.set()
        cancel = getattr(self.port, "cancel_read", None)
        if cancel is not None:
            with contextlib.suppress(Exception):  # the port may already be dead; closing is what matters
                cancel()
        self._thread.join(timeout=2 * READ_TIMEOUT_S + 1.0)
        with contextlib.suppress(Exception):
            self.port.close()
