"""A misbehaving Modbus TCP peer on 127.0.0.1: reads real requests, answers with crafted bytes.

pymodbus' own server always answers correctly; this peer answers what a test tells it to (wrong
protocol id, a byte count that disagrees with the data, more registers than asked, garbage), so a
test pins the exact bytes on the wire. Each connection is served by its own thread; every request
is recorded. Run as a script it serves a rotating set of misbehaviours forever (the daemon-level
log test starts it in-process instead)::

    python tests/helpers/modbus_peer.py --port 15020
"""

from __future__ import annotations

import argparse
import socket
import struct
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass


@dataclass(frozen=True)
class Request:
    """One MBAP-framed request as received."""

    tid: int
    protocol: int
    unit: int
    function: int
    address: int
    count: int
    raw: bytes


#: (request) -> the bytes to send back (b"" = say nothing)
Responder = Callable[[Request], bytes]


def mbap(tid: int, unit: int, pdu: bytes, protocol: int = 0) -> bytes:
    """An MBAP header (length = unit + PDU) and the PDU."""
    return struct.pack(">HHHB", tid, protocol, len(pdu) + 1, unit) + pdu


def registers_pdu(function: int, registers: Sequence[int], byte_count: int | None = None) -> bytes:
    data = b"".join(r.to_bytes(2, "big") for r in registers)
    return bytes([function, 2 * len(registers) if byte_count is None else byte_count]) + data


def correct(values: Sequence[int]) -> Responder:
    """A proper answer with ``count`` of ``values``."""
    return lambda r: mbap(r.tid, r.unit, registers_pdu(r.function, list(values)[: r.count]))


def too_many(extra: int = 1) -> Responder:
    """More registers than requested, with a byte count that agrees with them."""
    return lambda r: mbap(r.tid, r.unit, registers_pdu(r.function, [0x00D7 + i for i in range(r.count + extra)]))


def byte_count_says(byte_count: int) -> Responder:
    """The requested registers, but a byte count that says something else."""
    return lambda r: mbap(r.tid, r.unit, registers_pdu(r.function, [0x00D7 + i for i in range(r.count)], byte_count))


def wrong_protocol_id(protocol: int = 1) -> Responder:
    return lambda r: mbap(r.tid, r.unit, registers_pdu(r.function, [0x00D7] * r.count), protocol=protocol)


def garbage(data: bytes = b"\xde\xad\xbe\xef\x00\x01\x02\x03\xff\xfe\xfd\xfc\x13\x37") -> Responder:
    return lambda r: data


class CraftedModbusPeer:
    """Listens on 127.0.0.1:``port`` (0 = any free port); answers request *n* with ``responders[n % len]``."""

    def __init__(self, responders: Sequence[Responder], port: int = 0) -> None:
        self.responders = list(responders)
        self.requests: list[Request] = []
        self.served: list[str] = []  # the responder name per answer sent
        self._cond = threading.Condition()
        self._listener = socket.create_server(("127.0.0.1", port))
        self._listener.settimeout(0.1)
        self.port = self._listener.getsockname()[1]
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self._accepting = threading.Thread(target=self._accept, name="modbus-peer", daemon=True)
        self._accepting.start()

    def _accept(self) -> None:
        while not self._stop.is_set():
            try:
                conn, _ = self._listener.accept()
            except TimeoutError:
                continue
            except OSError:
                return
            thread = threading.Thread(target=self._serve, args=(conn,), daemon=True)
            self._threads.append(thread)
            thread.start()

    def _serve(self, conn: socket.socket) -> None:
        conn.settimeout(0.1)
        buffer = b""
        with conn:
            while not self._stop.is_set():
                try:
                    data = conn.recv(4096)
                except TimeoutError:
                    continue
                except OSError:
                    return
                if not data:
                    return
                buffer += data
                while len(buffer) >= 12:  # FC 3/4 requests are 12 bytes
                    raw, buffer = buffer[:12], buffer[12:]
                    tid, protocol, _length, unit, function, address, count = struct.unpack(">HHHBBHH", raw)
                    request = Request(tid, protocol, unit, function, address, count, raw)
                    with self._cond:
                        index = len(self.requests)
                        self.requests.append(request)
                        responder = self.responders[index % len(self.responders)]
                    answer = responder(request)
                    try:
                        if answer:
                            conn.sendall(answer)
                    except OSError:
                        return
                    with self._cond:
                        self.served.append(getattr(responder, "__qualname__", "responder"))
                        self._cond.notify_all()

    def wait_requests(self, n: int, timeout: float) -> list[Request]:
        """Until ``n`` requests have been answered; AssertionError after ``timeout`` s."""
        with self._cond:
            if not self._cond.wait_for(lambda: len(self.served) >= n, timeout):
                raise AssertionError(f"only {len(self.served)} of {n} Modbus requests within {timeout} s")
            return list(self.requests)

    def close(self) -> None:
        self._stop.set()
        self._listener.close()
        self._accepting.join(2)
        for thread in self._threads:
            thread.join(2)

    def __enter__(self) -> CraftedModbusPeer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def misbehaving() -> list[Responder]:
    """The rotation a daemon meets in the log test: every kind of wrong answer, then a right one."""
    return [wrong_protocol_id(), byte_count_says(6), garbage(), too_many(), correct([215] * 8)]


def main(argv: Sequence[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description="a misbehaving Modbus TCP peer on 127.0.0.1")
    parser.add_argument("--port", type=int, required=True)
    args = parser.parse_args(argv)
    peer = CraftedModbusPeer(misbehaving(), port=args.port)
    print(f"misbehaving modbus peer on 127.0.0.1:{peer.port}", flush=True)
    try:
        threading.Event().wait()
    except KeyboardInterrupt:
        peer.close()


if __name__ == "__main__":
    main()
