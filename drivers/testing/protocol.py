"""A device that expects an exact conversation, in the spirit of PyMeasure's ``expected_protocol``.

::

    with expected_protocol(tmp_path / "ttyBOX", [(b"SVA 1 4.9990\\n", None),
                                                 (b"SVA? 1\\n", b"1=4.9990\\n")]) as box:
        ... drive the plugin against box.port ...
    # on leaving: every exchange took place, in order, and nothing else was written

Each exchange is what the driver must write (exactly these bytes) and what the device answers then
(``None``: nothing). Bytes that are not the next expected request are kept in ``unexpected`` and fail
the check, as do exchanges that never came. The device lives on a pty (:class:`PtyDevice`), so the
driver under test opens a real serial port.
"""

from __future__ import annotations

import os
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path

from nanodrift.drivers.testing.pty_devices import PtyDevice

Exchange = tuple[bytes, bytes | None]


class ScriptedDevice(PtyDevice):
    """Answers the requests of ``exchanges`` in order; records everything else as unexpected."""

    def __init__(self, link: Path, exchanges: Sequence[Exchange]) -> None:
        self.exchanges = list(exchanges)
        self.done = 0  # exchanges completed
        self.unexpected = bytearray()
        self._lock = threading.Lock()
        super().__init__(link)

    def problems(self) -> list[str]:
        """What differs from the script (empty: the conversation was exactly the script)."""
        with self._lock:
            found = []
            if self.unexpected:
                expected = self.exchanges[self.done][0] if self.done < len(self.exchanges) else b"nothing more"
                found.append(f"unexpected bytes {bytes(self.unexpected)!r} (expected {expected!r} next)")
            if self.done < len(self.exchanges):
                missing = [request for request, _ in self.exchanges[self.done:]]
                found.append(f"{len(missing)} exchange(s) never took place, first {missing[0]!r}")
            return found

    def _serve(self, master: int, stop: threading.Event) -> None:
        buffer = b""
        for data in self._chunks(master, stop):
            buffer += data
            with self._lock:
                while buffer and self.done < len(self.exchanges) and buffer.startswith(self.exchanges[self.done][0]):
                    request, answer = self.exchanges[self.done]
                    buffer = buffer[len(request):]
                    self.done += 1
                    if answer:
                        os.write(master, answer)
                # what is left is the start of the next request (the rest is on its way), or unexpected
                if buffer and not (self.done < len(self.exchanges) and self.exchanges[self.done][0].startswith(buffer)):
                    self.unexpected += buffer
                    buffer = b""


@contextmanager
def expected_protocol(link: Path, exchanges: Sequence[Exchange]) -> Iterator[ScriptedDevice]:
    """A :class:`ScriptedDevice` for the ``with`` body; on a clean exit, an ``AssertionError`` naming
    every difference between the conversation and ``exchanges``."""
    device = ScriptedDevice(link, exchanges)
    try:
        yield device
    finally:
        device.close()
    problems = device.problems()
    assert not problems, "; ".join(problems)
