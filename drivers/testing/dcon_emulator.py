"""DCON thermocouple modules (ADAM-4018 / ICP DAS I-7018 style) on an emulated RS-485 bus: a pty.

Built from the ADAM 4000 Series User's Manual and ICP DAS's checksum rule (see
:mod:`nanodrift.drivers.dcon.protocol`): ``#AA`` answers ``>`` and every channel's value in engineering
units (``+0025.23``), ``#AAN`` channel N alone, an open thermocouple reads the over-range code
``+9999``; ``$AAM`` answers the module name, ``$AA2`` its configuration, ``$AAB`` (when the model has
it) the open/out-of-range mask;
``?AA`` answers a command the module does not know; a wrong address, a bad checksum or a syntax error
gets no answer, as on the real bus. Several modules may share the bus (one address each)::

    bus = DconBusEmulator(tmp_path / "ttyRS485", [DconModule(1, [21.5, 22.0, 22.5, 23.0], open_channels={2})])
    ... a plugin opens bus.port ...
    bus.modules[1].temperatures_c[0] = 24.0      # what the next #01 reads
    bus.requests                                  # every command the bus received, in order

:class:`DconTcpGateway` serves the same modules behind a serial-to-Ethernet gateway (raw TCP, 127.0.0.1).
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

from nanodrift.drivers.dcon.protocol import CHECKSUM_BIT, checksum
from nanodrift.drivers.testing.loopback import LoopbackDevice, LoopbackServer
from nanodrift.drivers.testing.pty_devices import PtyDevice


@dataclass
class DconModule:
    """One module: its address, a temperature per channel (4 or 8), and what is wrong with it."""

    address: int
    temperatures_c: list[float]
    name: str = "4018"
    open_channels: set[int] = field(default_factory=set)
    #: channels ``$AAB`` flags besides the open ones (a module diagnosing wiring its values do not show yet)
    diagnosed_channels: set[int] = field(default_factory=set)
    checksum: bool = False
    #: answers $AAB (ADAM-4018+, 4019+); a module without it answers ?AA
    diagnoses: bool = True
    #: $AA2's FF byte data format bits (0 = engineering units)
    data_format: int = 0
    type_code: int = 0x0F  # thermocouple type K (ADAM 4000 manual, input range table)
    #: when set, every channel's temperature at the moment of each read, e.g. an emulated cell's thermocouples
    follow: Callable[[], Sequence[float]] | None = None

    def value_text(self, channel: int, temperatures_c: Sequence[float] | None = None) -> str:
        if channel in self.open_channels:
            return "+9999"
        return f"{(temperatures_c or self.temperatures_c)[channel]:+08.2f}"

    def answer(self, command: str) -> str:
        """The answer (without checksum and CR) to ``command`` addressed to this module."""
        aa = f"{self.address:02X}"
        if command == f"#{aa}":
            now = list(self.follow()) if self.follow is not None else self.temperatures_c
            return ">" + "".join(self.value_text(c, now) for c in range(len(now)))
        if len(command) == 4 and command.startswith(f"#{aa}") and command[3].isdigit():  # #AAN: one channel
            channel = int(command[3])
            return f">{self.value_text(channel)}" if channel < len(self.temperatures_c) else f"?{aa}"
        if command == f"${aa}M":
            return f"!{aa}{self.name}"
        if command == f"${aa}2":
            format_byte = self.data_format | (CHECKSUM_BIT if self.checksum else 0)
            return f"!{aa}{self.type_code:02X}06{format_byte:02X}"  # baud code 06: 9600 bps
        if command == f"${aa}B" and self.diagnoses:
            mask = sum(1 << c for c in self.open_channels | self.diagnosed_channels)
            return f"!{aa}{mask:02X}"
        return f"?{aa}"


def bus_answer(modules: dict[int, DconModule], line: str) -> str | None:
    """What the bus carries back for one command line (without its CR): the addressed module's answer,
    with its checksum when it uses one; None when no module answers (a syntax error, nobody at that
    address, a bad checksum: the manual's "no response")."""
    if len(line) < 3 or line[0] not in "#$%@":
        return None
    try:
        address = int(line[1:3], 16)
    except ValueError:
        return None
    module = modules.get(address)
    if module is None:
        return None
    command = line
    if module.checksum:
        command, given = line[:-2], line[-2:]
        if len(command) < 3 or given != checksum(command):
            return None
    answer = module.answer(command)
    return answer + (checksum(answer) if module.checksum else "")


class _Bus:
    """What every transport of the emulated bus shares: the modules, the misbehaviours, the record."""

    def __init__(self, modules: Sequence[DconModule]) -> None:
        self.modules = {m.address: m for m in modules}
        self.silent = False
        self.reply: bytes | None = None
        self.requests: list[str] = []
        self._lock = threading.Lock()

    def respond(self, raw: bytes) -> bytes | None:
        line = raw.decode("latin-1")
        with self._lock:
            self.requests.append(line)
            answer = None if self.silent else bus_answer(self.modules, line)
            if answer is None:
                return None
            return self.reply if self.reply is not None else (answer + "\r").encode("latin-1")


class DconBusEmulator(_Bus, PtyDevice):
    """An RS-485 bus of :class:`DconModule` on a pty behind ``link``; ``silent`` makes every module mute,
    ``reply`` (bytes) replaces every answer (garbage on the line); ``requests`` is every command line."""

    def __init__(self, link: Path, modules: Sequence[DconModule]) -> None:
        _Bus.__init__(self, modules)
        PtyDevice.__init__(self, link)

    def _serve(self, master: int, stop: threading.Event) -> None:
        self._serve_lines(master, stop, b"\r", self.respond)


class DconTcpGateway(_Bus, LoopbackDevice):
    """The same bus behind a serial-to-Ethernet gateway: raw TCP on 127.0.0.1 (an ephemeral port), the
    bytes passed through as they are. ``stop()`` closes it (and every connection), ``start()`` serves again
    on the same port."""

    def __init__(self, modules: Sequence[DconModule], port: int = 0) -> None:
        super().__init__(modules)
        self._tcp = LoopbackServer(self._serve_connection, port, name="dcon-gateway")
        self.start()

    def _serve_connection(self, sock: socket.socket) -> None:
        buffer = b""
        while data := sock.recv(4096):
            buffer += data
            while b"\r" in buffer:
                raw, _, buffer = buffer.partition(b"\r")
                answer = self.respond(raw)
                if answer is not None:
                    sock.sendall(answer)
            buffer = buffer[-4096:]
