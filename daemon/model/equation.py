"""The model as one readable equation, for people: ``q = 6.671e-09·x³ − 5.177e-06·x² + 1.001·x − … − 27.95``.

One formatter, so ``calibrate``, ``demo`` and ``fit`` print a model the same way. Signs are joined
into the sum (never ``+ -5.2``), powers of x are superscripts, the bias is the bare constant.
"""

from __future__ import annotations

from collections.abc import Sequence

from daemon.model.model import FittedTerm, Model
from daemon.model.terms import Bias, Power

_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")
MINUS = "−"  # U+2212: a minus sign, not a hyphen


def term_label(term: object) -> str:
    """``x³`` for a power of x, ``x·T1`` for a product, other names as they are; ``""`` for the bias."""
    if isinstance(term, Bias):
        return ""
    if isinstance(term, Power):
        return "x" if term.k == 1 else "x" + str(term.k).translate(_SUPERSCRIPT)
    return str(getattr(term, "name", term)).replace("*", "·")


def _number(value: float, digits: int) -> str:
    return f"{value:.{digits}g}"


def equation(model: Model | Sequence[FittedTerm], *, digits: int = 4, lhs: str = "q") -> str:
    """``lhs = Σ coef·term`` with ``digits`` significant digits per coefficient."""
    terms = model.terms if isinstance(model, Model) else list(model)
    parts: list[str] = []
    for ft in terms:
        label = term_label(ft.term)
        magnitude = _number(abs(ft.coef), digits)
        body = f"{magnitude}·{label}" if label else magnitude
        negative = ft.coef < 0
        if not parts:
            parts.append(f"{MINUS}{body}" if negative else body)
        else:
            parts.append(f"{MINUS if negative else '+'} {body}")
    return f"{lhs} = " + (" ".join(parts) if parts else "0")
