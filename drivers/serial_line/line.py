"""A serial instrument polled as a sensor group of one channel.

- Query mode (``query`` set): each poll sends the query and takes the first line that arrives
  after it, within ``timeout_s``.
- Streaming mode (``query`` empty): the device sends lines by itself; the newest is kept, stamped
  with its arrival time. A poll returns it if it arrived within the last ``timeout_s``, else waits
  up to ``timeout_s`` for the next one.

A port that answers requests (a queried sensor, an actuator's controller, or both on one port) is a
*solicited* line, and its answers are matched to the request that asked for them:

- one request outstanding at a time (the port's lock), and its answer is the *first* line after it;
- before a request is written, what waits unread (a fragment of a line, bytes in the OS buffer) is
  dropped, and lines already received belong to nobody;
- a line that arrives while no request waits (an answer that came after its request timed out, a
  second line to one request) is a *late answer*: dropped, counted in ``late_answers``, logged once
  per episode (``serial_late_answers``), and it makes the line *dirty*; so does a request that timed
  out or was cancelled. Before the next request on a dirty line the driver waits until nothing has
  arrived for ``min(timeout_s, QUIET_S)`` (the quiet period; the wait is at most ``timeout_s`` plus
  that), discarding what comes: a late answer to an earlier request is not taken for the answer to
  the next one. A line that does not go quiet is a fault for that request, with nothing sent.

Without more, an answer later than the quiet period after its request timed out cannot be told from
a fresh one (the protocol carries no request ids): it may still be taken for the next answer, once
(found by the serial chaos suite: a late ``SVA? 1`` answer, ``1=-0.5883``, published as the position).
A line with a *resynchronisation query* (``resync_query``/``resync_pattern``, e.g. GCS ``*IDN?`` and
``PI|Physik``) closes that gap: before the next request on a dirty line it sends the resync query
instead of waiting for quiet, and discards every line until one in which ``resync_pattern`` is found.
A controller answers in the order it was asked, so whatever came before that answer is the past,
however late. No such line within ``timeout_s`` is a fault for that request, with nothing sent, and
the line stays dirty. The resync queries that went unanswered are counted (and the count passed on
to the line a reload opens next on the port): an answer to one of them that comes later (a line the
pattern is found in) is discarded, never taken for another request's answer. A write that expects
no answer (an actuator's ``SVA``) goes out on a dirty line without the resync: it takes no answer,
and the controller works through it in order.

What goes wrong, and how it is reported:

- silence -> a ``fault`` reading, "no line from /dev/ttyUSB0 in 1.0 s" (the port itself is fine);
- a line in which ``pattern`` is not found (``re.search``) -> ``fault`` naming what came
  (truncated repr) and the pattern expected: an answer that does not match is never a value;
- the port vanished (unplugged, EIO) or cannot be opened -> :class:`DeviceError`; the daemon closes
  and reopens the group. A ``read`` (or an actuator's ``exchange``) on a closed port opens it first:
  one attempt per call, so the channel recovers under any caller. When to call again is the
  caller's back-off (the daemon's poller, the actuation loop), never the driver's.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
import re
import threading
from functools import partial
from typing import Literal

import structlog

from nanodrift.drivers.base import Clock, DeviceError, Reading, SensorGroup, shown
from nanodrift.drivers.serial_line.config import SerialLineSensorConfig
from nanodrift.drivers.serial_line.reader import SerialLineReader

log = structlog.get_logger(__name__)
#: ports closed while a request on them was left unanswered (the line dirty), each with the resync queries
#: sent on it whose answers are still due: the device may still answer them, so whoever opens the port next (a
#: reload builds a new line for it) resynchronises first and skips those answers (else the first of them is
#: taken for its own resync query's, and its own for the next request's answer)
_UNSETTLED_PORTS: dict[str, int] = {}

SHOWN_CHARS = 60  # of a garbage line in a fault reason
GRACE_S = 0.25  # callers' limit beyond timeout_s, so the driver's own verdict ("no line ...") comes first
QUIET_S = 0.2  # a dirty line is clean again once nothing arrived for min(timeout_s, QUIET_S)


def quiet_for(timeout_s: float) -> float:
    """How long a dirty line must stay silent before a request with this timeout is sent."""
    return min(timeout_s, QUIET_S)


def _close_abandoned(opening: asyncio.Future[SerialLineReader]) -> None:
    """Close a port whose open ended after its caller gave up on it (a thread: closing blocks ~0.1 s)."""
    if opening.cancelled() or opening.exception() is not None:
        return
    threading.Thread(target=opening.result().close, name="serial-close-abandoned", daemon=True).start()


class LineBusyError(DeviceError):
    """A dirty line did not go quiet within its budget: nothing was sent (for a sensor, a fault reading)."""


class SerialLineGroup(SensorGroup):
    """One line-oriented instrument on one serial port."""

    def __init__(self, config: SerialLineSensorConfig, clock: Clock, *, solicited: bool | None = None) -> None:
        """``solicited``: the port only speaks when asked (default: when the sensor queries); the
        actuator's own port is one, whatever its placeholder sensor config says. The resync query is
        the sensor config's (:meth:`use_resync` sets the actuator's on a shared port)."""
        self.config = config
        self.clock = clock
        self.set_channels([config])
        self.solicited = not config.streaming if solicited is None else solicited
        # a poll on a solicited line: a dirty line's quiet wait (<= timeout_s + quiet), then the query (timeout_s)
        wait_s = config.timeout_s + (config.timeout_s + quiet_for(config.timeout_s) if self.solicited else 0.0)
        self.timeout_s = wait_s + GRACE_S
        self._pattern = re.compile(config.pattern)
        self._terminator = config.eol[-1].encode()
        self._reader: SerialLineReader | None = None
        self._error: BaseException | None = None
        self._latest: tuple[str, float] | None = None  # (line, arrival time on self.clock)
        self._seq = 0  # lines received so far
        self._generation = 0  # one per opened port: late callbacks of a closed port are ignored
        self._arrived = asyncio.Event()
        self._lock = asyncio.Lock()  # one request/answer at a time on the port (a query, an actuator's command)
        self._opening = asyncio.Lock()  # one open at a time: one reader on the port
        # a request waits for its answer ("answer": the next line is it; "resync": the next line the resync
        # pattern is found in)
        self._outstanding: Literal["answer", "resync"] | None = None
        self._answer: tuple[str, float] | None = None  # the line that answered the current request
        self._dirty = False  # a late answer may still come: wait for quiet before the next request
        self._dirty_since = 0.0  # loop time the line went dirty
        self._last_line = -math.inf  # loop time of the last line received
        self._episode = False  # late answers are being discarded (logged once, at the first)
        self.late_answers = 0  # lines (or unread fragments) nobody asked for, discarded
        self._resync_query: bytes | None = None
        self._resync_pattern: re.Pattern[str] | None = None
        self._resyncs_pending = 0  # resync queries sent whose answer has not come (yet)
        self.resyncs = 0  # resync queries sent, for tests
        if config.resync is not None:
            self.use_resync(*config.resync)

    def __repr__(self) -> str:
        return f"SerialLineGroup({self.config.name!r}, port={self.config.port!r})"

    @property
    def port(self) -> str:
        return self.config.port

    @property
    def resync(self) -> tuple[str, str] | None:
        """(query, pattern) of the resynchronisation query, or None (a dirty line waits for quiet)."""
        if self._resync_query is None or self._resync_pattern is None:
            return None
        return self._resync_query.decode("latin-1"), self._resync_pattern.pattern

    def use_resync(self, query: str, pattern: str) -> None:
        """Resynchronise a dirty line with ``query``, whose answer is the first line ``pattern`` is found in
        (the actuator's keys on a port whose sensor declares none)."""
        self._resync_query, self._resync_pattern = query.encode("latin-1"), re.compile(pattern)

    # -- the port ---------------------------------------------------------------------------------

    async def open(self) -> None:
        # the sensor's poll and the actuator (at a reload, after a fault) reopen the port on their own: two opens
        # at once would start two readers, the first left reading beside the second (found by the chaos suite)
        async with self._opening:
            if self._reader is not None and self._error is None:
                return
            await self._open_port()

    async def _open_port(self) -> None:
        await self._close_reader()
        c = self.config
        settings = {"baudrate": c.baudrate, "bytesize": c.bytesize, "parity": c.parity, "stopbits": c.stopbits,
                    "write_timeout": c.timeout_s}
        loop = asyncio.get_running_loop()
        self._generation += 1
        # the thread opens the port whatever happens here: shielded, so that an open this call gives up on (its
        # timeout, a reload's cancellation) is closed when it ends instead of reading the port for ever beside
        # the next one (two readers steal each other's bytes: "readiness to read but returned no data", and
        # answers lost for good; found by the serial chaos suite)
        opening = asyncio.ensure_future(asyncio.to_thread(
            SerialLineReader.open, c.port, settings, loop=loop, terminator=self._terminator,
            on_line=partial(self._on_line, self._generation), on_error=partial(self._on_error, self._generation)))
        try:
            # asyncio.timeout, not wait_for: on 3.11 wait_for can swallow a cancellation, and a daemon
            # stopping or reloading then waits for ever on the task that swallowed it (found by the chaos suite)
            async with asyncio.timeout(c.timeout_s):
                self._reader = await asyncio.shield(opening)
        except BaseException as error:
            opening.add_done_callback(_close_abandoned)
            if isinstance(error, TimeoutError):
                raise DeviceError(f"cannot open {c.port}: no answer from the OS within {c.timeout_s:g} s") from None
            if isinstance(error, Exception):  # SerialException, OSError, ValueError for a malformed URL
                raise DeviceError(f"cannot open {c.port}: {error}") from error
            raise  # cancelled
        if self.port in _UNSETTLED_PORTS:  # a line closed before this one left a request unanswered
            self._resyncs_pending = _UNSETTLED_PORTS.pop(self.port)
            self._dirty, self._dirty_since = True, loop.time()

    async def close(self) -> None:
        # after an open in flight (a reload closes the line while a poll or the actuator reopens it): else that
        # open ends after the close, and the closed line keeps a reader on the port beside the next line's
        async with self._opening:
            await self._close_reader()

    async def _close_reader(self) -> None:
        if self._dirty or self._outstanding or self._resyncs_pending:
            _UNSETTLED_PORTS[self.port] = self._resyncs_pending
        reader, self._reader = self._reader, None
        self._generation += 1
        self._error = None
        self._latest = None
        if reader is not None:
            await asyncio.to_thread(reader.close)

    def _on_line(self, generation: int, raw: bytes) -> None:
        if generation != self._generation:
            return
        line = (raw.decode("latin-1").strip(), self.clock.now())
        self._latest = line
        self._seq += 1
        self._last_line = asyncio.get_running_loop().time()
        text = line[0]
        resync_answer = (self._resyncs_pending > 0 and self._resync_pattern is not None
                         and self._resync_pattern.search(text) is not None)
        if resync_answer:
            self._resyncs_pending -= 1
        if self._outstanding == "resync":  # everything before the resync query's answer is the past
            if resync_answer:
                self._answer, self._outstanding = line, None
            else:
                self._discarded(text)
        elif self._outstanding == "answer":  # the first line after a request is its answer ...
            if resync_answer:  # ... but an earlier resync query's (it timed out): in order, the answer is next
                self._discarded(text, dirty=False)
            else:
                self._answer, self._outstanding = line, None
        elif self.solicited:  # nobody asked: a late answer (or a second line to one request)
            self._discarded(text, dirty=not resync_answer)  # a late resync answer: the one awaited, counted
        self._arrived.set()

    def _discarded(self, text: str, *, dirty: bool = True) -> None:
        """Count (and log once per episode) input nobody asked for; ``dirty``: more may follow, so the
        next request waits for the line to go quiet."""
        self.late_answers += 1
        if dirty:
            self._dirty = True
            self._dirty_since = asyncio.get_running_loop().time()
        if not self._episode:
            self._episode = True
            log.warning("serial_late_answers", port=self.port, line=shown(text, SHOWN_CHARS),
                        why="a line nobody asked for (an answer after its request timed out?) is discarded; "
                            "requests wait for the line to go quiet")

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
        c = self.config
        loop = asyncio.get_running_loop()
        if c.query:
            start = loop.time()
            try:
                async with self._lock:  # the whole poll, lock wait included, within self.timeout_s
                    line = await self._request(c.query.encode("latin-1"), "query", answer=True, timeout_s=c.timeout_s,
                                               until=start + 2 * c.timeout_s + quiet_for(c.timeout_s))
            except LineBusyError as error:
                return {c.name: Reading.fault(self.clock.now(), str(error), c.value_unit)}
        elif self._latest is not None and self.clock.now() - self._latest[1] <= c.timeout_s:
            line = self._latest  # streamed within the last timeout_s
        else:  # the next streamed line, within timeout_s
            seq, deadline = self._seq, loop.time() + c.timeout_s
            while self._seq <= seq and self._error is None and (left := deadline - loop.time()) > 0:
                await self._arrival(left)
            line = self._latest if self._seq > seq and self._error is None else None
        if line is None:
            await self._raise_if_vanished()
            return {c.name: Reading.fault(self.clock.now(), f"no line from {self.port} in {c.timeout_s:g} s",
                                          c.value_unit)}
        return {c.name: self.parse(*line)}

    async def _request(self, data: bytes, what: str, *, answer: bool, timeout_s: float,
                       until: float = math.inf) -> tuple[str, float] | None:
        """Make a dirty line clean (the resync query, else a quiet wait), send ``data`` and (``answer``) wait
        ``timeout_s`` for the line that answers it (None: silence); ``until`` (loop time) caps the whole.
        The lock is held."""
        loop = asyncio.get_running_loop()
        if self._reader is None:  # closed (while this request waited for the lock, or vanished): reopen it
            await self.open()
        was_dirty = self._dirty and self.solicited
        if was_dirty and self._resync_query is not None:
            if answer:  # a write that takes no answer needs no clean line: the controller answers in order
                await self._resynchronise(timeout_s, until)
        elif was_dirty:
            quiet_s = quiet_for(timeout_s)
            budget_s = min(timeout_s + quiet_s, until - loop.time())
            await self._quiet(budget_s, quiet_s)
        late_before = self.late_answers
        deadline = min(loop.time() + timeout_s, until)
        line = await self._send(data, what, "answer" if answer else None, timeout_s, deadline)
        if line is not None and not was_dirty and self.late_answers == late_before:
            self._episode = False  # a whole request without a late answer: the episode is over
        return line

    async def _resynchronise(self, timeout_s: float, until: float) -> None:
        """Send the resync query and discard every line up to its answer (:meth:`_on_line`); the line is
        clean then. :class:`LineBusyError` (nothing else sent; the line stays dirty) when no answer comes
        within ``timeout_s`` (or by ``until``)."""
        assert self._resync_query is not None and self._resync_pattern is not None
        loop = asyncio.get_running_loop()
        deadline = min(loop.time() + timeout_s, until)
        discarded = self.late_answers
        query = self._resync_query.decode("latin-1")
        line = await self._send(self._resync_query, f"resync query {query!r}", "resync", timeout_s, deadline)
        if line is None:
            await self._raise_if_vanished()
            raise LineBusyError(
                f"{self.port}: no answer matching resync_pattern {self._resync_pattern.pattern!r} to the resync "
                f"query {query!r} within {timeout_s:g} s after an unanswered request ({self.late_answers - discarded} "
                "late line(s) discarded meanwhile); nothing was sent")
        self._dirty = False

    async def _send(self, data: bytes, what: str, awaits: Literal["answer", "resync"] | None, timeout_s: float,
                    deadline: float) -> tuple[str, float] | None:
        """Write ``data`` and wait until ``deadline`` (loop time) for the line ``awaits`` (None: no answer)."""
        loop = asyncio.get_running_loop()
        reader = self._reader
        assert reader is not None
        self._answer, self._outstanding = None, awaits
        if awaits == "resync":
            self._resyncs_pending += 1
            self.resyncs += 1
        try:
            try:
                async with asyncio.timeout(max(0.0, deadline - loop.time())):
                    dropped = await asyncio.to_thread(reader.write, data, discard=self.solicited)
            except TimeoutError:
                await self.close()
                raise DeviceError(f"{self.port}: {what} not sent within {timeout_s:g} s") from None
            except Exception as error:  # SerialTimeoutException, SerialException, OSError
                await self.close()  # the next read reopens the port
                raise DeviceError(f"{self.port}: cannot send {what}: {error}") from error
            if dropped:
                self._discarded(f"({dropped} unread byte(s) before {what})", dirty=False)  # gone with the flush
            if awaits is None:
                return None
            while self._answer is None and self._error is None and (left := deadline - loop.time()) > 0:
                await self._arrival(left)
            return self._answer
        finally:
            if self._outstanding:  # timed out, failed or cancelled: its answer may still come
                self._outstanding = None
                self._dirty, self._dirty_since = True, loop.time()

    async def _quiet(self, budget_s: float, quiet_s: float) -> None:
        """Wait until nothing has arrived for ``quiet_s`` since the line went dirty, at most ``budget_s``;
        what arrives meanwhile is discarded by :meth:`_on_line`. :class:`LineBusyError` if it does not."""
        loop = asyncio.get_running_loop()
        end = loop.time() + max(0.0, budget_s)
        discarded = self.late_answers
        while True:
            if self._error is not None:
                await self._raise_if_vanished()
            now = loop.time()
            quiet_at = max(self._dirty_since, self._last_line) + quiet_s
            if now >= quiet_at:
                self._dirty = False
                return
            if now >= end:
                raise LineBusyError(
                    f"{self.port}: the line did not go quiet for {quiet_s:g} s within {budget_s:g} s after an "
                    f"unanswered request ({self.late_answers - discarded} late line(s) discarded meanwhile); "
                    "nothing was sent")
            await self._arrival(min(quiet_at, end) - now)

    async def _arrival(self, timeout_s: float) -> None:
        """Wait at most ``timeout_s`` for the next line to arrive (or the port to fail)."""
        self._arrived.clear()
        with contextlib.suppress(TimeoutError):
            async with asyncio.timeout(timeout_s):
                await self._arrived.wait()

    def parse(self, text: str, t: float) -> Reading:
        """A reading from one received line (garbage -> a fault naming what came and what was expected)."""
        unit = self.config.value_unit
        match = self._pattern.search(text)  # grep-like; ^...$ in the pattern demands the whole line
        if match is None:
            return Reading.fault(t, f"unexpected line from {self.port}: {shown(text, SHOWN_CHARS)} "
                                    f"(expected pattern {self.config.pattern!r})", unit)
        try:
            raw = float(match.group("value"))
        except ValueError:
            return Reading.fault(t, f"unexpected value from {self.port}: {match.group('value')!r} in {text!r} "
                                    f"is not a number", unit)
        if not math.isfinite(raw):
            return Reading.fault(t, f"unexpected value from {self.port}: {text!r} is not finite", unit)
        return Reading(value=raw * self.config.scale + self.config.offset, t=t, unit=unit)

    # -- an actuator on this port -----------------------------------------------------------------

    def distrust_answer(self) -> None:
        """The caller does not believe the answer it got (garbled, or a value the device cannot hold): it may
        have been a stray line, with the real answer still to come, so the next request makes the line clean
        first (found by the serial chaos suite: a stray ``1=-777.0000`` taken for an ``SVA?`` answer, whose
        real answer then came as the next ``POS?`` answer and was published as the position). Call it before
        the next ``await``: the port's lock is free, and a waiting request must find the line dirty."""
        if self.solicited:
            self._dirty, self._dirty_since = True, asyncio.get_running_loop().time()

    async def exchange(self, data: bytes, *, answer: bool, timeout_s: float) -> str | None:
        """Write ``data`` and, with ``answer``, return the line that answers it (None: silence for ``timeout_s``).

        For an actuator on this port (a controller that is also this sensor, or the actuator's own
        port): serialised with the sensor's queries by the port's one lock, and matched like them
        (see the module's docstring), so every request gets its own answer. :class:`DeviceError` when
        the port fails or cannot be (re)opened, or when a dirty line does not go quiet in time
        (:class:`LineBusyError`; nothing was written).
        """
        async with self._lock:
            await self._raise_if_vanished()  # then the request (re)opens a closed port
            line = await self._request(data, repr(data.decode("latin-1")), answer=answer, timeout_s=timeout_s)
            if answer and line is None:
                await self._raise_if_vanished()
            return line[0] if line is not None else None
