"""One shared Modbus connection (a TCP socket, or one RS-485 bus) and the requests made on it.

Every request on a hub goes through one :class:`asyncio.Lock`: a bus carries one transaction at a
time, and a module behind one TCP socket answers in order anyway. The hub connects when asked (an
``open``, or a request while the link is down): one attempt per call, and callers that queued behind
an attempt that failed share its answer instead of each trying again. *When* to ask again is not the
hub's decision: the daemon's poller owns the timing (exponential backoff with jitter, one log line per
episode), so there is one back-off, not one per layer. It classifies what went wrong:

- the device answered with an exception code -> :class:`ModbusExceptionError` (the channels fault);
- no answer, lost connection, cannot connect -> :class:`nanodrift.drivers.base.DeviceError` (the daemon
  closes and reopens the group; the channels are refused until the module answers again);
- an answer whose register count or byte count is not exactly what was asked -> ``DeviceError``
  naming the device, the address and both counts. pymodbus would take the byte count at its word
  and drop or invent registers, so the hub decodes FC 3/4 answers itself (:class:`CheckedRegisters`).

pymodbus' own automatic reconnect is switched off (``reconnect_delay=0``): a connection attempt is
made only when the hub is asked for one.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable, Sequence
from typing import Any

from pymodbus import FramerType, ModbusException
from pymodbus.client import AsyncModbusSerialClient, AsyncModbusTcpClient
from pymodbus.pdu.register_message import ReadHoldingRegistersResponse, ReadInputRegistersResponse

from nanodrift.drivers.base import DeviceError
from nanodrift.drivers.modbus.config import ModbusHubConfig

#: Modbus application protocol spec v1.1b3, section 7
EXCEPTION_NAMES: dict[int, str] = {
    1: "illegal function",
    2: "illegal data address",
    3: "illegal data value",
    4: "server device failure",
    5: "acknowledge",
    6: "server device busy",
    8: "memory parity error",
    10: "gateway path unavailable",
    11: "gateway target device failed to respond",
}

REGISTER_KIND_NAMES = {"input": "input register", "holding": "holding register"}

Client = AsyncModbusTcpClient | AsyncModbusSerialClient


class ModbusExceptionError(Exception):
    """The device answered, with a Modbus exception code instead of data."""

    def __init__(self, code: int, device_id: int, input_type: str, address: int, count: int) -> None:
        self.code = code
        name = EXCEPTION_NAMES.get(code, "unknown exception code")
        where = f"{REGISTER_KIND_NAMES[input_type]} {address}"
        if count > 1:
            where += f" (count {count})"
        super().__init__(f"Modbus exception {code} ({name}) from device {device_id} at {where}")


class CheckedRegisters(ReadHoldingRegistersResponse):
    """An FC 3 answer decoded without trusting it: what its byte count says and what it carries.

    pymodbus' own decode reads as many registers as the byte count claims and ignores the rest of
    the frame; this one keeps every complete register the frame carries, and both counts, for the
    hub to compare with the request.
    """

    byte_count = 0
    data_bytes = 0

    def decode(self, data: bytes) -> None:
        self.byte_count = data[0] if data else -1
        payload = data[1:]
        self.data_bytes = len(payload)
        self.registers = [int.from_bytes(payload[i : i + 2], "big") for i in range(0, len(payload) - 1, 2)]


class CheckedInputRegisters(CheckedRegisters, ReadInputRegistersResponse):
    """The same for FC 4."""

    function_code = 4


class ModbusHub:
    """A connection shared by every channel configured with ``hub = <name>``."""

    def __init__(self, config: ModbusHubConfig) -> None:
        if config.type == "serial" and not isinstance(config.port, str):
            raise ValueError(
                f"hub {config.name!r}: type = 'serial' needs port = the serial device "
                f"(e.g. '/dev/ttyUSB0'), got {config.port!r}"
            )
        if config.type == "tcp" and not str(config.port).isdigit():
            raise ValueError(f"hub {config.name!r}: type = 'tcp' needs a numeric port, got {config.port!r}")
        self.config = config
        #: connections tried: a caller that queued for the lock while an attempt failed takes that failure as
        #: its own answer instead of trying again (:meth:`_connect_locked`)
        self.connect_attempts = 0
        self._client: Client | None = None
        self._lost = asyncio.Event()
        self._lock = asyncio.Lock()
        self._users = 0
        self._connect_failure: str | None = None  # why the last attempt failed (None: it succeeded)

    @property
    def name(self) -> str:
        return self.config.name

    @property
    def endpoint(self) -> str:
        if self.config.type == "tcp":
            return f"{self.config.host}:{self.config.port}"
        return str(self.config.port)

    @property
    def connected(self) -> bool:
        return self._client is not None and self._client.connected

    @property
    def request_budget_s(self) -> float:
        """The longest one request may take: every retry waits up to ``timeout_s``."""
        return self.config.timeout_s * (self.config.retries + 1)

    @property
    def poll_timeout_s(self) -> float:
        """A poll's time limit for callers: long enough for the hub to give its own verdict first."""
        return self.request_budget_s + 0.5

    # -- users: groups open/close the hub; the last one out closes the connection ------------------

    def acquire(self) -> None:
        self._users += 1

    async def ensure_connected(self) -> None:
        """Connect unless connected (one attempt); :class:`DeviceError` when the module is unreachable."""
        seen = self.connect_attempts
        async with self._lock:
            await self._connect_locked(seen)

    def release(self) -> None:
        self._users = max(0, self._users - 1)
        if self._users == 0:
            self._drop()

    # -- connection -------------------------------------------------------------------------------

    def _new_client(self, lost: asyncio.Event) -> Client:
        """A fresh client whose disconnect sets ``lost`` (so a late callback of an old one cannot)."""
        c = self.config

        def on_connection_change(connected: bool) -> None:
            if not connected:
                lost.set()

        common: dict[str, Any] = {"timeout": c.timeout_s, "retries": c.retries, "reconnect_delay": 0,
                                  "name": f"hub {c.name}", "trace_connect": on_connection_change}
        client: Client
        if c.type == "tcp":
            client = AsyncModbusTcpClient(c.host, port=int(c.port), **common)
        else:
            client = AsyncModbusSerialClient(str(c.port), framer=FramerType.RTU, baudrate=c.baudrate,
                                             bytesize=c.bytesize, parity=c.parity, stopbits=c.stopbits, **common)
        for response in (CheckedRegisters, CheckedInputRegisters):  # this client's decoder only
            client.register(response)
        return client

    def _drop(self) -> None:
        if self._client is not None:
            self._client.close()
            self._client = None

    async def _connect_locked(self, seen: int) -> None:
        """Connect unless connected. ``seen``: :attr:`connect_attempts` when the caller queued for the
        lock; an attempt made and failed meanwhile is this caller's answer too (no second try)."""
        if self.connected:
            return
        self._drop()
        if self.connect_attempts != seen and self._connect_failure is not None:
            raise DeviceError(self._connect_failure)
        self.connect_attempts += 1
        self._lost = asyncio.Event()
        client = self._new_client(self._lost)
        if not await client.connect():
            client.close()
            self._connect_failure = f"modbus hub {self.name!r}: cannot connect to {self.endpoint}"
            raise DeviceError(self._connect_failure)
        self._client = client
        self._connect_failure = None

    # -- requests ---------------------------------------------------------------------------------

    async def read_registers(self, input_type: str, device_id: int, address: int, count: int) -> list[int]:
        """``count`` registers from ``address`` of ``device_id``; one request, serialised on the hub."""
        where = f"device {device_id} {REGISTER_KIND_NAMES[input_type]} {address} (count {count})"

        def read(client: Client) -> Awaitable[Any]:
            request = client.read_input_registers if input_type == "input" else client.read_holding_registers
            return request(address, count=count, device_id=device_id)

        response = await self._exchange(read, "reading", where)
        if response.isError():
            raise ModbusExceptionError(int(response.exception_code), device_id, input_type, address, count)
        registers: Sequence[int] = response.registers
        byte_count = getattr(response, "byte_count", 2 * len(registers))
        data_bytes = getattr(response, "data_bytes", 2 * len(registers))
        if len(registers) != count or byte_count != 2 * count or data_bytes != 2 * count:
            raise DeviceError(
                f"modbus hub {self.name!r} ({self.endpoint}): malformed answer from {where}: "
                f"{count} registers ({2 * count} bytes) requested, the answer's byte count says {byte_count} "
                f"and it carries {data_bytes} data bytes ({len(registers)} registers)"
            )
        return list(registers)

    def _after_silence(self) -> None:
        # A silent TCP peer is a dead socket: drop it so the next read reconnects. On an RS-485 bus
        # one silent device says nothing about the others: keep the port open.
        if self.config.type == "tcp":
            self._drop()

    # -- writes (an analog output channel) --------------------------------------------------------

    async def write_registers(self, device_id: int, address: int, registers: Sequence[int]) -> None:
        """Write ``registers`` from ``address``: one register with function 6, several with function 16.

        Serialised on the hub's lock like every read. The device's exception answer is a
        :class:`ModbusExceptionError`; no answer or a lost link a :class:`DeviceError`.
        """
        values = [int(r) & 0xFFFF for r in registers]
        fc = 6 if len(values) == 1 else 16
        where = f"device {device_id} holding register {address}" + (f" (count {len(values)})" if fc == 16 else "")

        def write(client: Client) -> Awaitable[Any]:
            if fc == 6:
                return client.write_register(address, values[0], device_id=device_id)
            return client.write_registers(address, values, device_id=device_id)

        response = await self._exchange(write, "writing", where)
        if response.isError():
            raise ModbusExceptionError(int(response.exception_code), device_id, "holding", address, len(values))

    async def _exchange(self, request: Callable[[Client], Awaitable[Any]], verb: str, where: str) -> Any:
        """The response to ``request(client)`` (``verb`` "reading"/"writing" ``where``) on the hub's lock,
        connecting first when the link is down; :class:`DeviceError` on a refusal, silence or a lost link."""
        seen = self.connect_attempts
        async with self._lock:
            await self._connect_locked(seen)
            client = self._client
            assert client is not None
            try:
                call = asyncio.ensure_future(request(client))
            except ModbusException as error:  # pymodbus refuses at once when the link just went away: the next
                self._drop()  # call reconnects (a rebooted module is back at once), after the caller's back-off
                raise DeviceError(f"modbus hub {self.name!r}: {self.endpoint}: {error} ({verb} {where})") from error
            lost = asyncio.ensure_future(self._lost.wait())
            try:
                done, _ = await asyncio.wait(
                    {call, lost}, timeout=self.request_budget_s + 0.5, return_when=asyncio.FIRST_COMPLETED
                )
            except asyncio.CancelledError:
                self._after_silence()  # the caller gave up mid-transaction: where the link stands is unknown
                raise
            finally:
                lost.cancel()
                call.cancel()
            if call in done and call.exception() is None:
                return call.result()
            if call in done:
                self._after_silence()
                failure = call.exception()
                detail = "no response" if isinstance(failure, ModbusException) else repr(failure)
                raise DeviceError(f"modbus hub {self.name!r} ({self.endpoint}): {detail} from {where} "
                                  f"within {self.request_budget_s:g} s") from failure
            if lost in done:
                self._drop()
                raise DeviceError(f"modbus hub {self.name!r}: connection to {self.endpoint} lost while {verb} {where}")
            self._after_silence()
            raise DeviceError(f"modbus hub {self.name!r} ({self.endpoint}): no response from {where}")


class HubLease:
    """One user's share of a hub (a sensor group or the output): ``open`` joins and connects, ``close``
    leaves once; the last user out closes the connection. Safe to close after a failed open."""

    def __init__(self, hub: ModbusHub) -> None:
        self.hub = hub
        self._acquired = False

    async def open(self) -> None:
        if not self._acquired:
            self._acquired = True  # before connecting: close() after a failed open releases the hub
            self.hub.acquire()
        await self.hub.ensure_connected()

    def close(self) -> None:
        if self._acquired:
            self._acquired = False
            self.hub.release()
