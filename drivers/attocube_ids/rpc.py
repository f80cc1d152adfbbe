"""A JSON-RPC 2.0 client for the attocube IDS's TCP API: one request at a time, one line each way.

The IDS answers each request object with one response object on one line: attocube's published API
(``attocube-systems/IDS-APIs``: each MATLAB function ``writeline``s one request and ``readline``s one
answer; the ``IDS`` python package's ``ACS.Device.request`` likewise) on TCP port 9090. The ``result`` is a
list whose first element is an error or warning number (0: none; ``com.attocube.system.errorNumberToString``
gives its text); a failed call is a JSON-RPC 2.0 ``error`` object. The request carries ``"api": 2`` as
attocube's clients send it. Every failure of the link or
of the answer's shape is a :class:`DeviceError` naming the device, the method and what was expected.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from typing import Any

from nanodrift.drivers.base import DeviceError, shown

#: the longest answer line taken (a few numbers): a peer sending an endless line must not grow memory
MAX_LINE_BYTES = 65536


class IdsRpcError(DeviceError):
    """The IDS answered a call with a JSON-RPC error object: the exchange itself was sound."""


class IdsRpc:
    """The connection to one IDS (``host``:``port``)."""

    def __init__(self, host: str, port: int, timeout_s: float) -> None:
        self.host = host
        self.port = port
        self.timeout_s = timeout_s
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._next_id = 1
        self._lock = asyncio.Lock()

    @property
    def endpoint(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        return self._writer is not None

    async def connect(self) -> None:
        if self._writer is not None:
            return
        try:
            self._reader, self._writer = await asyncio.wait_for(
                asyncio.open_connection(self.host, self.port, limit=MAX_LINE_BYTES), self.timeout_s)
        except (OSError, TimeoutError) as error:
            raise DeviceError(f"attocube IDS {self.endpoint}: cannot connect: {error or 'timed out'}") from error

    async def close(self) -> None:
        writer, self._writer, self._reader = self._writer, None, None
        if writer is not None:
            writer.close()
            with contextlib.suppress(Exception):  # the peer may be gone already: closing is what matters
                await asyncio.wait_for(writer.wait_closed(), 1.0)

    async def call(self, method: str, params: list[Any] | None = None) -> list[Any]:
        """The ``result`` list of ``method``; :class:`DeviceError` for anything but a well-formed answer."""
        async with self._lock:
            await self.connect()
            try:
                return await self._call_locked(method, params or [])
            except IdsRpcError:
                raise  # a well-formed answer: the stream is in step
            except DeviceError:
                await self.close()  # the stream may hold a late answer: never read it as the next one's
                raise

    async def _call_locked(self, method: str, params: list[Any]) -> list[Any]:
        assert self._reader is not None and self._writer is not None
        request_id = self._next_id
        self._next_id += 1
        request = {"jsonrpc": "2.0", "method": method, "params": params, "id": request_id, "api": 2}
        where = f"attocube IDS {self.endpoint}: {method}"
        try:
            self._writer.write(json.dumps(request).encode() + b"\n")
            await asyncio.wait_for(self._writer.drain(), self.timeout_s)
            line = await asyncio.wait_for(self._reader.readuntil(b"\n"), self.timeout_s)
        except TimeoutError:
            raise DeviceError(f"{where}: no answer within {self.timeout_s:g} s (expected a JSON-RPC response "
                              f"with id {request_id})") from None
        except asyncio.IncompleteReadError as error:
            raise DeviceError(f"{where}: the connection closed before the answer "
                              f"(received {shown(error.partial)})") from None
        except asyncio.LimitOverrunError:
            raise DeviceError(f"{where}: an answer line longer than {MAX_LINE_BYTES} bytes") from None
        except OSError as error:
            raise DeviceError(f"{where}: connection lost: {error}") from error
        return self._result(line, request_id, where)

    @staticmethod
    def _result(line: bytes, request_id: int, where: str) -> list[Any]:
        expected = f"a JSON-RPC 2.0 response with id {request_id} and a result list"
        try:
            answer = json.loads(line)
        except (ValueError, UnicodeDecodeError):
            raise DeviceError(f"{where}: answer {shown(line)} is not JSON (expected {expected})") from None
        if not isinstance(answer, dict) or answer.get("id") != request_id:
            raise DeviceError(f"{where}: answer {shown(line)} is not {expected}")
        error = answer.get("error")
        if error is not None:
            code = error.get("code") if isinstance(error, dict) else None
            message = error.get("message") if isinstance(error, dict) else error
            raise IdsRpcError(f"{where}: JSON-RPC error {code}: {message}")
        result = answer.get("result")
        if not isinstance(result, list) or not result:
            raise DeviceError(f"{where}: answer {shown(line)} has no result list (expected {expected})")
        return result
