"""A serial instrument emulated on a pty, reached through a stable symlink (like /dev/serial/by-id/...).

``unplug()`` closes the pty (the driver's reads fail with EIO, as with a USB adapter pulled out) and
removes the link; ``replug()`` creates a new pty behind the same link name.
"""

from __future__ import annotations

import os
import select
import threading
import time
import tty
from pathlib import Path


class FakeInterferometer:
    """Answers ``query`` with ``P <position_nm> nm`` lines, or streams them every ``period_s``."""

    def __init__(self, link: Path, *, query: bytes = b"POS?\r", stream: bool = False, period_s: float = 0.02,
                 eol: bytes = b"\r\n") -> None:
        self.link = Path(link)
        self.query = query
        self.stream = stream
        self.period_s = period_s
        self.eol = eol
        self.position_nm = 123456.7
        self.reply: bytes | None = None  # send this instead of a proper line (garbage)
        self.silent = False
        self.received = bytearray()
        self.lines_sent = 0
        self._lock = threading.Lock()
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.replug()

    @property
    def port(self) -> str:
        return str(self.link)

    def line(self) -> bytes:
        if self.reply is not None:
            return self.reply
        return f"P {self.position_nm:.1f} nm".encode() + self.eol

    def replug(self) -> None:
        self._master, self._slave = os.openpty()
        tty.setraw(self._slave)
        tmp = self.link.with_name(self.link.name + ".new")
        os.symlink(os.ttyname(self._slave), tmp)
        os.replace(tmp, self.link)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._serve, args=(self._master, self._stop), daemon=True)
        self._thread.start()

    def unplug(self) -> None:
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join(timeout=2)
        self._thread = None
        os.close(self._master)
        os.close(self._slave)
        self.link.unlink(missing_ok=True)

    def _send(self, master: int) -> None:
        if not self.silent:
            os.write(master, self.line())
            self.lines_sent += 1

    def _serve(self, master: int, stop: threading.Event) -> None:
        buffer = b""
        next_line = time.monotonic()
        while not stop.is_set():
            ready, _, _ = select.select([master], [], [], 0.005)
            if ready:
                try:
                    data = os.read(master, 4096)
                except OSError:  # nobody holds the port open right now
                    data = b""
                with self._lock:
                    self.received.extend(data)
                buffer += data
                while self.query and self.query in buffer:
                    _, _, buffer = buffer.partition(self.query)
                    self._send(master)
            if self.stream and time.monotonic() >= next_line:
                next_line += self.period_s
                self._send(master)

    def close(self) -> None:
        self.unplug()
