"""The ``[[sensors]]`` keys of a line-oriented serial instrument."""

from __future__ import annotations

import re
from typing import Literal

from pydantic import Field, FiniteFloat, field_validator

from drivers.base import SensorConfig

#: a number anywhere on its own line: "12345.6", "-0.25", "+1.5e3"
DEFAULT_PATTERN = r"\s*(?P<value>[-+]?(?:\d+\.?\d*|\.\d+)(?:[eE][-+]?\d+)?)\s*"


class SerialLineSensorConfig(SensorConfig):
    """One value per line of text from a serial port (queried, or streamed by the device)."""

    kind: Literal["serial_line"] = "serial_line"
    port: str = Field(description="anything pyserial's serial_for_url accepts: /dev/ttyUSB0, socket://host:port")
    baudrate: int = Field(default=9600, gt=0)
    bytesize: Literal[5, 6, 7, 8] = 8
    parity: Literal["N", "E", "O", "M", "S"] = "N"
    stopbits: Literal[1, 1.5, 2] = 1
    query: str = Field(default="", description="sent each interval_s, exactly as written; empty: the device "
                                               "streams lines by itself")
    pattern: str = Field(default=DEFAULT_PATTERN, description="regex the whole line must match (re.fullmatch), "
                                                              "with a named group 'value'")
    scale: FiniteFloat = Field(default=1.0, description="raw -> unit (e.g. nm -> um: 0.001)")
    offset: FiniteFloat = 0.0
    eol: Literal["\r\n", "\n", "\r"] = Field(
        default="\n", description="line terminator; '\\n' and '\\r\\n' behave the same (a trailing '\\r' is "
                                  "dropped); '\\r' for devices that end lines with CR only")
    unit: str | None = Field(default=None, description="unit of the scaled value; default um / degC by role")

    @field_validator("pattern")
    @classmethod
    def _pattern_has_value_group(cls, pattern: str) -> str:
        try:
            compiled = re.compile(pattern)
        except re.error as error:
            raise ValueError(f"not a valid regular expression: {error}") from None
        if "value" not in compiled.groupindex:
            raise ValueError("needs a named group 'value', e.g. 'P (?P<value>[-+0-9.]+) nm'")
        return pattern

    @property
    def value_unit(self) -> str:
        if self.unit is not None:
            return self.unit
        return "um" if self.role == "position" else "degC"

    @property
    def streaming(self) -> bool:
        return self.query == ""
