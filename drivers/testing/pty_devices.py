"""Serial instruments emulated on a pty, reached through a stable symlink (like /dev/serial/by-id/...):
an interferometer, and a PI controller speaking GCS; :class:`PtyDevice` to write another.

``unplug()`` closes the pty (the driver's reads fail with EIO, as with a USB adapter pulled out) and
removes the link; ``replug()`` creates a new pty behind the same link name. A driver under test
opens ``device.port`` (the link) like any serial port.
"""

from __future__ import annotations

import contextlib
import os
import select
import threading
import time
import tty
from collections.abc import Callable, Iterator
from pathlib import Path


class PtyDevice:
    """A device on a pty behind a stable ``link``, served by ``_serve`` on its own thread: ``unplug``
    and ``replug`` as with a USB adapter pulled out and put back."""

    def __init__(self, link: Path) -> None:
        self.link = Path(link)
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self.replug()

    @property
    def port(self) -> str:
        return str(self.link)

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

    close = unplug

    def _serve(self, master: int, stop: threading.Event) -> None:
        """What the device does with the bytes it gets, on its own thread until ``stop`` is set: a
        subclass says (the base device is a port nobody answers on, as an unpowered instrument)."""
        stop.wait()

    @staticmethod
    def _chunks(master: int, stop: threading.Event, poll_s: float = 0.005) -> Iterator[bytes]:
        """What the driver writes, chunk by chunk, until ``stop`` is set; ``b""`` after a poll of ``poll_s``
        with nothing (or while nobody holds the port open), so a device that also acts on time gets its turn."""
        while not stop.is_set():
            ready, _, _ = select.select([master], [], [], poll_s)
            try:
                yield os.read(master, 4096) if ready else b""
            except OSError:  # nobody holds the port open right now
                yield b""

    @staticmethod
    def _serve_lines(master: int, stop: threading.Event, end: bytes,
                     answer: Callable[[bytes], bytes | None]) -> None:
        """A line-oriented device's ``_serve``: each request up to ``end`` (without it) is answered with
        ``answer(request)`` written whole (None: the device stays silent); a port nobody holds open is
        waited out, and a run of bytes with no ``end`` keeps only its last 4 KiB (line noise)."""
        buffer = b""
        for data in PtyDevice._chunks(master, stop):
            buffer += data
            while end in buffer:
                raw, _, buffer = buffer.partition(end)
                reply = answer(raw)
                if reply is not None:
                    with contextlib.suppress(OSError):
                        os.write(master, reply)
            buffer = buffer[-4096:]


class FakeInterferometer(PtyDevice):
    """Answers ``query`` with ``P <position_nm> nm`` lines, or streams them every ``period_s``."""

    def __init__(self, link: Path, *, query: bytes = b"POS?\r", stream: bool = False, period_s: float = 0.02,
                 eol: bytes = b"\r\n") -> None:
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
        super().__init__(link)

    def line(self) -> bytes:
        if self.reply is not None:
            return self.reply
        return f"P {self.position_nm:.1f} nm".encode() + self.eol

    def _send(self, master: int) -> None:
        if not self.silent:
            os.write(master, self.line())
            self.lines_sent += 1

    def _serve(self, master: int, stop: threading.Event) -> None:
        buffer = b""
        next_line = time.monotonic()
        for data in self._chunks(master, stop):
            with self._lock:
                self.received.extend(data)
            buffer += data
            while self.query and self.query in buffer:
                _, _, buffer = buffer.partition(self.query)
                self._send(master)
            if self.stream and time.monotonic() >= next_line:
                next_line += self.period_s
                self._send(master)


class FakeGcsController(PtyDevice):
    """A PI controller speaking GCS on a pty behind ``link``: ``SVA 1 <V>`` sets the axis' voltage (no
    answer), ``SVA? 1`` -> ``1=<V>``, ``POS? 1`` -> ``1=<position>`` (``position_per_volt`` x V),
    ``ERR?`` -> the error code (then 0), ``*IDN?`` -> :data:`IDN` (the resync query: no value answer looks
    like it). An unknown command or axis sets error 2 / 15, as GCS does.

    Misbehaviours for tests: ``silent`` (answers nothing), ``answer`` (answers every query with this
    instead), ``amplifier_off`` (``SVA`` is accepted but the voltage does not change), ``late_s``
    (command word -> seconds: that query is answered this late; answers leave in the order asked, as
    from a controller that works through its input, at least ``spacing_s`` apart: an ``*IDN?`` asked
    after a late ``SVA?`` is answered after it), ``inject`` (bytes sent as they are, unasked).
    """

    IDN = "(c)2015 Physik Instrumente (PI) GmbH & Co. KG, E-709, 0115018620, 01.502"

    def __init__(self, link: Path, position_per_volt: float = 100.0, axes: tuple[str, ...] = ("1",)) -> None:
        self.position_per_volt = position_per_volt
        #: the controller's axis identifiers (a multi-axis controller: ("1", "2", "3")); ``voltage`` is the first's
        self.axes = axes
        self.voltages = dict.fromkeys(axes, 0.0)
        self.voltage = 0.0
        self.error = 0
        self.silent = False
        self.answer: bytes | None = None
        self.amplifier_off = False
        self.received = bytearray()
        self.lines: list[str] = []  # every complete line received
        self.line_times: list[float] = []  # time.perf_counter() when each line was complete
        self.on_voltage: Callable[[float], None] | None = None  # called (on the pty thread) when SVA lands
        self.late_s: dict[str, float] = {}
        self.spacing_s = 0.0
        self.sent: list[tuple[float, str]] = []  # (time.perf_counter(), answer) for each answer written
        super().__init__(link)

    def inject(self, data: bytes) -> None:
        """Write ``data`` to the port now, unasked (a fragment, a stray line)."""
        os.write(self._master, data)

    def _reply(self, line: str) -> str | None:
        words = line.split()
        if not words:
            return None
        command, args = words[0], words[1:]
        if command == "*IDN?":
            return self.IDN
        if command == "ERR?":
            code, self.error = self.error, 0
            return str(code)
        if command in ("SVA", "SVA?", "POS?") and (not args or args[0] not in self.axes):
            self.error = 15  # invalid axis identifier
            return None
        axis = args[0] if command in ("SVA", "SVA?", "POS?") else self.axes[0]
        if command == "SVA" and len(args) == 2:
            try:
                volts = float(args[1])
            except ValueError:
                self.error = 1  # parameter syntax error
                return None
            if not self.amplifier_off:
                self.voltages[axis] = volts
                if axis == self.axes[0]:
                    self.voltage = volts
                    if self.on_voltage is not None:
                        self.on_voltage(volts)
            return None
        volts_now = self.voltage if axis == self.axes[0] else self.voltages[axis]
        if command == "SVA?":
            return f"{axis}={volts_now:.4f}"
        if command == "POS?":
            return f"{axis}={volts_now * self.position_per_volt:.4f}"
        self.error = 2  # unknown command
        return None

    def _serve(self, master: int, stop: threading.Event) -> None:
        buffer = b""
        pending: list[tuple[float, bytes]] = []  # (when, answer) in the order asked
        last_due = -float("inf")
        for data in self._chunks(master, stop, poll_s=0.002):  # answers due within a couple of ms
            self.received.extend(data)
            buffer += data
            while b"\n" in buffer:
                raw, _, buffer = buffer.partition(b"\n")
                line = raw.decode("latin-1").rstrip("\r")
                now = time.perf_counter()
                self.lines.append(line)
                self.line_times.append(now)
                reply = self._reply(line)
                if reply is None or self.silent:
                    continue
                words = line.split()
                last_due = max(now + self.late_s.get(words[0], 0.0), last_due + self.spacing_s)
                pending.append((last_due, (self.answer if self.answer is not None else reply.encode()) + b"\n"))
            while pending and pending[0][0] <= time.perf_counter():
                answer = pending.pop(0)[1]
                try:
                    os.write(master, answer)
                except OSError:
                    continue
                self.sent.append((time.perf_counter(), answer.decode("latin-1").strip()))
