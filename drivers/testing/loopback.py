"""A TCP device on 127.0.0.1 that a test can switch off and on again, as the emulators of network instruments
(the IDS interferometer, a DCON bus behind a serial-to-Ethernet gateway) need.

``stop()`` closes the listening socket and cuts every open connection (the driver sees the peer gone, as
with a device powered off); ``start()`` listens again on the same port.
"""

from __future__ import annotations

import contextlib
import socket
import socketserver
import threading
from collections.abc import Callable
from typing import Self


class LoopbackServer:
    """Serves each connection with ``serve(sock)`` on its own thread; ``port`` 0: an ephemeral port, kept
    across ``stop``/``start``. A connection that fails (``OSError``) just ends."""

    def __init__(self, serve: Callable[[socket.socket], None], port: int = 0, *, name: str = "loopback") -> None:
        self.port = port
        self._serve = serve
        self._name = name
        self._server: socketserver.ThreadingTCPServer | None = None
        self._thread: threading.Thread | None = None
        self._lock = threading.Lock()
        self._sockets: set[socket.socket] = set()

    def start(self) -> None:
        owner = self

        class Handler(socketserver.BaseRequestHandler):
            def handle(self) -> None:
                owner._handle(self.request)

        class Server(socketserver.ThreadingTCPServer):
            allow_reuse_address = True
            daemon_threads = True

        self._server = Server(("127.0.0.1", self.port), Handler)
        self.port = self._server.server_address[1]
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.05},
                                        name=self._name, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        server, self._server = self._server, None
        if server is None:
            return
        server.shutdown()
        server.server_close()
        with self._lock:
            for sock in list(self._sockets):
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)
                sock.close()
            self._sockets.clear()
        if self._thread is not None:
            self._thread.join(timeout=2)

    def _handle(self, sock: socket.socket) -> None:
        with self._lock:
            self._sockets.add(sock)
        try:
            self._serve(sock)
        except OSError:
            return
        finally:
            with self._lock:
                self._sockets.discard(sock)


class LoopbackDevice:
    """An emulator served by its :class:`LoopbackServer` ``_tcp``: its ``port``, ``start``, ``stop`` (also
    ``close``), and a ``with`` block that stops it."""

    _tcp: LoopbackServer

    @property
    def port(self) -> int:
        return self._tcp.port

    def start(self) -> None:
        self._tcp.start()

    def stop(self) -> None:
        self._tcp.stop()

    def close(self) -> None:
        self.stop()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()
