"""The DCON ASCII protocol of ADAM-4000 and ICP DAS I-7000 modules: framing, checksum, and the answers
nanodrift reads. Pure: no I/O.

Sources (each behaviour below names where it comes from):

- *ADAM 4000 Series User's Manual* (Advantech), chapter 5 "Analog Input Module Commands":
  ``#AA`` (Analog Data In, 4017/4018/4018+/4019+: ``>`` then every channel's value run together, each a
  sign and five digits with a fixed decimal point in engineering units; the manual's example ``#21`` ->
  ``>+7.2111+7.2567+7.3125+7.1000+7.4712+7.2555+7.1234+7.5678``); the out-of-bounds table of ``#AA``
  (a thermocouple or RTD input outside its configured range reads ``+9999`` over, ``-0000`` under, in
  engineering units; a value at or beyond 9999 in magnitude is taken as such a code on every module:
  no thermocouple reads 9999 degC); ``$AAM`` (Read Module Name: ``!AA`` then the name, e.g. ``!014018``); ``$AA2``
  (Configuration Status: ``!AATTCCFF``; FF bits 0-1 the data format, 00 = engineering units, bit 6 the
  checksum); ``$AAB`` (Channel Diagnose, 4015/4018+/4019+: ``!AANN``, bit N set = channel N over range,
  under range or open wiring); ``?AA`` answers an invalid command; a wrong address or a syntax error
  gets no answer at all.
- *ICP DAS DCON checksum* (e.g. the ZT-2005 and DGW-521 manuals, section "Checksum"): the sum of the
  ASCII codes of every character before the CR, masked by 0xFF, sent as two upper-case hex digits
  before the CR, in commands and answers alike (``$012`` -> ``$012B7``).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

CR = "\r"
#: the ADAM manual's over-range code (engineering units): an open thermocouple reads it too
OVER_RANGE = 9999.0
#: one channel's value in an ``#AA`` answer: a sign, digits, an optional fixed decimal point
VALUE = re.compile(r"[+-](?:\d+\.?\d*|\.\d+)")
#: the data-format bits of ``$AA2``'s FF byte (00 = engineering units) and its checksum bit
FORMAT_MASK = 0x03
CHECKSUM_BIT = 0x40


class DconFormatError(ValueError):
    """An answer that is not what the protocol says it must be (the message says what was expected)."""


def checksum(text: str) -> str:
    """Two upper-case hex digits: the sum of the characters' codes, masked by 0xFF (ICP DAS)."""
    return f"{sum(text.encode('latin-1')) & 0xFF:02X}"


def frame(command: str, *, with_checksum: bool) -> bytes:
    """What goes on the wire for ``command`` (``#01``): with its checksum when the module wants one, then CR."""
    return (command + (checksum(command) if with_checksum else "") + CR).encode("latin-1")


def unframe(answer: str, *, with_checksum: bool) -> str:
    """The answer without its CR and checksum; :class:`DconFormatError` when the checksum is wrong or missing."""
    body = answer.rstrip(CR)
    if not with_checksum:
        return body
    if len(body) < 3:
        raise DconFormatError(f"expected an answer and two checksum digits, got {body!r}")
    body, given = body[:-2], body[-2:]
    if given.upper() != checksum(body):
        raise DconFormatError(f"checksum {given!r} does not match {checksum(body)!r} (the sum of {body!r})")
    return body


@dataclass(frozen=True, slots=True)
class ChannelValue:
    """One channel of an ``#AA`` answer: its value in the module's unit, or why it is no value."""

    value: float
    text: str  # as the module wrote it
    problem: str = ""  # "" = a measurement


def channel_value(text: str) -> ChannelValue:
    """The value ``text`` carries; over range (at or beyond +/-9999) and the under-range code ``-0000``
    are problems, never temperatures."""
    value = float(text)
    if text == "-0000":
        return ChannelValue(math.nan, text, "under range (the module's code -0000)")
    if not math.isfinite(value) or abs(value) >= OVER_RANGE:
        return ChannelValue(math.nan, text, f"over range or open thermocouple (the module's code {text})")
    return ChannelValue(value, text)


def parse_all_channels(body: str) -> list[ChannelValue]:
    """Every channel of an ``#AA`` answer (``>+0025.23+0024.98...``, checksum already removed), in order.

    :class:`DconFormatError` for anything else: ``?AA`` (the module refused the command), a missing
    ``>``, characters that are not values.
    """
    if body.startswith("?"):
        raise DconFormatError(f"the module answered {body!r}: invalid command")
    if not body.startswith(">"):
        raise DconFormatError(f"expected '>' and the channels' values (e.g. '>+0025.23+0024.98'), got {body!r}")
    data = body[1:]
    values = VALUE.findall(data)
    if not values or "".join(values) != data:
        raise DconFormatError(f"expected signed values (e.g. '+0025.23') after '>', got {body!r}")
    return [channel_value(text) for text in values]


def _reply_to(body: str, address: int, what: str) -> str:
    """What follows ``!AA`` in a ``$AA...`` answer; :class:`DconFormatError` otherwise."""
    prefix = f"!{address:02X}"
    if not body.upper().startswith(prefix):
        raise DconFormatError(f"expected {prefix}... answering {what}, got {body!r}")
    return body[len(prefix):]


def parse_module_name(body: str, address: int) -> str:
    """The name in a ``$AAM`` answer (``!014018`` -> ``4018``)."""
    name = _reply_to(body, address, f"${address:02X}M").strip()
    if not name:
        raise DconFormatError(f"expected a module name after !{address:02X}, got {body!r}")
    return name


@dataclass(frozen=True, slots=True)
class ModuleConfiguration:
    """``$AA2``'s answer: input range code, baud code, and the data-format byte."""

    type_code: int
    baud_code: int
    format_byte: int

    @property
    def engineering_units(self) -> bool:
        return self.format_byte & FORMAT_MASK == 0

    @property
    def checksum(self) -> bool:
        return bool(self.format_byte & CHECKSUM_BIT)


def parse_configuration(body: str, address: int) -> ModuleConfiguration:
    """``!AATTCCFF`` -> its three bytes."""
    rest = _reply_to(body, address, f"${address:02X}2")
    if not re.fullmatch(r"[0-9A-Fa-f]{6}", rest):
        raise DconFormatError(f"expected !{address:02X}TTCCFF (six hex digits after the address), got {body!r}")
    return ModuleConfiguration(int(rest[0:2], 16), int(rest[2:4], 16), int(rest[4:6], 16))


def parse_diagnosis(body: str, address: int) -> int:
    """The channel bit mask of a ``$AAB`` answer (``!01NN``): bit N set = channel N out of range or open."""
    rest = _reply_to(body, address, f"${address:02X}B")
    if not re.fullmatch(r"[0-9A-Fa-f]{1,2}", rest):
        raise DconFormatError(f"expected !{address:02X}NN (a hex channel mask), got {body!r}")
    return int(rest, 16)
