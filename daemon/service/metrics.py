"""Prometheus metrics for the lab's monitoring (``[metrics] listen``): read from the cell at scrape time.

Nothing is updated on the loop: a custom collector builds the ``status`` document (under the state
lock, as the ``status`` queryable does) when Prometheus scrapes, and turns it into metric families.
Health and actuator state are read from that document when it carries them, so this module does not
depend on how they are measured. The one thing measured on the target path is the answer latency:
:class:`AnswerLatency` counts it into fixed buckets (a bisect and two additions under an
uncontended lock), and the collector exposes the counts as a histogram.

Each :class:`MetricsServer` has its own ``CollectorRegistry`` (no global state: tests run several
daemons in one process) and serves HTTP from the daemon's event loop (``asyncio.start_server``), bounded
so that a flood of idle connections cannot take the daemon's file descriptors (with a thread per
connection and no timeout, ~1000 idle ones would exhaust them): at most ``max_connections`` open, a
request head within ``header_timeout_s`` and ``max_header_bytes``, one request per connection. The
page itself is rendered on one worker thread of its own (the collector waits for the state lock,
which the target path holds), never on the loop.
Names follow Prometheus' conventions: ``nanodrift_`` prefix, base units (seconds, metres), counters
ending ``_total``; every series carries the ``cell`` label.
"""

from __future__ import annotations

import asyncio
import bisect
import errno
import gzip
import importlib.metadata
import math
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from http import HTTPStatus
from typing import Any

from prometheus_client import CollectorRegistry
from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, HistogramMetricFamily
from prometheus_client.exposition import choose_encoder
from prometheus_client.registry import Collector

from daemon.errors import UserError

#: answer latency buckets (seconds): the daemon answers in tens to hundreds of µs on a loaded machine
LATENCY_BUCKETS_S = (25e-6, 50e-6, 100e-6, 200e-6, 500e-6, 1e-3, 2e-3, 5e-3, 10e-3, 50e-3, 0.25, 1.0)
#: every value of ``nanodrift_sensor_state`` / ``nanodrift_actuator_state``'s ``state`` label (a state set)
SENSOR_STATES = ("ok", "stale", "fault")
ACTUATOR_STATES = ("ok", "fault", "closed")
#: every value of ``nanodrift_health_state``'s ``state`` label (the health document's states)
HEALTH_STATES = ("unknown", "ok", "degraded")
#: every kind of refusal the daemon produces (``Refusal(kind, ...)``; ``stale``/``fault`` are a channel's
#: state): ``nanodrift_errors_total`` has a series from 0 for each, so ``rate()`` works from the first error
ERROR_KINDS = ("out_of_workspace", "no_model", "missing_channel", "stale", "fault", "voltage_limit",
               "actuator_fault", "bad_payload", "shutting_down", "internal")


def build_version() -> str:
    """The installed distribution's version (``nanodrift --version``), for ``nanodrift_build_info``."""
    try:
        return importlib.metadata.version("nanodrift")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "0+unknown"


class AnswerLatency:
    """Answer latencies counted into :data:`LATENCY_BUCKETS_S` (non-cumulative; the last slot is +Inf)."""

    __slots__ = ("_counts", "_lock", "_sum_s")

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._counts = [0] * (len(LATENCY_BUCKETS_S) + 1)
        self._sum_s = 0.0

    def observe(self, seconds: float) -> None:
        index = bisect.bisect_left(LATENCY_BUCKETS_S, seconds)  # the first bucket with le >= seconds
        with self._lock:
            self._counts[index] += 1
            self._sum_s += seconds

    def snapshot(self) -> tuple[list[int], float]:
        """Cumulative counts per bucket (ending with +Inf, the total) and the sum."""
        with self._lock:
            counts, total = list(self._counts), self._sum_s
        cumulative, running = [], 0
        for count in counts:
            running += count
            cumulative.append(running)
        return cumulative, total


def _number(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    return float(value) if math.isfinite(value) else None


class CellCollector(Collector):
    """Metric families from one status document per scrape (``status_doc`` takes the state lock)."""

    def __init__(self, status_doc: Callable[[], dict[str, Any]], latency: AnswerLatency) -> None:
        self.status_doc = status_doc
        self.latency = latency
        self.version = build_version()

    def collect(self) -> Iterator[Any]:
        doc = self.status_doc()
        cell = str(doc.get("cell", ""))
        yield from self._counters(doc, cell)
        yield self._latency(cell)
        yield from self._sensors(doc, cell)
        yield from self._cell(doc, cell)
        yield from self._health(doc, cell)
        yield from self._actuator(doc, cell)
        build = GaugeMetricFamily("nanodrift_build_info", "1, labelled with the daemon's version",
                                  labels=["cell", "version"])
        build.add_metric([cell, self.version], 1.0)
        yield build

    def _counters(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        counters = doc.get("counters") or {}
        for name, key, text in (
            ("nanodrift_targets_total", "targets", "targets received (each gets one command or one error)"),
            ("nanodrift_commands_total", "commands", "commands computed and published"),
            ("nanodrift_reloads_total", "reloads", "configuration reloads applied"),
            ("nanodrift_reload_failures_total", "reload_failures", "configuration reloads refused"),
        ):
            family = CounterMetricFamily(name, text, labels=["cell"])
            family.add_metric([cell], float(counters.get(key) or 0))
            yield family
        errors = CounterMetricFamily("nanodrift_errors_total", "targets refused, by error kind",
                                     labels=["cell", "kind"])
        counts = {str(kind): count for kind, count in (counters.get("errors") or {}).items()}
        for kind in dict.fromkeys((*ERROR_KINDS, *sorted(counts))):  # the known kinds first, from 0
            errors.add_metric([cell, kind], float(counts.get(kind) or 0))
        yield errors

    def _latency(self, cell: str) -> HistogramMetricFamily:
        cumulative, total = self.latency.snapshot()
        bounds = [repr(b) for b in LATENCY_BUCKETS_S] + ["+Inf"]
        family = HistogramMetricFamily("nanodrift_answer_latency_seconds",
                                       "from a target's arrival to its answer published", labels=["cell"])
        family.add_metric([cell], list(zip(bounds, [float(c) for c in cumulative], strict=True)), total)
        return family

    def _sensors(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        """Readings in base units by role (the model reads temperatures in °C, positions in µm), the
        age, and the state as a state set (one series per state, 1 for the current one)."""
        temperature = GaugeMetricFamily("nanodrift_temperature_celsius", "each temperature channel's last reading",
                                        labels=["cell", "channel"])
        position = GaugeMetricFamily("nanodrift_position_meters", "each position channel's last reading",
                                     labels=["cell", "channel"])
        age = GaugeMetricFamily("nanodrift_sensor_age_seconds", "age of each channel's last reading",
                                labels=["cell", "channel"])
        states = GaugeMetricFamily("nanodrift_sensor_state", "1 for the state each channel is in (ok, stale, fault)",
                                   labels=["cell", "channel", "state"])
        for name, sensor in sorted((doc.get("sensors") or {}).items()):
            if not isinstance(sensor, dict):
                continue
            reading = _number(sensor.get("value"))
            if reading is not None and sensor.get("role") == "temperature":
                temperature.add_metric([cell, name], reading)
            elif reading is not None and sensor.get("role") == "position":
                position.add_metric([cell, name], reading * 1e-6)
            seconds = _number(sensor.get("age_s"))
            if seconds is not None:
                age.add_metric([cell, name], seconds)
            for state in SENSOR_STATES:
                states.add_metric([cell, name, state], 1.0 if sensor.get("state") == state else 0.0)
        yield from (temperature, position, age, states)

    def _cell(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        healthy = GaugeMetricFamily("nanodrift_healthy", "1 while every sensor poller makes progress",
                                    labels=["cell"])
        healthy.add_metric([cell], 1.0 if doc.get("healthy") else 0.0)
        uptime = GaugeMetricFamily("nanodrift_uptime_seconds", "since the daemon started", labels=["cell"])
        uptime.add_metric([cell], _number(doc.get("uptime_s")) or 0.0)
        model = GaugeMetricFamily("nanodrift_model_info", "1, labelled with the model id being served (none: none)",
                                  labels=["cell", "model"])
        info = doc.get("model")
        model.add_metric([cell, str(info.get("id")) if isinstance(info, dict) else "none"], 1.0)
        extrapolating = GaugeMetricFamily("nanodrift_extrapolating",
                                          "1 while a channel (or x) is outside the model's training range",
                                          labels=["cell"])
        extrapolating.add_metric([cell], 1.0 if doc.get("extrapolating") else 0.0)
        yield from (healthy, uptime, model, extrapolating)

    def _health(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        health = doc.get("health")
        if not isinstance(health, dict):
            return
        for name, key, scale, text in (
            ("nanodrift_health_residual_rms_meters", "residual_rms_nm", 1e-9, "RMS of the settled residuals"),
            ("nanodrift_health_residual_mean_meters", "residual_mean_nm", 1e-9, "mean of the settled residuals"),
            ("nanodrift_health_correction_meters", "correction_um", 1e-6, "the adaptive correction applied"),
        ):
            number = _number(health.get(key))
            if number is not None:
                family = GaugeMetricFamily(name, text, labels=["cell"])
                family.add_metric([cell], number * scale)
                yield family
        count = _number(health.get("n"))
        if count is not None:
            residuals = GaugeMetricFamily("nanodrift_health_residuals", "settled residuals in the rolling statistics",
                                          labels=["cell"])
            residuals.add_metric([cell], count)
            yield residuals
        if health.get("state") is not None:
            current = str(health["state"])
            state = GaugeMetricFamily("nanodrift_health_state",
                                      "1 for the health state the daemon is in (unknown, ok, degraded)",
                                      labels=["cell", "state"])
            for name in dict.fromkeys((*HEALTH_STATES, current)):
                state.add_metric([cell, name], 1.0 if name == current else 0.0)
            yield state

    def _actuator(self, doc: dict[str, Any], cell: str) -> Iterator[Any]:
        actuator = doc.get("actuator")
        if not isinstance(actuator, dict) or actuator.get("state") is None:
            return
        kind, current = str(actuator.get("kind", "")), str(actuator["state"])
        family = GaugeMetricFamily("nanodrift_actuator_state", "1 for the state the actuator is in (ok, fault, closed)",
                                   labels=["cell", "kind", "state"])
        for state in dict.fromkeys((*ACTUATOR_STATES, current)):
            family.add_metric([cell, kind, state], 1.0 if state == current else 0.0)
        ok = GaugeMetricFamily("nanodrift_actuator_ok", "1 unless the actuator is in fault", labels=["cell", "kind"])
        ok.add_metric([cell, kind], 0.0 if current == "fault" else 1.0)
        yield from (family, ok)


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
