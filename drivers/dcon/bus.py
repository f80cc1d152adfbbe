"""One RS-485 bus (or TCP gateway) of DCON modules: one request at a time, each answer the next CR-ended line.

DCON is strictly master/slave (ADAM 4000 manual, "Command Set"): a module speaks only when asked, one
answer follows one command. So no reader runs in the background: a request drops what is pending, writes
the command and reads up to the CR, in a worker thread (pyserial blocks) bounded by the hub's
``timeout_s``. A TCP gateway is opened as pyserial's ``socket://host:port``. One :class:`asyncio.Lock`
per bus, whichever module's group asks, and a thread lock around the port itself: a request abandoned
by its caller (a cancelled poll) finishes in its thread before the next one may touch the port.
"""

from __future__ import annotations

import asyncio
import contextlib
import termios
import threading

import serial

from nanodrift.drivers.base import DeviceError
from nanodrift.drivers.dcon.config import DconHubConfig
from nanodrift.drivers.dcon.protocol import CR

#: the longest answer taken: eight channels with checksum are ~70 characters
MAX_ANSWER_BYTES = 256


class DconBus:
    """A shared connection; groups ``open``/``release`` it, the last one out closes the port."""

    def __init__(self, config: DconHubConfig) -> None:
        self.config = config
        self._lock = asyncio.Lock()
        self._port_lock = threading.Lock()
        self._port: serial.SerialBase | None = None
        self._users = 0

    @property
    def is_open(self) -> bool:
        return self._port is not None

    @property
    def description(self) -> str:
        return f"DCON hub {self.config.name!r} ({self.config.endpoint})"

    async def open(self) -> None:
        """Open the port unless open; :class:`DeviceError` naming it when it cannot be."""
        async with self._lock:
            await asyncio.to_thread(self._open_blocking)
        self._users += 1  # only a group that opened it releases it

    async def release(self) -> None:
        self._users = max(0, self._users - 1)
        if self._users == 0:
            async with self._lock:
                await asyncio.to_thread(self._close_blocking)

    def _open_blocking(self) -> None:
        with self._port_lock:
            if self._port is not None:
                return
            c = self.config
            settings = {} if c.type == "tcp" else {"baudrate": c.baudrate, "bytesize": c.bytesize, "parity": c.parity,
                                                   "stopbits": c.stopbits}
            try:
                self._port = serial.serial_for_url(c.url, timeout=c.timeout_s, write_timeout=c.timeout_s, **settings)
            except (serial.SerialException, OSError, ValueError) as error:
                raise DeviceError(f"{self.description}: cannot open: {error}") from error

    def _close_blocking(self) -> None:
        with self._port_lock:
            port, self._port = self._port, None
            if port is not None:
                with contextlib.suppress(Exception):  # the port may be dead already: closing is what matters
                    port.close()

    def _exchange_blocking(self, data: bytes, shown: str, expected: str) -> bytes:
        with self._port_lock:
            port = self._port
            if port is None:
                raise DeviceError(f"{self.description}: not open (asked {shown!r})")
            try:
                port.reset_input_buffer()  # nothing that came before the command may begin its answer
                port.write(data)
                port.flush()
                answer = bytes(port.read_until(CR.encode(), MAX_ANSWER_BYTES))
            except (serial.SerialException, OSError, TypeError, termios.error) as error:  # TypeError: a closed fd
                self._port = None
                with contextlib.suppress(Exception):
                    port.close()
                raise DeviceError(f"{self.description}: the port failed asking {shown!r} ({expected}): "
                                  f"{error}") from error
        if not answer.endswith(CR.encode()):
            if not answer:
                raise DeviceError(f"{self.description}: no answer to {shown!r} within {self.config.timeout_s:g} s "
                                  f"(expected {expected}; a module at a wrong address or with other serial "
                                  "settings answers nothing)")
            raise DeviceError(f"{self.description}: answer {answer[:60]!r} to {shown!r} has no CR "
                              f"(expected {expected})")
        return answer[:-1]

    async def request(self, data: bytes, expected: str) -> str:
        """Write ``data`` (a framed command) and return the answer line without its CR.

        :class:`DeviceError` naming the hub, the command and ``expected`` (what the answer should have been)
        on silence, a lost port or a line that is not text. A port that failed is reopened by the next request.
        """
        shown = data.decode("latin-1").rstrip(CR)
        async with self._lock:
            await asyncio.to_thread(self._open_blocking)
            raw = await asyncio.to_thread(self._exchange_blocking, data, shown, expected)
        try:
            return raw.decode("ascii")
        except UnicodeDecodeError:
            raise DeviceError(f"{self.description}: answer {raw[:60]!r} to {shown!r} is not ASCII "
                              f"(expected {expected}; wrong baud rate?)") from None
