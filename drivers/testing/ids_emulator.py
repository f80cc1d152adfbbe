"""An attocube IDS3010 answering its JSON-RPC 2.0 API on TCP, 127.0.0.1, an ephemeral port (or a given one).

Built from attocube's published API (``attocube-systems/IDS-APIs``: the MATLAB functions' method names and
result layouts, the same as the ``IDS`` python package's ``Displacement`` and ``System`` classes) and the
JSON-RPC 2.0 specification: each request object on the connection is
answered by one response line, ``{"jsonrpc": "2.0", "result": [...], "id": <the request's id>}``, the
result starting with an error/warning number; an unknown method is JSON-RPC error -32601. Three axes,
each a displacement in picometres, a contrast and baseline in permille and a warning number; the
measurement can be stopped (``measurement_running = False``: the mode is "system idle")::

    with IdsEmulator() as ids:                     # serving at once on 127.0.0.1:ids.port
        ids.axes[0].displacement_pm = 240e6         # 240 um
        ids.axes[1].contrast_permille = 20          # a bad signal
        ids.measurement_running = False             # stopped
        ids.requests                                # every (method, params) received, in order

``stop()`` closes the listener and every connection (a device switched off); ``start()`` serves again on
the same port. ``silent`` answers nothing; ``reply`` (bytes) is sent instead of every answer (garbage).
"""

from __future__ import annotations

import json
import socket
import threading
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar

from nanodrift.drivers.testing.loopback import LoopbackDevice, LoopbackServer

#: JSON-RPC 2.0 specification, section 5.1
METHOD_NOT_FOUND = -32601
PARSE_ERROR = -32700
MAX_REQUEST_BYTES = 65536


@dataclass
class IdsAxis:
    displacement_pm: float = 0.0
    contrast_permille: int = 850
    baseline_permille: int = 20
    warning: int = 0
    #: when set, the displacement (pm) at the moment of each request, e.g. an emulated stage's position
    follow: Callable[[], float] | None = None

    def displacement_now_pm(self) -> float:
        return self.follow() if self.follow is not None else self.displacement_pm


class IdsEmulator(LoopbackDevice):
    """See the module docstring. Thread-based, so a synchronous test and an asyncio one use it alike."""

    #: texts for ``com.attocube.system.errorNumberToString`` (a test adds what it needs)
    ERROR_TEXTS: ClassVar[dict[int, str]] = {0: "No error"}

    def __init__(self, port: int = 0, *, start: bool = True) -> None:
        self.axes = [IdsAxis(displacement_pm=123_456_789.0), IdsAxis(displacement_pm=-2_500_000.0), IdsAxis()]
        self.measurement_running = True
        #: what getSystemError answers (the error that stopped a measurement; 0: none)
        self.system_error = 0
        self.silent = False
        self.reply: bytes | None = None
        self.error_texts = dict(self.ERROR_TEXTS)
        self.requests: list[tuple[str, list[Any]]] = []
        self.connections = 0
        self._tcp = LoopbackServer(self._serve, port, name="ids-emulator")
        self._lock = threading.Lock()
        if start:
            self.start()

    @property
    def mode(self) -> str:
        return "measurement running" if self.measurement_running else "system idle"

    def _serve(self, sock: socket.socket) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # one small answer per request, sent at once
        with self._lock:
            self.connections += 1
        with sock.makefile("rb") as rfile:
            while line := rfile.readline(MAX_REQUEST_BYTES):
                answer = self.answer(line)
                if answer is not None and not self.silent:
                    sock.sendall(self.reply if self.reply is not None else answer)

    def answer(self, line: bytes) -> bytes | None:
        """The response line to one request line (None: a notification, which JSON-RPC does not answer)."""
        try:
            request = json.loads(line)
            method, params, request_id = request["method"], request.get("params", []), request.get("id")
        except (ValueError, KeyError, TypeError):
            return self._encode(None, error={"code": PARSE_ERROR, "message": "Parse error"})
        with self._lock:
            self.requests.append((method, list(params)))
        if request_id is None:
            return None
        try:
            result = self._result(method, params)
        except LookupError:
            return self._encode(request_id, error={"code": METHOD_NOT_FOUND, "message": "Method not found"})
        return self._encode(request_id, result=result)

    @staticmethod
    def _encode(request_id: Any, **member: Any) -> bytes:
        return json.dumps({"jsonrpc": "2.0", **member, "id": request_id}).encode() + b"\n"

    def _result(self, method: str, params: list[Any]) -> list[Any]:
        if method == "com.attocube.ids.displacement.getMeasurementEnabled":
            return [0, self.measurement_running]
        if method == "com.attocube.ids.system.getCurrentMode":
            return [0, self.mode]
        if method == "com.attocube.ids.system.getSystemError":
            return [self.system_error]
        if method == "com.attocube.system.errorNumberToString":
            return [0, self.error_texts.get(int(params[1]), f"error {params[1]}")]
        if method in ("com.attocube.ids.displacement.getAxisSignalQuality",
                      "com.attocube.ids.displacement.getAxisDisplacement"):
            axis = self.axes[int(params[0])]  # IndexError is a LookupError: not found, as for a bad axis
            if method.endswith("getAxisSignalQuality"):
                contrast = axis.contrast_permille if self.measurement_running else 0
                return [axis.warning, contrast, axis.baseline_permille]
            return [axis.warning, axis.displacement_now_pm() if self.measurement_running else 0.0]
        if method == "com.attocube.ids.displacement.getAxesDisplacement":
            return [0, *(axis.displacement_now_pm() for axis in self.axes)]
        raise LookupError(method)
