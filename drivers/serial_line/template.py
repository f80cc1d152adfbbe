"""What a serial command template sends, as numbers: the string written is what is checked.

``"SVA 1 {voltage_v:.1f}\\n"`` with ``v_max = 9.17`` and a command of 9.17 V would write ``SVA 1 9.2``:
the daemon checked 9.17 against the limits, the controller got 9.2. Here each field is formatted
alone with its own format spec and the number the device will read is parsed back from that text.
A ``voltage_v`` that the template's rounding puts outside ``[v_min, v_max]`` is written as the
nearest value the template can write *inside* them (rounded toward the inside at the template's
precision: ``SVA 1 9.1``), the way the Modbus output takes the count on the inside; when no
representable value lies inside, :class:`ValueError` (nothing is written). The numbers sent are
returned with the text, so the readback is compared with what the device was told.

Format specs: the float types of Python's format mini-language (``f F e E g G n %`` and none), with
any width, sign, fill and grouping whose output still reads as the number. A conversion
(``{voltage_v!r}``) or a nested field in a spec is refused: the sent number must follow from the spec.

Every field is held to the limits in force for its unit: ``voltage_v`` to ``[v_min, v_max]``, the
position fields ``q_um`` and ``x_um`` to the command range those voltages mean (``[q(v_min), q(v_max)]``):
``MOV 1 {q_um:.0f}`` with q 459.552 um at a 9.19 V limit writes ``MOV 1 459``, never ``460``. A value
already outside its range (an ``x_um`` target the compensation moved outside) is refused, never clamped.
"""

from __future__ import annotations

import math
import re
import string
from collections.abc import Mapping
from dataclasses import dataclass
from decimal import ROUND_CEILING, ROUND_FLOOR, Decimal

#: what a field may name
COMMAND_FIELDS = ("voltage_v", "q_um", "x_um")
#: the fields that carry a stage position (um): held to the command range, as ``voltage_v`` to the voltage limits
POSITION_FIELDS = ("q_um", "x_um")
#: float rounding of a limit mapped through the gain (um or V), not a digit of any template
LIMIT_SLACK = 1e-9

_SPEC = re.compile(r"^(?:(?P<fill>.)?[<>=^])?[-+ ]?z?#?0?(?P<width>\d+)?[,_]?(?:\.(?P<precision>\d+))?"
                   r"(?P<type>[eEfFgGn%])?$", re.DOTALL)
_NUMBER = re.compile(r"[-+]?(?:\d[\d,_]*(?:\.\d*)?|\.\d+)(?:[eE][-+]?\d+)?%?")
#: values a template must write back as themselves (to its precision) to be accepted
_PROBES = (-123.456789, -9.17, -0.5, 0.0, 0.000123, 0.4, 9.17, 1234.5678)
#: inward steps tried before giving up (the first is almost always it; 'g'/'e' may cross a decade)
_INWARD_TRIES = 3


@dataclass(frozen=True)
class TemplateField:
    """One ``{name:spec}`` of a command template."""

    name: str
    spec: str
    type: str  # one of "eEfFgGn%" or "" (none)
    precision: int | None

    @property
    def text(self) -> str:
        return "{" + self.name + (":" + self.spec if self.spec else "") + "}"

    def format(self, value: float) -> str:
        return format(value, self.spec)

    def number(self, text: str) -> float:
        """The number ``text`` (this field's output) carries, as the device reads it."""
        match = _NUMBER.search(text)
        if match is None:
            raise ValueError(f"{self.text} wrote {text!r}, which carries no number")
        digits = match.group().replace(",", "").replace("_", "")
        if digits.endswith("%"):
            return float(Decimal(digits[:-1]) / 100)
        return float(Decimal(digits))

    def sent(self, value: float) -> tuple[str, float]:
        """The text written for ``value`` and the number it carries."""
        text = self.format(value)
        return text, self.number(text)

    @property
    def exact(self) -> bool:
        """Writes every float exactly (shortest repr, no precision): nothing is rounded."""
        return self.type == "" and self.precision is None

    def step(self, magnitude: float) -> Decimal:
        """The spacing of the values this field can write near ``magnitude`` (0: exact)."""
        if self.exact:
            return Decimal(0)
        precision = 6 if self.precision is None else self.precision
        if self.type in ("f", "F"):
            return Decimal(1).scaleb(-precision)
        if self.type == "%":
            return Decimal(1).scaleb(-precision - 2)
        if magnitude == 0 or not math.isfinite(magnitude):
            return Decimal(0)
        exponent = Decimal(repr(abs(magnitude))).adjusted()  # the decade, exactly
        if self.type in ("e", "E"):
            return Decimal(1).scaleb(exponent - precision)
        return Decimal(1).scaleb(exponent - max(precision, 1) + 1)  # g, G, n, none: significant digits

    def inside(self, value: float, low: float, high: float) -> tuple[str, float]:
        """The text for ``value`` and its number, the number within ``[low, high]``: as formatted when
        it is, else the nearest value this field can write inside (:class:`ValueError`: none)."""
        if not math.isfinite(value):
            raise ValueError(f"{value} is not a finite number")
        text, sent = self.sent(value)
        if low <= sent <= high:
            return text, sent
        down = sent > high
        limit = high if down else low
        candidate = Decimal(repr(limit))
        step = self.step(limit)
        if step:
            candidate = (candidate / step).to_integral_value(ROUND_FLOOR if down else ROUND_CEILING) * step
        for _ in range(_INWARD_TRIES):
            text, sent = self.sent(float(candidate))
            if low <= sent <= high:
                return text, sent
            if not step:
                break
            candidate += -step if down else step
        raise ValueError(f"{self.text} cannot write {value:.6g} within [{low:g}, {high:g}]: it writes "
                         f"{self.format(value).strip()!r}, and no value it can write lies within")


class CommandTemplate:
    """A ``str.format`` command template, field by field (:class:`ValueError` for one it cannot take)."""

    def __init__(self, template: str) -> None:
        self.template = template
        self.pieces: list[tuple[str, TemplateField | None]] = []
        try:
            parsed = list(string.Formatter().parse(template))
        except ValueError as error:
            raise ValueError(f"not a valid format template: {error}") from None
        unknown = sorted({name for _, name, _, _ in parsed if name is not None and name not in COMMAND_FIELDS})
        if unknown:
            raise ValueError(f"unknown field(s) {', '.join('{' + n + '}' for n in unknown)}; "
                             f"fields: {', '.join(COMMAND_FIELDS)}")
        for literal, name, spec, conversion in parsed:
            if name is None:
                self.pieces.append((literal, None))
                continue
            spec = spec or ""
            shown = "{" + name + (f"!{conversion}" if conversion else "") + (f":{spec}" if spec else "") + "}"
            if conversion:
                raise ValueError(f"{shown}: a conversion (!{conversion}) writes a string, not a number the "
                                 f"limits can be checked on; write e.g. {{{name}:.4f}}")
            if "{" in spec:
                raise ValueError(f"{shown}: a field inside a format spec is not supported; write e.g. {{{name}:.4f}}")
            match = _SPEC.match(spec)
            if match is None:
                raise ValueError(f"{shown}: cannot format a number with it (a float format: f, e, g or %, "
                                 f"e.g. {{{name}:.4f}})")
            precision = match["precision"]
            field = TemplateField(name, spec, match["type"] or "", None if precision is None else int(precision))
            for probe in _PROBES:
                try:
                    text, number = field.sent(probe)
                except ValueError:
                    number, text = math.nan, field.format(probe)
                if not abs(number - probe) <= float(field.step(probe)) / 2 * 1.000001 + 1e-12 * abs(probe):
                    raise ValueError(f"{shown}: the number it writes cannot be read back ({probe:g} is written "
                                     f"{text!r}); write e.g. {{{name}:.4f}}")
            self.pieces.append((literal, field))
        if not self.fields:
            raise ValueError("names none of the fields voltage_v, q_um, x_um: every command would write the same")

    @property
    def fields(self) -> list[TemplateField]:
        return [field for _, field in self.pieces if field is not None]

    def render(self, values: Mapping[str, float], limits_v: tuple[float, float] | None = None,
               limits_q_um: tuple[float, float] | None = None) -> tuple[str, dict[str, float]]:
        """The text to write, and the number each field's first occurrence carries.

        Each field is kept within its limits (``voltage_v`` within ``limits_v``, ``q_um`` and ``x_um``
        within ``limits_q_um``; None: not checked), rounded toward the inside at its precision;
        :class:`ValueError` for a non-finite value, one outside its limits before formatting, or one
        that cannot be written inside.
        """
        out: list[str] = []
        sent: dict[str, float] = {}
        for literal, field in self.pieces:
            out.append(literal)
            if field is None:
                continue
            value = values[field.name]
            if not math.isfinite(value):
                raise ValueError(f"{field.name} = {value} is not a finite number")
            limits = limits_q_um if field.name in POSITION_FIELDS else limits_v
            if limits is None:
                text, number = field.sent(value)
            else:
                low, high = limits
                slack = LIMIT_SLACK * max(1.0, abs(low), abs(high))
                if field.name in POSITION_FIELDS and not low - slack <= value <= high + slack:
                    raise ValueError(f"{field.name} = {value:.6g} um is outside the command range [{low:.6g}, "
                                     f"{high:.6g}] um (the voltage limits through the gain): nothing written")
                text, number = field.inside(value, low, high)
            out.append(text)
            sent.setdefault(field.name, number)
        return "".join(out), sent
