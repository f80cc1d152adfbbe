"""The metrics' HTTP endpoint (``[metrics] listen``): ``/metrics`` served from the daemon's event loop, bounded.

Each :class:`MetricsServer` has its own ``CollectorRegistry`` holding a
:class:`nanodrift.service.metrics.CellCollector` and prometheus_client's ``ProcessCollector``
(``process_*``: descriptors, memory, CPU; no global state: tests run several daemons in one
process) and serves HTTP from the daemon's event loop (``asyncio.start_server``), bounded so that a
flood of idle connections cannot take the daemon's file descriptors (with a thread per connection
and no timeout, ~1000 idle ones would exhaust them): at most ``max_connections`` open, a request
head within ``header_timeout_s`` and ``max_header_bytes``, one request per connection. The page
itself is rendered on one worker thread of its own (the collector waits for the state lock, which
the target path holds), never on the loop.
"""

from __future__ import annotations

import asyncio
import errno
import gzip
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from http import HTTPStatus
from typing import Any

from prometheus_client import CollectorRegistry, ProcessCollector
from prometheus_client.exposition import choose_encoder

from nanodrift.errors import UserError
from nanodrift.service.latency import AnswerLatency
from nanodrift.service.metrics import CellCollector


def split_listen(listen: str) -> tuple[str, int]:
    """``"127.0.0.1:9464"`` -> (host, port); ``[::1]:9464`` for IPv6."""
    host, _, port = listen.rpartition(":")
    return host.strip("[]"), int(port)


#: what ``/`` answers (a person's browser, a load balancer's probe)
INDEX_TEXT = b"nanodrift: Prometheus metrics at /metrics\n"


class MetricsServer:
    """The HTTP endpoint: ``/metrics`` on ``listen`` from the running event loop, with its own registry.

    Bounded, because the page is open to whatever reaches the port:

    - at most ``max_connections`` open at once. A connection beyond that takes the place of the oldest
      one that has not sent its request yet (an idle one: it is closed), so a scrape gets through a
      flood of idle connections at once; when every open one is being answered, the new one is
      closed at once, unread;
    - the request head (request line and headers, at most ``max_header_bytes``) must be complete
      within ``header_timeout_s`` of the connection, however it trickles in (slowloris): else 408
      and the connection is closed; too long a head gets 431;
    - one request per connection (``Connection: close``), and the answer must be taken within
      ``send_timeout_s``;
    - ``GET``/``HEAD`` of ``/metrics`` (and ``/``, a line of text) only: 404 for another path, 405
      for another method, 400 for what is not HTTP/1.x.

    ``start`` and ``stop`` are coroutines on the loop that serves; ``stop`` is idempotent.
    """

    def __init__(self, listen: str, status_doc: Callable[[], dict[str, Any]], latency: AnswerLatency, *,
                 max_connections: int = 32, header_timeout_s: float = 5.0, send_timeout_s: float = 10.0,
                 max_header_bytes: int = 8192) -> None:
        self.listen = listen
        self.registry = CollectorRegistry(auto_describe=False)
        self.registry.register(CellCollector(status_doc, latency))
        ProcessCollector(registry=self.registry)  # process_open_fds, process_max_fds, memory, CPU, start time
        self.max_connections = max_connections
        self.header_timeout_s = header_timeout_s
        self.send_timeout_s = send_timeout_s
        self.max_header_bytes = max_header_bytes
        #: every open connection -> True once its request head is read (being answered); oldest first
        self._connections: dict[asyncio.StreamWriter, bool] = {}
        self._handlers: set[asyncio.Task[None]] = set()
        self._server: asyncio.Server | None = None
        self._executor: ThreadPoolExecutor | None = None
        #: the most connections ever open at once, idle ones closed to admit a new one, new ones closed unread
        self.peak_connections = 0
        self.evicted = 0
        self.refused = 0

    @property
    def open_connections(self) -> int:
        return len(self._connections)

    @property
    def answering_connections(self) -> int:
        """Open connections whose request is being answered (the others are idle: waiting for a head)."""
        return sum(self._connections.values())

    async def start(self) -> None:
        host, port = split_listen(self.listen)
        try:
            self._server = await asyncio.start_server(self._accept, host, port, limit=self.max_header_bytes)
        except (OSError, UnicodeError) as error:  # UnicodeError: a host name the resolver cannot encode
            in_use = getattr(error, "errno", None) == errno.EADDRINUSE
            reason = "already in use" if in_use else getattr(error, "strerror", None) or str(error)
            raise UserError(f"[metrics] listen = {self.listen!r}: cannot serve metrics there ({reason})") from None
        # one thread renders the page: concurrent scrapes queue instead of each taking a thread
        self._executor = ThreadPoolExecutor(max_workers=1, thread_name_prefix="metrics")

    @property
    def url(self) -> str:
        host, port = split_listen(self.listen)
        if self._server is not None and self._server.sockets:
            port = self._server.sockets[0].getsockname()[1]
        return f"http://{host if ':' not in host else f'[{host}]'}:{port}/metrics"

    async def stop(self) -> None:
        """Stop listening and close every connection; a second call (or one before ``start``) does nothing."""
        server, self._server = self._server, None
        try:
            if server is not None:
                server.close()
            for writer in list(self._connections):
                writer.transport.abort()
            handlers = list(self._handlers)
            for task in handlers:
                task.cancel()
            await asyncio.gather(*handlers, return_exceptions=True)
            if server is not None:
                await server.wait_closed()
        finally:
            self._connections.clear()
            self._handlers.clear()
            executor, self._executor = self._executor, None
            if executor is not None:
                executor.shutdown(wait=False, cancel_futures=True)

    def _admit(self, writer: asyncio.StreamWriter) -> bool:
        """Room for a new connection: below the bound, or by closing the oldest idle one."""
        if self._server is None:  # accepted just before stop
            return False
        if len(self._connections) >= self.max_connections:
            idle = next((w for w, answering in self._connections.items() if not answering), None)
            if idle is None:
                self.refused += 1
                return False
            del self._connections[idle]
            idle.transport.abort()  # its handler sees the end of its stream and returns
            self.evicted += 1
        self._connections[writer] = False
        self.peak_connections = max(self.peak_connections, len(self._connections))
        return True

    async def _accept(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        if not self._admit(writer):
            writer.transport.abort()
            return
        task = asyncio.current_task()
        assert task is not None
        self._handlers.add(task)
        writer.transport.set_write_buffer_limits(high=0)  # drain() returns once the kernel has it all
        done = False
        try:
            await self._serve(reader, writer)
            done = True
        except (OSError, TimeoutError, asyncio.IncompleteReadError):
            pass  # the client went away, or did not take the answer in time
        except asyncio.CancelledError:  # by stop(), the only one that cancels a handler: end quietly (the
            pass  # streams module logs a handler task that ends cancelled as an error)
        finally:
            self._connections.pop(writer, None)
            self._handlers.discard(task)
            if done:
                writer.close()  # nothing left in the transport's buffer: closes at once
            else:
                writer.transport.abort()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            async with asyncio.timeout(self.header_timeout_s):
                head = await reader.readuntil(b"\r\n\r\n")
        except TimeoutError:
            await self._send(writer, HTTPStatus.REQUEST_TIMEOUT, b"request head not received in time\n")
            return
        except asyncio.LimitOverrunError:
            await self._send(writer, HTTPStatus.REQUEST_HEADER_FIELDS_TOO_LARGE,
                             f"request head over {self.max_header_bytes} bytes\n".encode())
            return
        if writer not in self._connections:  # closed by stop() or to admit another while the head arrived
            return
        self._connections[writer] = True  # being answered: never closed to admit another
        request = parse_request(head)
        if isinstance(request, HTTPStatus):
            extra = ("Allow: GET, HEAD",) if request is HTTPStatus.METHOD_NOT_ALLOWED else ()
            await self._send(writer, request, f"{request.value} {request.phrase}\n".encode(), extra=extra)
            return
        method, path, headers = request
        if path == "/":
            await self._send(writer, HTTPStatus.OK, INDEX_TEXT, head_only=method == "HEAD")
            return
        encoder, content_type = choose_encoder(headers.get("accept", ""))
        compress = "gzip" in headers.get("accept-encoding", "")
        try:
            body = await asyncio.get_running_loop().run_in_executor(self._executor, _render, encoder,
                                                                     self.registry, compress)
        except Exception as error:  # a bug in the collector: the scrape fails with the reason, the daemon serves on
            await self._send(writer, HTTPStatus.INTERNAL_SERVER_ERROR,
                             f"{type(error).__name__}: {error}\n".encode())
            return
        await self._send(writer, HTTPStatus.OK, body, content_type=content_type, head_only=method == "HEAD",
                         extra=("Content-Encoding: gzip",) if compress else ())

    async def _send(self, writer: asyncio.StreamWriter, status: HTTPStatus, body: bytes, *,
                    content_type: str = "text/plain; charset=utf-8", extra: tuple[str, ...] = (),
                    head_only: bool = False) -> None:
        lines = (f"HTTP/1.1 {status.value} {status.phrase}", f"Content-Type: {content_type}",
                 f"Content-Length: {len(body)}", "Connection: close", *extra)
        writer.write(("\r\n".join(lines) + "\r\n\r\n").encode("latin-1") + (b"" if head_only else body))
        async with asyncio.timeout(self.send_timeout_s):
            await writer.drain()


def _render(encoder: Callable[[CollectorRegistry], bytes], registry: CollectorRegistry, compress: bool) -> bytes:
    body = encoder(registry)
    return gzip.compress(body, compresslevel=1) if compress else body


def parse_request(head: bytes) -> tuple[str, str, dict[str, str]] | HTTPStatus:
    """(method, path, lower-cased headers) of a request head for ``/`` or ``/metrics``, else the status to answer."""
    lines = head.decode("latin-1").split("\r\n")
    parts = lines[0].split(" ")
    if len(parts) != 3 or not parts[2].startswith("HTTP/1.") or not parts[1].startswith("/"):
        return HTTPStatus.BAD_REQUEST
    headers: dict[str, str] = {}
    for line in lines[1:]:
        if not line:
            continue
        name, colon, text = line.partition(":")
        if not colon or not name or name != name.strip():
            return HTTPStatus.BAD_REQUEST
        headers[name.lower()] = text.strip()
    method, path = parts[0], parts[1].split("?", 1)[0]
    if path not in ("/", "/metrics"):
        return HTTPStatus.NOT_FOUND
    if method not in ("GET", "HEAD"):
        return HTTPStatus.METHOD_NOT_ALLOWED
    return method, path, headers
