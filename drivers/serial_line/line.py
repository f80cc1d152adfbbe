"""A serial instrument polled as a sensor group of one channel.

- Query mode (``query`` set): each poll sends the query and takes the first line that arrives
  after it, within ``timeout_s``.
- Streaming mode (``query`` empty): the device sends lines by itself; the newest is kept, stamped
  with its arrival time. A poll returns it if it arrived within the last ``timeout_s``, else waits
  up to ``timeout_s`` for the next one.

What goes wrong, and how it is reported:

- silence -> a ``fault`` reading, "no line from /dev/ttyUSB0 in 1.0 s" (the port itself is fine);
- a line in which ``pattern`` is not found (``re.search``) -> ``fault`` naming what came
  (truncated repr) and the pattern expected;
- the port vanished (unplugged, EIO) or cannot be opened -> :class:`DeviceError`; the daemon closes
  and reopens the group. A ``read`` (or an actuator's ``exchange``) on a closed port opens it first:
  one attempt per call, so the channel recovers under any caller. When to call again is the
  caller's back-off (the daemon's poller, the actuation loop), never the driver's.
"""

from __future__ import annotations

import asyncio
import math
import re
from functools import partial

from drivers.base import Clock, DeviceError, Reading, SensorGroup
from drivers.serial_line.config import SerialLineSensorConfig
from drivers.serial_line.reader import SerialLineReader

SHOWN_CHARS = 60  # of a garbage line in a fault reason
GRACE_S = 0.25  # callers' limit beyond timeout_s, so the driver's own verdict ("no line ...") comes first


class SerialLineGroup(SensorGroup):
    """One line-oriented instrument on one serial port."""

    def __init__(self, config: SerialLineSensorConfig, clock: Clock) -> None:
        self.config = config
        self.clock = clock
        self.names = (config.name,)
        self.roles = {config.name: config.role}
        self.interval_s = config.interval_s
        self.timeout_s = config.timeout_s + GRACE_S
        self._pattern = re.compile(config.pattern)
        self._terminator = config.eol[-1].encode()
        self._reader: SerialLineReader | None = None
        self._error: BaseException | None = None
        self._latest: tuple[str, float] | None = None  # (line, arrival time on self.clock)
        self._seq = 0  # lines received so far
        self._generation = 0  # one per opened port: late callbacks of a closed port are ignored
        self._arrived = asyncio.Event()
        self.open_attempts = 0  # ports opened or tried, for tests
        self._lock = asyncio.Lock()  # one request/answer at a time on the port (a query, an actuator's command)

    def __repr__(self) -> str:
        return f"SerialLineGroup({self.config.name!r}, port={self.config.port!r})"

    @property
    def port(self) -> str:
        return self.config.port

    # -- the port ---------------------------------------------------------------------------------

    async def open(self) -> None:
        if self._reader is not None and self._error is None:
            return
        await self.close()
        c = self.config
        settings = {"baudrate": c.baudrate, "bytesize": c.bytesize, "parity": c.parity, "stopbits": c.stopbits,
                    "write_timeout": c.timeout_s}
        loop = asyncio.get_running_loop()
        self._generation += 1
        self.open_attempts += 1
        try:
            self._reader = await asyncio.wait_for(
                asyncio.to_thread(SerialLineReader.open, c.port, settings, loop=loop, terminator=self._terminator,
                                  on_line=partial(self._on_line, self._generation),
                                  on_error=partial(self._on_error, self._generation)),
                timeout=c.timeout_s,
            )
        except TimeoutError:
            raise DeviceError(f"cannot open {c.port}: no answer from the OS within {c.timeout_s:g} s") from None
        except Exception as error:  # SerialException, OSError, ValueError for a malformed URL
            raise DeviceError(f"cannot open {c.port}: {error}") from error

    async def close(self) -> None:
        reader, self._reader = self._reader, None
        self._generation += 1
        self._error = None
        self._latest = None
        if reader is not None:
            await asyncio.to_thread(reader.close)

    def _on_line(self, generation: int, raw: bytes) -> None:
        if generation != self._generation:
            return
        self._latest = (raw.decode("latin-1").strip(), self.clock.now())
        self._seq += 1
        self._arrived.set()

    def _on_error(self, generation: int, error: BaseException) -> None:
        if generation != self._generation:
            return
        self._error = error
        self._arrived.set()

    async def _raise_if_vanished(self) -> None:
        """The port failed under the reader: close it (the next read reopens it) and say why."""
        error = self._error
        if error is not None:
            await self.close()
            raise DeviceError(f"{self.port}: {error}")

    # -- polling ----------------------------------------------------------------------------------

    async def read(self) -> dict[str, Reading]:
        await self._raise_if_vanished()
        if self._reader is None:
            await self.open()
        deadline = asyncio.get_running_loop().time() + self.config.timeout_s
        line = await (self._query(deadline) if self.config.query else self._newest(deadline))
        if line is None:
            await self._raise_if_vanished()
            return {self.config.name: Reading.fault(
                self.clock.now(), f"no line from {self.port} in {self.config.timeout_s:g} s",
                self.config.value_unit)}
        return {self.config.name: self.parse(*line)}

    async def _query(self, deadline: float) -> tuple[str, float] | None:
        async with self._lock:
            return await self._transaction(self.config.query.encode("latin-1"), deadline, "query")

    async def _transaction(self, data: bytes, deadline: float, what: str,
                           answer: bool = True) -> tuple[str, float] | None:
        """Send ``data``, then (``answer``) wait for the next line until ``deadline``; the lock is held."""
        if self._reader is None:  # closed while this request waited for the lock
            await self.open()
        assert self._reader is not None
        after = self._seq
        try:
            await asyncio.wait_for(asyncio.to_thread(self._reader.write, data),
                                   timeout=max(0.0, deadline - asyncio.get_running_loop().time()))
        except TimeoutError:
            await self.close()
            raise DeviceError(f"{self.port}: {what} not sent within {self.config.timeout_s:g} s") from None
        except Exception as error:  # SerialTimeoutException, SerialException, OSError
            await self.close()  # the next read reopens the port
            raise DeviceError(f"{self.port}: cannot send {what}: {error}") from error
        return await self._line_after(after, deadline) if answer else None

    async def _newest(self, deadline: float) -> tuple[str, float] | None:
        if self._latest is not None and self.clock.now() - self._latest[1] <= self.config.timeout_s:
            return self._latest
        return await self._line_after(self._seq, deadline)

    async def _line_after(self, seq: int, deadline: float) -> tuple[str, float] | None:
        """The newest line once more than ``seq`` lines have arrived; None at ``deadline`` (loop time)."""
        loop = asyncio.get_running_loop()
        while self._seq <= seq and self._error is None:
            left = deadline - loop.time()
            if left <= 0:
                return None
            self._arrived.clear()
            try:
                await asyncio.wait_for(self._arrived.wait(), timeout=left)
            except TimeoutError:
                continue
        return self._latest if self._error is None else None

    def parse(self, text: str, t: float) -> Reading:
        """A reading from one received line (garbage -> a fault naming what came and what was expected)."""
        unit = self.config.value_unit
        match = self._pattern.search(text)  # grep-like; ^...$ in the pattern demands the whole line
        if match is None:
            shown = text if len(text) <= SHOWN_CHARS else text[:SHOWN_CHARS] + "..."
            return Reading.fault(
                t, f"unexpected line from {self.port}: {shown!r} (expected pattern {self.config.pattern!r})", unit)
        try:
            raw = float(match.group("value"))
        except ValueError:
            return Reading.fault(t, f"unexpected value from {self.port}: {match.group('value')!r} in {text!r} "
                                    f"is not a number", unit)
        if not math.isfinite(raw):
            return Reading.fault(t, f"unexpected value from {self.port}: {text!r} is not finite", unit)
        return Reading(value=raw * self.config.scale + self.config.offset, t=t, unit=unit)

    # -- an actuator on this port -----------------------------------------------------------------

    async def exchange(self, data: bytes, *, answer: bool, timeout_s: float) -> str | None:
        """Write ``data`` and, with ``answer``, return the line that follows (None: silence for ``timeout_s``).

        For an actuator on this port (a controller that is also this sensor, or the actuator's own
        port): serialised with the sensor's queries by the port's one lock, so every request gets
        its own answer. :class:`DeviceError` when the port fails or cannot be (re)opened.
        """
        async with self._lock:
            await self._raise_if_vanished()
            if self._reader is None:
                await self.open()
            deadline = asyncio.get_running_loop().time() + timeout_s
            line = await self._transaction(data, deadline, repr(data.decode("latin-1")), answer)
            if answer and line is None:
                await self._raise_if_vanished()
            return line[0] if line is not None else None
