"""A PI piezo controller speaking GCS 2.0 (E-727, E-753, E-709 ...), served over TCP and on a pty, for
testing the ``pi_gcs`` plugin and a lab's own GCS code against the behaviour that matters to a drift
compensator.

Where each behaviour comes from (PIPython 2.13.0.2, PI's own Python library):

- ``pipython/pidevice/common/gcsbasecommands.py`` (the command reference as PIPython documents it):
  ``SVA`` "Servo must be switched off (open-loop operation) when using this command"; ``SVO``/``SVO?``
  servo on/off; ``MOV``/``MOV?``; ``POS?``; ``ONT?`` "Check if 'axes' have reached the target";
  ``OVF?`` "Overflow means that the control variables are out of range (can only happen if controller
  is in closed-loop mode)"; ``VOL?`` piezo voltage per channel; ``TMN?``/``TMX?`` the travel range;
  ``VMI?``/``VMA?`` the PZT voltage soft limits per piezo channel; ``DCO?`` drift compensation mode;
  ``ERR?`` "Get current controller error" (``qERR``; PIPython's ``gcsmessages.py`` asks it after every
  command and takes 0 for no error: the emulator keeps the last error and resets it once read);
  ``STP`` "Stop all axes abruptly ... May raise GCSError(E10_PI_CNTR_STOP)"; answers ``item=value``, one line per item;
- ``pipython/pidevice/gcsmessages.py`` (``checksize``): an answer is complete at a LF *not* preceded by
  a space; every line of a multi-line answer but the last ends with ``" \\n"``;
- ``pipython/pidevice/gcserror.py`` (the error table): 1 parameter syntax error, 2 unknown command,
  5 "move attempted with servo off", 7 position out of limits, 10 controller was stopped by command,
  15 invalid axis identifier, 79 "Open-loop commands are not allowed when servo is on", 302 voltage out
  of limits (the table also has 66 with the same text; the emulator uses 302);
- ``pipython/pidevice/interfaces/pisocket.py``: TCP port 50000.

What the emulator does not model: motion dynamics (a MOV reaches its target after ``settle_s``, an
SVA at once), wave generators, data recorder, macros. Every line received is kept in ``lines``
(``(connection id, line)``), the device's own log, so a test asserts what the controller was told.
"""

from __future__ import annotations

import asyncio
import itertools
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path

from nanodrift.drivers.pi_gcs.errors import GCS_ERRORS, error_text
from nanodrift.drivers.testing.loopback import LoopbackServer
from nanodrift.drivers.testing.pty_devices import PtyDevice

__all__ = ["GCS_ERRORS", "EmulatedAxis", "PiGcsEmulator", "PiGcsPtyDevice", "PiGcsTcpServer", "error_text"]

PARAM_SYNTAX, UNKNOWN_COMMAND, MOVE_WITH_SERVO_OFF, POS_OUT_OF_LIMITS = 1, 2, 5, 7
STOPPED, INVALID_AXIS, OPEN_LOOP_WITH_SERVO_ON, VOLTAGE_OUT_OF_LIMITS = 10, 15, 79, 302

IDN = "(c)2021 Physik Instrumente (PI) GmbH & Co. KG, E-727, 0121000001, 13.21.00.09"


@dataclass
class EmulatedAxis:
    """One axis of the controller and the piezo channel that drives it."""

    travel_um: tuple[float, float] = (0.0, 500.0)  # TMN?, TMX?
    voltage_v: tuple[float, float] = (-30.0, 130.0)  # VMI?, VMA? of its piezo channel
    servo: bool = False
    drift_compensation: bool = False  # DCO
    sva_v: float = 0.0  # the open-loop value (SVA?)
    target_um: float = 0.0  # MOV?
    moved_at: float = 0.0  # time.monotonic() of the last MOV
    overflow: bool = False


@dataclass
class PiGcsEmulator:
    """The controller's state and its answers to GCS lines; thread-safe (a pty thread and the TCP server's
    connection threads may all talk to it).

    Knobs for tests: ``axes`` (identifier -> :class:`EmulatedAxis`), ``settle_s`` (a MOV is on target
    this long after it), ``fail_next`` (command word -> error code: the next such command is refused
    with it, changing nothing), ``has_voltage_limits`` (False: ``VMI?``/``VMA?`` are unknown commands,
    as on a controller without them), ``silent`` (answers nothing), ``frozen`` (SVA and MOV are accepted
    without an error and change nothing: an amplifier off, a stage unplugged), ``on_sva``/``on_mov`` (below),
    ``stray`` (a line sent once, unasked, before the next answer), ``um_per_volt`` (open-loop position per
    volt, for ``POS?``).
    """

    axes: dict[str, EmulatedAxis] = field(default_factory=lambda: {"1": EmulatedAxis()})
    idn: str = IDN
    settle_s: float = 0.0
    um_per_volt: float = 4.0
    has_voltage_limits: bool = True
    silent: bool = False
    frozen: bool = False
    stray: str | None = None
    error: int = 0
    fail_next: dict[str, int] = field(default_factory=dict)
    #: every line received, in order: (connection id, line)
    lines: list[tuple[str, str]] = field(default_factory=list)
    #: when each line of ``lines`` arrived (time.monotonic())
    line_times: list[float] = field(default_factory=list)
    #: every SVA / MOV value that took effect: (axis, value)
    applied_sva: list[tuple[str, float]] = field(default_factory=list)
    applied_mov: list[tuple[str, float]] = field(default_factory=list)
    #: told (axis, value) each time an SVA takes effect (on the serving thread): what an amplifier does with it
    on_sva: Callable[[str, float], None] | None = None
    #: told (axis, value) each time a MOV takes effect: where a simulated closed-loop stage is commanded to
    on_mov: Callable[[str, float], None] | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock, repr=False)

    # -- the device's side, for tests ---------------------------------------------------------------

    def received(self, word: str | None = None) -> list[str]:
        """Every line received (all connections), or only those whose command word is ``word``."""
        with self._lock:
            return [line for _, line in self.lines if word is None or line.split()[:1] == [word]]

    def stamped(self, word: str) -> list[tuple[float, str]]:
        """(arrival time, line) of every line whose command word is ``word``."""
        with self._lock:
            return [(t, line) for t, (_, line) in zip(self.line_times, self.lines, strict=True)
                    if line.split()[:1] == [word]]

    def raise_error(self, code: int) -> None:
        """The controller's error register becomes ``code`` now, as if something else caused it."""
        with self._lock:
            self.error = code

    def set_servo(self, axis: str, on: bool) -> None:
        """The servo switched from outside (front panel, PIMikroMove on another connection)."""
        with self._lock:
            self.axes[axis].servo = on

    # -- GCS ----------------------------------------------------------------------------------------

    def handle(self, line: str, connection: str = "") -> str | None:
        """The answer to one received line (None: the command answers nothing), without the final LF."""
        with self._lock:
            self.lines.append((connection, line))
            self.line_times.append(time.monotonic())
            if self.silent:
                return None
            words = line.split()
            if not words:
                return None
            word, args = words[0], words[1:]
            forced = self.fail_next.pop(word, None)
            if forced is not None:
                self.error = forced
                return None
            try:
                answer = self._answer(word, args)
            except _GcsFault as fault:
                self.error = fault.code
                return None
            if answer is not None and self.stray is not None:  # a line nobody asked for, before this answer
                answer, self.stray = f"{self.stray}\n{answer}", None
            return answer

    def _answer(self, word: str, args: list[str]) -> str | None:
        setters: dict[str, Callable[..., None]] = {"SVO": self._svo, "SVA": self._sva, "MOV": self._mov,
                   "DCO": partial(self._switch, flag="drift_compensation")}
        if word == "*IDN?":
            return self.idn
        if word == "ERR?":
            code, self.error = self.error, 0
            return str(code)
        if word == "STP" or word == "HLT":
            for axis in self.axes.values():
                axis.target_um = self._position_um(axis)
            self.error = STOPPED  # as PIPython's STP/HLT docstrings say: error 10 is set
            return None
        if word in setters:
            pairs = self._pairs(args)
            for name, value in pairs:  # all checked before any is applied, as one command
                setters[word](self.axes[name], value, check_only=True)
            moves = {"SVA": (self.applied_sva, self.on_sva), "MOV": (self.applied_mov, self.on_mov)}.get(word)
            if self.frozen and moves is not None:
                return None  # accepted without an error, and nothing moves
            for name, value in pairs:
                setters[word](self.axes[name], value, check_only=False)
                if moves is not None:
                    applied, told = moves
                    applied.append((name, value))
                    if told is not None:
                        told(name, value)
            return None
        queries = {
            "SVO?": lambda a: str(int(a.servo)),
            "SVA?": lambda a: f"{a.sva_v:.6f}",
            "MOV?": lambda a: f"{a.target_um:.6f}",
            "POS?": lambda a: f"{self._position_um(a):.6f}",
            "ONT?": lambda a: str(int(a.servo and time.monotonic() - a.moved_at >= self.settle_s)),
            "OVF?": lambda a: str(int(a.overflow)),
            "TMN?": lambda a: f"{a.travel_um[0]:.6f}",
            "TMX?": lambda a: f"{a.travel_um[1]:.6f}",
            "DCO?": lambda a: str(int(a.drift_compensation)),
        }
        if word in queries:
            return self._per_item(args, list(self.axes), lambda name: queries[word](self.axes[name]))
        channels = {str(i + 1): axis for i, axis in enumerate(self.axes.values())}  # piezo channel n: axis n
        channel_queries = {
            "VOL?": lambda a: f"{self._piezo_voltage(a):.6f}",
            "VMI?": lambda a: f"{a.voltage_v[0]:.6f}",
            "VMA?": lambda a: f"{a.voltage_v[1]:.6f}",
        }
        if word in channel_queries and (word == "VOL?" or self.has_voltage_limits):
            return self._per_item(args, list(channels), lambda name: channel_queries[word](channels[name]))
        raise _GcsFault(UNKNOWN_COMMAND)

    def _pairs(self, args: list[str]) -> list[tuple[str, float]]:
        if not args or len(args) % 2:
            raise _GcsFault(PARAM_SYNTAX)
        pairs = []
        for name, text in zip(args[::2], args[1::2], strict=True):
            if name not in self.axes:
                raise _GcsFault(INVALID_AXIS)
            try:
                pairs.append((name, float(text)))
            except ValueError:
                raise _GcsFault(PARAM_SYNTAX) from None
        return pairs

    @staticmethod
    def _per_item(args: list[str], known: list[str], value: object) -> str:
        """``item=value`` per item asked (all when none): a multi-line answer, ``" \\n"`` between lines."""
        items = args or known
        if any(item not in known for item in items):
            raise _GcsFault(INVALID_AXIS)
        return " \n".join(f"{item}={value(item)}" for item in items)  # type: ignore[operator]

    def _svo(self, axis: EmulatedAxis, value: float, *, check_only: bool) -> None:
        if not check_only and value == 1.0 and not axis.servo:
            axis.target_um = self._position_um(axis)  # the loop closes where the stage is
        self._switch(axis, "servo", value, check_only=check_only)

    def _sva(self, axis: EmulatedAxis, value: float, *, check_only: bool) -> None:
        if axis.servo:
            raise _GcsFault(OPEN_LOOP_WITH_SERVO_ON)
        if not axis.voltage_v[0] <= value <= axis.voltage_v[1]:
            raise _GcsFault(VOLTAGE_OUT_OF_LIMITS)
        if not check_only:
            axis.sva_v = value

    def _mov(self, axis: EmulatedAxis, value: float, *, check_only: bool) -> None:
        if not axis.servo:
            raise _GcsFault(MOVE_WITH_SERVO_OFF)
        if not axis.travel_um[0] <= value <= axis.travel_um[1]:
            raise _GcsFault(POS_OUT_OF_LIMITS)
        if not check_only:
            axis.target_um = value
            axis.moved_at = time.monotonic()

    @staticmethod
    def _switch(axis: EmulatedAxis, flag: str, value: float, *, check_only: bool) -> None:
        """An on/off setting (``SVO``, ``DCO``): 0 or 1, anything else a syntax error."""
        if value not in (0.0, 1.0):
            raise _GcsFault(PARAM_SYNTAX)
        if not check_only:
            setattr(axis, flag, bool(value))

    def _position_um(self, axis: EmulatedAxis) -> float:
        return axis.target_um if axis.servo else axis.sva_v * self.um_per_volt

    def _piezo_voltage(self, axis: EmulatedAxis) -> float:
        if not axis.servo:
            return axis.sva_v
        low, high = axis.travel_um
        return axis.voltage_v[0] + (axis.target_um - low) / (high - low) * (axis.voltage_v[1] - axis.voltage_v[0])

    def sva(self, axis: str = "1") -> float:
        with self._lock:
            return self.axes[axis].sva_v

    def target_um(self, axis: str = "1") -> float:
        with self._lock:
            return self.axes[axis].target_um


class _GcsFault(Exception):
    def __init__(self, code: int) -> None:
        super().__init__(code)
        self.code = code


# --- TCP -----------------------------------------------------------------------------------------------


class PiGcsTcpServer:
    """The emulator on TCP, 127.0.0.1 (port 0: a free one), a thread per connection (a :class:`LoopbackServer`,
    as the other network emulators).

    ``stop`` closes the listener and every connection (the controller unplugged); ``start`` again
    serves on the same port. ``connections`` are the ids of the connections open now.
    """

    def __init__(self, emulator: PiGcsEmulator, port: int = 0) -> None:
        self.emulator = emulator
        self.connections: set[str] = set()
        self.serving = False
        self._ids = itertools.count(1)
        self._tcp = LoopbackServer(self._serve, port, name="pi-gcs-emulator")

    @property
    def port(self) -> int:
        return self._tcp.port

    async def start(self) -> None:
        self._tcp.start()
        self.serving = True

    async def stop(self) -> None:
        if self.serving:
            self.serving = False
            await asyncio.to_thread(self._tcp.stop)

    def _serve(self, sock: socket.socket) -> None:
        sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)  # each answer sent at once, as asyncio's are
        connection = f"tcp{next(self._ids)}"
        self.connections.add(connection)
        try:
            with sock.makefile("rb") as lines:
                while raw := lines.readline():
                    answer = self.emulator.handle(raw.decode("latin-1").rstrip("\r\n"), connection)
                    if answer is not None:
                        sock.sendall(answer.encode("latin-1") + b"\n")
        finally:
            self.connections.discard(connection)


# --- pty -----------------------------------------------------------------------------------------------


class PiGcsPtyDevice(PtyDevice):
    """The emulator on a pty behind ``link``, a :class:`PtyDevice` (``unplug``, ``replug``)."""

    def __init__(self, link: Path, emulator: PiGcsEmulator) -> None:
        self.emulator = emulator
        super().__init__(link)

    def _serve(self, master: int, stop: threading.Event) -> None:
        def answer(raw: bytes) -> bytes | None:
            text = self.emulator.handle(raw.decode("latin-1").rstrip("\r"), "pty")
            return None if text is None else text.encode("latin-1") + b"\n"

        self._serve_lines(master, stop, b"\n", answer)
