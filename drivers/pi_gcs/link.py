"""One connection to a GCS controller (TCP or a serial port), shared by the axes driven through it.

GCS framing (PIPython ``gcsmessages.py``, ``checksize``): a request is a line ending in LF; an answer
is complete at a LF *not* preceded by a space, so every line of a multi-line answer but the last ends
with ``" \\n"``. The controller answers queries in the order it was asked and answers nothing to a
setting command, so a batch (``ERR?``, ``SVA 1 2.5``, ``ERR?``, ``SVA? 1``) is written at once and its
answers read in order: one round trip per command, as PIPython itself appends ``ERR?`` to a command
(``GCSMessages.send`` with ``embederr``).

One request batch at a time (a lock per connection): each batch gets its own answers. A batch that
times out or is cancelled leaves answers under way, so the connection is dropped (the next user
reconnects, and the actuator's open clears the error register again): a late answer is never taken
for the next one. A connection is leased: the last axis to close it closes it.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from typing import Any

import serial

from nanodrift.drivers.base import DeviceError
from nanodrift.drivers.pi_gcs.config import PiGcsActuatorConfig

MAX_ANSWER_LINES = 64  # a controller that never ends its answer must not grow memory
READ_TIMEOUT_S = 0.1  # the serial reader thread's poll, so it notices a close


class GcsLink:
    """A connection to one controller: ``ask(lines, answers)`` writes the lines and reads ``answers`` answers."""

    def __init__(self, config: PiGcsActuatorConfig) -> None:
        self.config = config
        self.description = f"PI controller at {config.address}"
        self.users = 0  # axes that opened it and have not closed it
        self.generation = 0  # counts connections made: an axis prepared on an earlier one prepares again
        self._lock = asyncio.Lock()
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._serial: serial.SerialBase | None = None
        self._thread_stop: threading.Event | None = None

    @property
    def connected(self) -> bool:
        return self._reader is not None

    async def connect(self) -> None:
        """Open the connection when it is not open (:class:`DeviceError` when the controller cannot be reached)."""
        if self.connected:
            return
        c = self.config
        try:
            if c.transport == "tcp":
                self._reader, self._writer = await asyncio.wait_for(
                    asyncio.open_connection(c.host, c.tcp_port), c.timeout_s)
            else:
                await self._open_serial()
        except (OSError, TimeoutError, serial.SerialException) as error:
            self.drop()
            raise DeviceError(f"{self.description}: cannot connect: {error or type(error).__name__}") from error
        self.generation += 1

    async def _open_serial(self) -> None:
        """pyserial is blocking: a thread reads the port and feeds an asyncio reader."""
        c = self.config
        port = await asyncio.to_thread(serial.serial_for_url, str(c.port), baudrate=c.baudrate,
                                       timeout=READ_TIMEOUT_S, write_timeout=c.timeout_s)
        port.reset_input_buffer()
        loop = asyncio.get_running_loop()
        reader = asyncio.StreamReader(limit=1 << 16)
        stop = threading.Event()

        def pump() -> None:
            while not stop.is_set():
                try:  # one byte (waiting up to READ_TIMEOUT_S), then whatever else has come
                    data = port.read(1)
                    if data and port.in_waiting:
                        data += port.read(port.in_waiting)
                except (OSError, serial.SerialException, TypeError, AttributeError) as error:
                    _call(loop, reader.set_exception, ConnectionError(f"serial port failed: {error}"))
                    return
                if data:
                    _call(loop, reader.feed_data, data)

        threading.Thread(target=pump, name=f"pi_gcs reader {c.port}", daemon=True).start()
        self._serial, self._thread_stop, self._reader = port, stop, reader

    def drop(self) -> None:
        """Close the connection now (safe when closed)."""
        if self._writer is not None:
            self._writer.close()
        if self._thread_stop is not None:
            self._thread_stop.set()
        if self._serial is not None:
            with contextlib.suppress(Exception):
                self._serial.close()
        self._reader = self._writer = self._serial = self._thread_stop = None

    async def _write(self, data: bytes) -> None:
        if self._writer is not None:
            self._writer.write(data)
            await self._writer.drain()
        elif self._serial is not None:
            await asyncio.to_thread(self._serial.write, data)
        else:
            raise ConnectionError("not connected")

    async def _answer(self) -> str:
        """One whole answer (lines joined with LF, without the continuation spaces)."""
        assert self._reader is not None
        lines: list[str] = []
        while len(lines) < MAX_ANSWER_LINES:
            raw = await self._reader.readline()
            if not raw.endswith(b"\n"):
                raise ConnectionError("the connection closed")
            line = raw.decode("latin-1").removesuffix("\n").removesuffix("\r")
            if line.endswith(" "):  # " \n": more lines follow
                lines.append(line.rstrip(" "))
                continue
            lines.append(line)
            return "\n".join(lines)
        raise ConnectionError(f"an answer of more than {MAX_ANSWER_LINES} lines")

    async def ask(self, lines: list[str], answers: int | None) -> list[str]:
        """Write ``lines`` (each a GCS command without LF) at once, then read ``answers`` answers in order.

        ``answers`` None (``lines`` ending with ``ERR?``): the answers up to ``ERR?``'s (a bare number: every
        query here answers ``item=value``), the last of the list; for queries the controller may not know (an
        unknown one answers nothing and sets error 2). :class:`DeviceError` when the controller cannot be
        reached, closes the connection, or stays silent for ``timeout_s``; the connection is then dropped
        (answers may still be under way).
        """
        async with self._lock:
            await self.connect()
            request = "".join(f"{line}\n" for line in lines)
            try:
                async with asyncio.timeout(self.config.timeout_s):
                    await self._write(request.encode("latin-1"))
                    if answers is not None:
                        return [await self._answer() for _ in range(answers)]
                    found: list[str] = []
                    while not found or "=" in found[-1]:
                        found.append(await self._answer())
                    return found
            except TimeoutError:
                self.drop()
                raise DeviceError(f"{self.description}: no answer within {self.config.timeout_s:g} s to "
                                  f"{' / '.join(lines)!r}") from None
            except (OSError, ConnectionError, serial.SerialException) as error:
                self.drop()
                raise DeviceError(f"{self.description}: connection lost during {' / '.join(lines)!r}: "
                                  f"{error}") from error
            except BaseException:  # cancelled mid-exchange: its answers may still come
                self.drop()
                raise


def _call(loop: asyncio.AbstractEventLoop, callback: Any, *args: Any) -> None:
    with contextlib.suppress(RuntimeError):  # the loop is closed: nobody listens any more
        loop.call_soon_threadsafe(callback, *args)
