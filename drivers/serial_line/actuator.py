"""An ASCII controller on a serial line as the stage's actuator (PI GCS: ``SVA 1 4.9990``).

Each command writes the configured template; an optional readback query and an optional error
query follow, and their answers are checked: silence, an answer that does not carry a value, a value
outside the tolerance, or the controller reporting an error is a :class:`DeviceError` naming the
port, what was written and what came back. The port is the sensor group's when a sensor reads the
same controller (one lock per port: each request gets its own answer), else the actuator's own.
The readback query also tells where the output is before the first command (:meth:`read_back`).

What is written is what is checked: the template is rendered field by field and the numbers the
string carries are parsed back (``template.py``). A ``voltage_v`` that the template's rounding would
put outside ``limits_v`` is written as the nearest value inside them at the template's precision
(``{voltage_v:.1f}`` with ``v_max = 9.17`` writes ``9.1``, never ``9.2``), and a ``q_um`` or ``x_um``
likewise within ``limits_q_um``; ``ValueError`` when the template can write no value inside, or an
``x_um`` lies outside the command range. The readback is compared with the number actually sent.
"""

from __future__ import annotations

import math
import re
from typing import Literal

from nanodrift.drivers.base import Actuator, DeviceError, shown
from nanodrift.drivers.serial_line.config import SerialLineActuatorConfig
from nanodrift.drivers.serial_line.line import SerialLineGroup
from nanodrift.drivers.serial_line.template import CommandTemplate

SHOWN_CHARS = 60  # of an unexpected answer in a message


class SerialLineActuator(Actuator):
    def __init__(self, config: SerialLineActuatorConfig, port: SerialLineGroup, *, owns_port: bool) -> None:
        self.config = config
        self.port = port
        self.owns_port = owns_port
        self.description = f"controller on {config.port}"
        self.template = CommandTemplate(config.command)
        self._readback = re.compile(config.readback_pattern)
        self._error_ok = re.compile(config.error_ok)

    def __repr__(self) -> str:
        shared = "" if self.owns_port else ", port shared with a sensor"
        return f"SerialLineActuator({self.config.port!r}{shared})"

    async def open(self) -> None:
        await self.port.open()

    async def close(self) -> None:
        if self.owns_port:  # a shared port stays with its sensor
            await self.port.close()

    def render(self, q_um: float, voltage_v: float, x_um: float | None = None) -> tuple[str, dict[str, float]]:
        """What one command writes, and the number each field carries in it (``voltage_v`` kept within
        ``limits_v``; :class:`ValueError` when it cannot be)."""
        return self._render({"voltage_v": voltage_v, "q_um": q_um, "x_um": q_um if x_um is None else x_um},
                            self.limits_q_um)

    def _render(self, values: dict[str, float], q_limits: tuple[float, float] | None) -> tuple[str, dict[str, float]]:
        try:
            return self.template.render(values, self.limits_v, q_limits)
        except ValueError as error:
            raise ValueError(f"{self.description}: command {self.config.command!r}: {error}") from None

    def check_command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        """:class:`ValueError` when the template cannot carry these values within their limits."""
        self.render(q_um, voltage_v, x_um)

    def sent_voltage(self, voltage_v: float) -> float:
        """The voltage the controller reads in the line for ``voltage_v`` (a closed-loop template, which
        writes ``q_um``, carries no voltage: then ``voltage_v`` itself)."""
        _, sent = self._render({"voltage_v": voltage_v, "q_um": 0.0, "x_um": 0.0}, None)  # only voltage_v asked about
        return sent.get("voltage_v", voltage_v)

    async def _ask(self, query: str, after: str) -> str:
        answer = await self.port.exchange(query.encode("latin-1"), answer=True, timeout_s=self.config.timeout_s)
        if answer is None:
            raise DeviceError(f"{self.description}: no answer to {query!r} within {self.config.timeout_s:g} s "
                              f"after {after!r}")
        return answer

    async def _read(self, after: str) -> tuple[float, str]:
        """The value the readback query's answer carries, and the answer (:class:`DeviceError` for silence
        or garble)."""
        c = self.config
        answer = await self._ask(c.readback, after)
        match = self._readback.search(answer)
        try:
            value = float(match.group("value")) if match else None
        except ValueError:
            value = None
        if value is None or not math.isfinite(value):  # never a value the answer does not carry
            self.port.distrust_answer()
            raise DeviceError(f"{self.description}: unexpected answer {shown(answer, SHOWN_CHARS)} to {c.readback!r} "
                              f"after {after!r} (expected pattern {c.readback_pattern!r})")
        return value, answer

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        """What the controller holds (the readback query's value) when it answers the voltage or the
        command; None without a readback, or when it answers the target ``x_um`` (not where the stage is)."""
        field = self.config.expected_field
        if not self.config.readback or field == "x_um":
            return None
        value, _ = await self._read("opening the port")
        limits = self.limits_v if field == "voltage_v" else self.limits_q_um
        if limits is not None and not limits[0] <= value <= limits[1]:
            self.port.distrust_answer()  # (the daemon does not believe it either: actuator_readback_untrusted)
        return ("voltage_v" if field == "voltage_v" else "q_um"), value

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        c = self.config
        text, sent = self.render(q_um, voltage_v, x_um)  # ValueError before anything is written
        await self.port.exchange(text.encode("latin-1"), answer=False, timeout_s=c.timeout_s)
        if c.readback:
            value, answer = await self._read(text)
            expected = sent[c.expected_field]  # what the device was told, not what was asked
            if not abs(value - expected) <= c.readback_tolerance:
                self.port.distrust_answer()
                raise DeviceError(f"{self.description}: wrote {text!r} ({c.expected_field} {expected:.6g}), read back "
                                  f"{value:.6g} (answer {shown(answer, SHOWN_CHARS)}; "
                                  f"tolerance {c.readback_tolerance:g})")
        if c.error_query:
            answer = await self._ask(c.error_query, text)
            if not self._error_ok.fullmatch(answer.strip()):
                raise DeviceError(f"{self.description}: the controller reports error {shown(answer, SHOWN_CHARS)} "
                                  f"after {text!r}")
