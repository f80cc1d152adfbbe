"""One axis of a PI piezo controller (E-727, E-753, E-709 ...) driven in GCS 2.0, as the stage's output.

What it does, and the document each behaviour comes from (PIPython 2.13.0.2, PI's Python library:
``pipython/pidevice/common/gcsbasecommands.py`` for the commands, ``gcsmessages.py`` for the framing,
``gcserror.py`` for the error table, ``interfaces/pisocket.py`` for TCP port 50000):

- **open**: ``ERR?`` first, to clear what an earlier user left in the error register ("Get current
  controller error", ``qERR``; logged, blamed on nothing); ``*IDN?`` (``qIDN``) the identity, logged;
  ``SVO?`` for every axis (a multi-line answer) to check the configured axis exists; ``TMN?``/``TMX?``
  (``qTMN``/``qTMX``: "the low/high end of the travel range"), and ``VMI?``/``VMA?`` (``qVMI``/``qVMA``:
  "PZT voltage soft limit" of the piezo channel) where the controller has them (an unknown command,
  error 2, means it has none). A config whose limits exceed them is refused, naming the axis and both
  ranges: open loop ``[v_min, v_max]`` against ``[VMI?, VMA?]``, closed loop ``[q_min_um, q_max_um]``
  against ``[TMN?, TMX?]``. ``DCO?`` (``qDCO``, drift compensation mode): a warning when it is on, since
  the controller's own drift compensation acts beside nanodrift's model. Then the servo is set to what
  ``mode`` needs and the change logged: ``SVO <axis> 0`` for open loop (``SVA``: "Servo must be switched
  off (open-loop operation) when using this command"), ``SVO <axis> 1`` for closed loop (``MOV`` with the
  servo off is error 5, "move attempted with servo off").
- **command**: one batch ``ERR?``, ``SVA <axis> <V>`` (or ``MOV <axis> <um>``), ``ERR?``, ``SVA? <axis>``
  (or ``MOV?`` and ``OVF?``: "Overflow means that the control variables are out of range"), written at
  once and answered in order (one round trip; PIPython appends ``ERR?`` to a command the same way). The
  first ``ERR?`` says what was pending *before* the command (reported as such: never blamed on it), the
  second what the command caused (``PI error N: <text>`` naming the command). The read-back must be the
  value sent: a controller that took the command but did not apply it is a fault, never "accepted".
- **numbers**: written with 6 decimals (1 uV, 1 pm); a value the rounding would put outside the limits is
  written as the nearest value inside them.
- **done**: :meth:`on_target` asks ``ONT?`` ("Check if 'axes' have reached the target") in closed loop; the
  daemon's ``done: reached`` waits for it (:meth:`nanodrift.drivers.base.Actuator.on_target`).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator
from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal
from typing import Literal

import structlog

from nanodrift.drivers.base import Actuator, DeviceError, shown
from nanodrift.drivers.pi_gcs.config import DECIMALS, PiGcsActuatorConfig
from nanodrift.drivers.pi_gcs.errors import UNKNOWN_COMMAND, error_text
from nanodrift.drivers.pi_gcs.link import GcsLink

log = structlog.get_logger(__name__)

QUANTUM = Decimal(1).scaleb(-DECIMALS)


class PiGcsLimitsError(DeviceError):
    """The config asks for more than the controller reports it can do: nothing is moved."""


class GarbledAnswer(DeviceError):
    """An answer that is not what was asked for (a stray line, a late answer): the exchange is out of step,
    so the connection is reset before anything else is asked on it."""


def rounded_inside(value: float, low: float | None, high: float | None, what: str) -> float:
    """``value`` at :data:`DECIMALS` decimals, moved inward to the nearest written value inside ``[low, high]``
    (``ValueError`` naming ``what`` when none is)."""
    written = Decimal(f"{value:.{DECIMALS}f}")
    if high is not None and written > Decimal(high):
        written = Decimal(high).quantize(QUANTUM, rounding=ROUND_FLOOR)
    if low is not None and written < Decimal(low):
        written = Decimal(low).quantize(QUANTUM, rounding=ROUND_CEILING)
    if (low is not None and written < Decimal(low)) or (high is not None and written > Decimal(high)):
        raise ValueError(f"{what}: no value with {DECIMALS} decimals lies within [{low!r}, {high!r}]")
    return float(written)


def _value(answer: str, axis: str, query: str) -> str:
    """The value of ``axis`` in a GCS ``item=value`` answer (one or several lines)."""
    for line in answer.split("\n"):
        item, sep, value = line.partition("=")
        if sep and item.strip() == axis:
            return value.strip()
    raise GarbledAnswer(f"no value for {axis!r} in the answer {shown(answer)} to {query!r}")


def _float(answer: str, axis: str, query: str) -> float:
    text = _value(answer, axis, query)
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not math.isfinite(value):
        raise GarbledAnswer(f"answer {shown(answer)} to {query!r} carries no number for {axis!r}")
    return value


class PiGcsActuator(Actuator):
    def __init__(self, config: PiGcsActuatorConfig, link: GcsLink) -> None:
        self.config = config
        self.link = link
        self.axis = config.axis
        loop = "SVA, open loop" if config.mode == "open_loop" else "MOV, closed loop"
        self.description = f"PI controller at {config.address}, axis {config.axis} ({loop})"
        self.identity = ""
        self.travel_um: tuple[float, float] | None = None
        self.voltage_range_v: tuple[float, float] | None = None
        self.q_range_um: tuple[float, float] | None = None
        self._leased = False
        self._prepared_for: int | None = None  # the link's connection the axis was prepared on

    def __repr__(self) -> str:
        return f"PiGcsActuator({self.description})"

    # -- talking ----------------------------------------------------------------------------------

    async def _ask(self, lines: list[str], answers: int | None) -> list[str]:
        try:
            return await self.link.ask(lines, answers)
        except DeviceError as error:
            raise DeviceError(f"{self.description}: {error}") from error

    def _code(self, answer: str) -> int:
        try:
            return int(answer.strip())
        except ValueError:
            raise GarbledAnswer(f"unexpected answer {shown(answer)} to 'ERR?'") from None

    def _check(self, answer: str, after: str) -> None:
        """The ``ERR?`` answer read right after ``after``: :class:`DeviceError` blaming it for any error."""
        code = self._code(answer)
        if code:
            raise DeviceError(f"{self.description}: {error_text(code)} (after {after!r})")

    async def _query(self, query: str) -> str:
        """``query`` and its ``ERR?``: the answer (:class:`DeviceError` naming the query on an error)."""
        if query == "*IDN?":  # the one answer that is not item=value
            answer, err = await self._ask([query, "ERR?"], 2)
            self._check(err, query)
            return answer
        found, code = await self._optional(query)
        if found is None:
            raise DeviceError(f"{self.description}: {error_text(code)} (after {query!r})")
        return found

    async def _optional(self, query: str) -> tuple[str | None, int]:
        """A query the controller may not know: (its answer, 0) or (None, the error code it set)."""
        *found, err = await self._ask([query, "ERR?"], None)
        if not found:  # no answer to the query: it set an error
            return None, self._code(err)
        self._check(err, query)
        return found[0], 0

    # -- open / close -----------------------------------------------------------------------------

    @contextlib.contextmanager
    def _in_step(self) -> Iterator[None]:
        """A garbled answer resets the connection (the next exchange reconnects and prepares the axis again):
        answers out of step are never taken for later requests' answers."""
        try:
            yield
        except GarbledAnswer as error:
            self.link.drop()
            raise DeviceError(f"{self.description}: {error}; the connection is reset") from error

    async def open(self) -> None:
        if not self._leased:
            self.link.users += 1
            self._leased = True
        try:
            with self._in_step():
                await self._prepare()
        except BaseException:
            await self.close()
            raise

    async def close(self) -> None:
        self._prepared_for = None
        if self._leased:
            self._leased = False
            self.link.users -= 1
            if self.link.users <= 0:
                self.link.drop()

    async def _prepare(self) -> None:
        """What :meth:`open` does on a fresh connection (see the module's docstring)."""
        c, axis = self.config, self.axis
        await self.link.connect()
        [pending] = await self._ask(["ERR?"], 1)
        if code := self._code(pending):
            log.warning("pi_gcs_error_cleared", device=self.description, error=error_text(code),
                        note="left in the controller's error register before this connection; blamed on nothing")
        self.identity = await self._query("*IDN?")
        servo_states = await self._query("SVO?")
        axes = [line.partition("=")[0].strip() for line in servo_states.split("\n") if "=" in line]
        if axis not in axes:
            raise PiGcsLimitsError(f"{self.description}: the controller has no axis {axis!r} (SVO? lists "
                                   f"{', '.join(axes) or 'none'}); set axis to one of them")
        servo_on = _value(servo_states, axis, "SVO?") == "1"
        tmn, tmx = await self._query(f"TMN? {axis}"), await self._query(f"TMX? {axis}")
        self.travel_um = (_float(tmn, axis, f"TMN? {axis}"), _float(tmx, axis, f"TMX? {axis}"))
        vmi, code = await self._optional(f"VMI? {c.channel}")
        vma, _ = await self._optional(f"VMA? {c.channel}") if vmi is not None else (None, code)
        if vmi is not None and vma is not None:
            channel = str(c.channel)
            self.voltage_range_v = (_float(vmi, channel, "VMI?"), _float(vma, channel, "VMA?"))
        elif code != UNKNOWN_COMMAND:
            raise DeviceError(f"{self.description}: {error_text(code)} (after 'VMI? {c.channel}')")
        self._check_limits()
        dco, code = await self._optional(f"DCO? {axis}")
        if dco is not None and _value(dco, axis, "DCO?") == "1":
            log.warning("pi_gcs_drift_compensation_on", device=self.description, identity=self.identity,
                        note="the controller's own drift compensation (DCO) acts beside nanodrift's model: "
                             "switch it off (DCO <axis> 0) unless the model was calibrated with it on")
        await self._set_servo(servo_on)
        self._prepared_for = self.link.generation
        log.info("pi_gcs_opened", device=self.description, identity=self.identity, travel_um=self.travel_um,
                 voltage_range_v=self.voltage_range_v, q_range_um=self.q_range_um, mode=c.mode)

    def _check_limits(self) -> None:
        """Refuse limits beyond what the controller reports, naming the axis and both ranges."""
        c = self.config
        assert self.travel_um is not None
        if c.mode == "closed_loop":
            low = self.travel_um[0] if c.q_min_um is None else c.q_min_um
            high = self.travel_um[1] if c.q_max_um is None else c.q_max_um
            if low < self.travel_um[0] or high > self.travel_um[1]:
                raise PiGcsLimitsError(
                    f"{self.description}: [q_min_um, q_max_um] = [{low:g}, {high:g}] um exceeds the travel range "
                    f"the controller reports for axis {self.axis}, [{self.travel_um[0]:g}, {self.travel_um[1]:g}] "
                    "um (TMN?/TMX?): narrow q_min_um/q_max_um to lie within it")
            self.q_range_um = (low, high)
        elif self.voltage_range_v is not None and self.limits_v is not None:
            (low, high), (vmi, vma) = self.limits_v, self.voltage_range_v
            if low < vmi or high > vma:
                raise PiGcsLimitsError(
                    f"{self.description}: [v_min, v_max] = [{low:g}, {high:g}] V exceeds the voltage range the "
                    f"controller reports for axis {self.axis} (piezo channel {c.channel}), [{vmi:g}, {vma:g}] V "
                    "(VMI?/VMA?): narrow v_min/v_max to lie within it")

    async def _set_servo(self, servo_on: bool) -> None:
        want = self.config.mode == "closed_loop"
        if servo_on != want:
            command = f"SVO {self.axis} {int(want)}"
            [err] = await self._ask([command, "ERR?"], 1)
            self._check(err, command)
            log.info("pi_gcs_servo_switched", device=self.description, servo="on" if want else "off",
                     reason="closed loop: MOV needs the servo on" if want else
                     "open loop: SVA is refused while the servo is on (GCS error 79)")
        state = await self._query(f"SVO? {self.axis}")
        if (_value(state, self.axis, "SVO?") == "1") != want:
            raise DeviceError(f"{self.description}: the servo stays {'off' if want else 'on'} after SVO")

    async def _ready(self) -> None:
        """Prepared on the connection the next exchange uses (a lost connection is prepared again)."""
        if not self._leased:
            raise DeviceError(f"{self.description}: not open")
        if not self.link.connected or self._prepared_for != self.link.generation:
            await self._prepare()

    # -- commands ---------------------------------------------------------------------------------

    def sent_voltage(self, voltage_v: float) -> float:
        """Open loop: the voltage ``SVA`` writes (6 decimals, inside ``limits_v``); closed loop the controller
        is given a position, so ``voltage_v`` itself."""
        if self.config.mode == "closed_loop":
            return voltage_v
        low, high = self.limits_v if self.limits_v is not None else (None, None)
        return rounded_inside(voltage_v, low, high, f"{self.description}: voltage {voltage_v!r} V")

    def sent_q(self, q_um: float) -> float:
        """Closed loop: the position ``MOV`` writes (6 decimals), inside ``[q_min_um, q_max_um]`` (read at open).

        ``ValueError`` for a position farther outside than the rounding: nothing is written."""
        low, high = self.q_range_um if self.q_range_um is not None else (None, None)
        if (low is not None and q_um < low - 1e-9) or (high is not None and q_um > high + 1e-9):
            raise ValueError(f"{self.description}: q_um = {q_um!r} is outside [q_min_um, q_max_um] = "
                             f"[{low!r}, {high!r}] um")
        return rounded_inside(q_um, low, high, f"{self.description}: position {q_um!r} um")

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        with self._in_step():
            await self._command(q_um, voltage_v)

    async def _command(self, q_um: float, voltage_v: float) -> None:
        axis = self.axis
        if self.config.mode == "open_loop":
            value = self.sent_voltage(voltage_v)  # ValueError before anything is written
            command = f"SVA {axis} {value:.{DECIMALS}f}"
            checks = [f"SVA? {axis}"]
        else:
            await self._ready()  # the travel range bounds the position
            value = self.sent_q(q_um)
            command = f"MOV {axis} {value:.{DECIMALS}f}"
            checks = [f"MOV? {axis}", f"OVF? {axis}"]
        await self._ready()
        before, after, *answers = await self._ask(["ERR?", command, "ERR?", *checks], 2 + len(checks))
        if code := self._code(before):
            raise DeviceError(f"{self.description}: {error_text(code)} was pending before {command!r} (raised "
                              "earlier, by something else: not by this command); nothing is trusted until the "
                              "next command finds the register clear")
        self._check(after, command)
        back = _float(answers[0], axis, checks[0])
        if abs(back - value) > 0.5 * float(QUANTUM):
            raise DeviceError(f"{self.description}: wrote {command!r}, {checks[0]!r} reads back {back!r}: the "
                              "controller did not apply it")
        if len(answers) > 1 and _value(answers[1], axis, checks[1]) != "0":
            raise DeviceError(f"{self.description}: overflow after {command!r} (OVF? {axis} = 1): the servo cannot "
                              "hold the position (control variables out of range)")

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        """Open loop ``SVA?`` (the voltage set), closed loop ``MOV?`` (the target position)."""
        query = f"SVA? {self.axis}" if self.config.mode == "open_loop" else f"MOV? {self.axis}"
        with self._in_step():
            await self._ready()
            value = _float(await self._query(query), self.axis, query)
        return ("voltage_v", value) if self.config.mode == "open_loop" else ("q_um", value)

    async def on_target(self) -> bool:
        """Closed loop: whether the axis has reached its target (``ONT?``); open loop has no target: True."""
        if self.config.mode == "open_loop":
            return True
        with self._in_step():
            await self._ready()
            return _value(await self._query(f"ONT? {self.axis}"), self.axis, "ONT?") == "1"
