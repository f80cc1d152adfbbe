"""The ``[[sensors]]`` keys of a line-oriented serial instrument."""

from __future__ import annotations

import math
import re
import string
from typing import Annotated, Literal

from pydantic import AfterValidator, Field, FiniteFloat, field_validator, model_validator

from nanodrift.drivers.base import ActuatorOptions, OutputClaim, SensorConfig
from nanodrift.drivers.serial_line.template import POSITION_FIELDS, CommandTemplate

#: a line that is just a number: "12345.6", "-0.25", "+1.5e3" (anchored: patterns are searched)
DEFAULT_PATTERN = r"^\s*(?P<value>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*$"

#: pyserial's stop bits: 1, 1.5 or 2 (a float in a Literal is not a valid type, so a checked float)
StopBits = Annotated[float, AfterValidator(lambda bits: _one_of(bits, (1, 1.5, 2)))]


def _one_of(value: float, allowed: tuple[float, ...]) -> float:
    if value not in allowed:
        raise ValueError(f"Input should be {', '.join(f'{a:g}' for a in allowed[:-1])} or {allowed[-1]:g}")
    return value


def any_pattern(pattern: str) -> str:
    """``pattern`` if it compiles; else why not."""
    try:
        re.compile(pattern)
    except re.error as error:
        raise ValueError(f"not a valid regular expression: {error}") from None
    return pattern


#: a key that is a regular expression (refused, saying why, when it does not compile)
Regex = Annotated[str, AfterValidator(any_pattern)]


def value_pattern(pattern: str, example: str) -> str:
    """``pattern`` if it compiles and has the named group ``value`` the driver reads; else why not."""
    if "value" not in re.compile(any_pattern(pattern)).groupindex:
        raise ValueError(f"needs a named group 'value', e.g. {example}")
    return pattern


RESYNC_QUERY_HELP = ("sent before the next request once a request on this port went unanswered (e.g. GCS "
                     "'*IDN?\\n'); every line up to its answer is discarded; empty: none (the line waits to go "
                     "quiet instead)")
RESYNC_PATTERN_HELP = ("regex searched in the resync query's answer (e.g. 'PI|Physik'); it must match no "
                       "answer to any other request on the port")


def check_resync(query: str, pattern: str) -> None:
    """A ``ValueError`` when a resync query and pattern do not go together (both or neither)."""
    if bool(query) != bool(pattern):
        missing = "resync_pattern" if query else "resync_query"
        raise ValueError(f"{missing}: resync_query and resync_pattern go together: the query is sent, and its "
                         "answer is the first line the pattern is found in (e.g. resync_query = \"*IDN?\\n\", "
                         "resync_pattern = 'PI|Physik')")


class SerialLineSensorConfig(SensorConfig):
    """One value per line of text from a serial port (queried, or streamed by the device).

    ``pattern`` is *searched* in each line (``re.search``), the way grep finds a pattern: with
    ``'P (?P<value>[-+0-9.]+) nm'`` the device's ``P +123456.7 nm OK`` reads 123456.7. Anchor it
    with ``^...$`` to demand that the whole line matches (then ``... OK`` is a fault).
    """

    kind: Literal["serial_line"] = "serial_line"
    port: str = Field(description="anything pyserial's serial_for_url accepts: /dev/ttyUSB0, socket://host:port")
    baudrate: int = Field(default=9600, gt=0)
    bytesize: Literal[5, 6, 7, 8] = 8
    parity: Literal["N", "E", "O", "M", "S"] = "N"
    stopbits: StopBits = 1
    query: str = Field(default="", description="sent each interval_s, exactly as written; empty: the device "
                                               "streams lines by itself")
    pattern: str = Field(default=DEFAULT_PATTERN, description="regex searched in each line (re.search), with a "
                                                              "named group 'value'; ^...$ demands the whole line")
    scale: FiniteFloat = Field(default=1.0, description="raw -> unit (e.g. nm -> um: 0.001)")
    offset: FiniteFloat = 0.0
    eol: Literal["\r\n", "\n", "\r"] = Field(
        default="\n", description="line terminator; '\\n' and '\\r\\n' behave the same (a trailing '\\r' is "
                                  "dropped); '\\r' for devices that end lines with CR only")
    unit: str | None = Field(default=None, description="unit of the scaled value; default um / degC by role")
    resync_query: str = Field(default="", description=RESYNC_QUERY_HELP)
    resync_pattern: Regex = Field(default="", description=RESYNC_PATTERN_HELP)

    @field_validator("scale")
    @classmethod
    def _scale_not_zero(cls, value: float) -> float:
        if value == 0:
            raise ValueError("must not be 0: every reading would be the offset, whatever the device sends")
        return value

    @field_validator("pattern")
    @classmethod
    def _pattern_has_value_group(cls, pattern: str) -> str:
        return value_pattern(pattern, "'P (?P<value>[-+0-9.]+) nm'")

    @model_validator(mode="after")
    def _resync(self) -> SerialLineSensorConfig:
        check_resync(self.resync_query, self.resync_pattern)
        if self.resync_query and self.streaming:
            raise ValueError("resync_query: a sensor that streams (query = \"\") asks nothing, so nothing on its "
                             "line can go unanswered; give it a query, or drop resync_query and resync_pattern")
        return self

    @property
    def resync(self) -> tuple[str, str] | None:
        """(query, pattern) of the resynchronisation query, or None."""
        return (self.resync_query, self.resync_pattern) if self.resync_query else None

    @property
    def value_unit(self) -> str:
        if self.unit is not None:
            return self.unit
        return "um" if self.role == "position" else "degC"

    @property
    def streaming(self) -> bool:
        return self.query == ""


#: a command template coarser than this much stage travel is warned about (check-config): the daemon
#: compensates drift of tens of nanometres, so a step of the written number worth more than 10 nm is
#: visible in the position (a fixed number of millivolts would mean 10 nm or 100 nm by the gain)
RESOLUTION_UM = 0.01

ReadbackField = Literal["voltage_v", "q_um", "x_um"]


def template_fields(template: str) -> list[str]:
    """The field names a ``str.format`` template uses, in order (``ValueError`` for a malformed one)."""
    return [name for _, name, _, _ in string.Formatter().parse(template) if name is not None]


def _decimals_for(step: float) -> str:
    """The ``.Nf`` precision whose step is at most ``step`` (e.g. ``.4`` for 2e-4)."""
    return f".{max(0, math.ceil(-math.log10(step) - 1e-9)) if step > 0 else 6}"


class SerialLineActuatorConfig(ActuatorOptions):
    """``[actuator] kind = "serial_line"``: an ASCII controller, e.g. PI GCS (``SVA`` open-loop voltage,
    ``MOV`` closed-loop position).

    Each command writes ``command`` formatted with ``voltage_v``, ``q_um`` and ``x_um`` (the target;
    ``q_um`` when the caller has none). ``readback`` (optional) is sent next; the value its answer
    carries (``readback_pattern``, searched in the line, named group ``value``) must be within
    ``readback_tolerance`` of the field the command wrote (``readback_field``; by default the one
    field the template names). ``error_query`` (optional, GCS: ``"ERR?\\n"``) is sent last; an
    answer not matching ``error_ok`` is the controller reporting an error. Silence, a garbled
    answer or a mismatch is an actuator fault.
    """

    kind: Literal["serial_line"] = "serial_line"
    port: str = Field(description="anything pyserial's serial_for_url accepts: /dev/ttyUSB1, socket://host:port")
    baudrate: int = Field(default=115200, gt=0)
    bytesize: Literal[5, 6, 7, 8] = 8
    parity: Literal["N", "E", "O", "M", "S"] = "N"
    stopbits: StopBits = 1
    command: str = Field(default="SVA 1 {voltage_v:.4f}\n", description="written for each command (str.format)")
    readback: str = Field(default="", description="query sent after each command; empty: none")
    readback_pattern: str = Field(default=r"=(?P<value>[-+0-9.eE]+)", description="searched in the answer")
    readback_tolerance: FiniteFloat = Field(default=0.001, ge=0, description="in the readback field's unit")
    readback_field: ReadbackField | None = Field(default=None, description="default: the template's one field")
    error_query: str = Field(default="", description="sent last, e.g. GCS 'ERR?\\n'; empty: none")
    error_ok: Regex = Field(default="0", description="regex the whole answer to error_query matches when all is well")
    eol: Literal["\r\n", "\n", "\r"] = Field(default="\n", description="how the controller ends its answers")
    timeout_s: float = Field(default=1.0, gt=0, description="an answer must come within this")
    resync_query: str = Field(default="", description=RESYNC_QUERY_HELP)
    resync_pattern: Regex = Field(default="", description=RESYNC_PATTERN_HELP)

    @field_validator("command")
    @classmethod
    def _template(cls, template: str) -> str:
        CommandTemplate(template)  # ValueError naming the field it cannot take (it formats each one, probing)
        return template

    @field_validator("readback_pattern")
    @classmethod
    def _readback_has_value_group(cls, pattern: str) -> str:
        return value_pattern(pattern, "'=(?P<value>[-+0-9.eE]+)'")

    @model_validator(mode="after")
    def _readback_field(self) -> SerialLineActuatorConfig:
        check_resync(self.resync_query, self.resync_pattern)
        if self.readback and self.readback_field is None:
            names = set(template_fields(self.command))
            if len(names) != 1:
                raise ValueError(f"readback_field: the command names {', '.join(sorted(names))}; say which one the "
                                 "readback answers (voltage_v, q_um or x_um)")
        return self

    @property
    def resync(self) -> tuple[str, str] | None:
        """(query, pattern) of the resynchronisation query, or None."""
        return (self.resync_query, self.resync_pattern) if self.resync_query else None

    @property
    def asks(self) -> bool:
        """The actuator asks the controller questions (a readback or an error query)."""
        return bool(self.readback or self.error_query)

    @property
    def expected_field(self) -> str:
        """The field whose value the readback must match."""
        return self.readback_field or template_fields(self.command)[0]

    @property
    def template(self) -> CommandTemplate:
        return CommandTemplate(self.command)

    def claims(self) -> list[OutputClaim]:
        """The output the command writes, told by its text without the numbers (``SVA 1 {}``): two axes on
        one port writing the same command write one controller axis. (Commands that name one axis in two
        ways, ``SVA 1`` and ``MOV 1``, cannot be told apart by their text: the operator's to keep apart.)"""
        skeleton = " ".join("".join(literal + ("{}" if field is not None else "")
                                    for literal, field in self.template.pieces).split())
        return [OutputClaim(f"the controller on port {self.port!r}", frozenset({f"command {skeleton!r}"}))]

    def voltage_range_problem(self, v_min: float, v_max: float, volts_per_um: float) -> str | None:
        """A ``voltage_v`` field that cannot write two different voltages within the limits (``.0f``
        with [-0.5, 0.4] writes 0 for all of them: the stage could not move), or none at all."""
        for field in self.template.fields:
            if field.name != "voltage_v":
                continue
            where = (f"command: {field.text} cannot write the voltages within [v_min, v_max] = "
                     f"[{v_min:g}, {v_max:g}] V")
            try:
                low, high = field.inside(v_min, v_min, v_max), field.inside(v_max, v_min, v_max)
            except ValueError:
                return (f"{where}: no value it writes lies within them ({v_min:g} is written "
                        f"{field.format(v_min).strip()!r}, {v_max:g} {field.format(v_max).strip()!r}); "
                        f"give it more decimals, e.g. {{voltage_v:{_decimals_for(v_max - v_min)}f}}")
            if low[1] == high[1]:
                return (f"{where}: it writes every one of them as {low[0].strip()!r}, so the stage could not move; "
                        f"give it more decimals, e.g. {{voltage_v:{_decimals_for(v_max - v_min)}f}}")
        return None

    def config_warnings(self, v_min: float, v_max: float, volts_per_um: float, offset_v: float) -> list[str]:
        """A field whose step is coarser than :data:`RESOLUTION_UM` of stage travel: every command is
        rounded to it on the way to the stage (``{voltage_v:.2f}`` at 0.02 V/um: 500 nm steps)."""
        warnings: list[str] = []
        q_ends = [(v - offset_v) / volts_per_um for v in (v_min, v_max)]
        q_low, q_high = min(q_ends), max(q_ends)
        x_field = next((field for field in self.template.fields if field.name == "x_um"), None)
        if x_field is not None:
            warnings.append(f"command: {x_field.text} writes the client's target moved along the ramp, not the "
                            "compensated command: a target the compensation leaves outside [q(v_min), q(v_max)] "
                            f"= [{q_low:g}, {q_high:g}] um is refused (the axis faults, nothing written); write "
                            f"{{q_um:{x_field.spec}}} for a closed-loop controller")
        for field in self.template.fields:
            if field.name in POSITION_FIELDS:
                try:
                    low, high = field.inside(q_low, q_low, q_high), field.inside(q_high, q_low, q_high)
                except ValueError:
                    low = high = ("", math.nan)
                if not low[1] < high[1]:
                    warnings.append(f"command: {field.text} cannot write two positions within [q(v_min), q(v_max)] "
                                    f"= [{q_low:g}, {q_high:g}] um: every command would be refused or the same; "
                                    f"e.g. {{{field.name}:{_decimals_for(RESOLUTION_UM)}f}}")
                    continue
            if field.name == "voltage_v":
                step = float(field.step(max(abs(v_min), abs(v_max))))
                step_um = step / abs(volts_per_um)
                unit, suggestion = f"{step:g} V", _decimals_for(RESOLUTION_UM * abs(volts_per_um))
                per = f", {step_um * 1000:g} nm of stage travel at volts_per_um = {volts_per_um:g}"
            else:
                step_um = float(field.step(max(abs(q) for q in q_ends)))
                unit, suggestion, per = f"{step_um:g} um", _decimals_for(RESOLUTION_UM), ""
            if step_um > RESOLUTION_UM * (1 + 1e-9):
                warnings.append(f"command: {field.text} writes {field.name} in steps of {unit}{per}, coarser than "
                                f"{RESOLUTION_UM * 1000:g} nm: every command reaches the stage rounded to that; "
                                f"e.g. {{{field.name}:{suggestion}f}}")
        return warnings
