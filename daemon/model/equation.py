"""The model as one readable equation, for people: ``q = 6.728e-09·x³ − 5.182e-06·x² + 1.000523·x − … − 27.92``.

One formatter, so ``calibrate``, ``demo`` and ``fit`` print a model the same way (and
:func:`training_lines`, the ranges it was trained on, so ``fit`` and ``calibrate`` print those alike). Signs are joined
into the sum (never ``+ -5.2``), powers of x are superscripts, the bias is the bare constant.

Each coefficient gets at least ``digits`` significant digits, and as many more as it takes for the
rounding to change its term by less than :data:`ROUNDING_TOLERANCE_UM` (1 nm) anywhere in the training
box: a gain of 1.00049 printed "1" would hide 0.24 µm at 480 µm, and -1.4784 µm/°C printed -1.478 hides
9 nm at 22 °C. So the printed equation computes the model's command to within a nanometre a term.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Sequence

import numpy as np

from nanodrift.model.model import FittedTerm, Model, Training
from nanodrift.model.terms import Bias, ChannelSquare, Power, Term, position_key

#: the most a printed coefficient's rounding may change its term inside the training box (µm)
ROUNDING_TOLERANCE_UM = 1e-3
MAX_DIGITS = 15

_SUPERSCRIPT = str.maketrans("0123456789-", "⁰¹²³⁴⁵⁶⁷⁸⁹⁻")
MINUS = "−"  # U+2212: a minus sign, not a hyphen


def term_label(term: object) -> str:
    """``x³`` for a power of x, ``x·T1`` for a product, ``(T2 − 22.05)²`` for a channel's square, other
    names as they are; ``""`` for the bias."""
    if isinstance(term, Bias):
        return ""
    if isinstance(term, Power):  # y³ as x³ for another axis of a cell
        return term.axis if term.k == 1 else term.axis + str(term.k).translate(_SUPERSCRIPT)
    if isinstance(term, ChannelSquare):  # (T2 − 22.05)², the centre as exact as in the name
        return term.name.replace(" - ", f" {MINUS} ").removesuffix("^2") + "²"
    return str(getattr(term, "name", term)).replace("*", "·")


def feature_bound(term: Term, training: Training) -> float | None:
    """The largest |feature| of ``term`` on the corners of the training box (x and every channel at
    their ends, held in turn: a lag or a product of them stays within the same bounds), or None when
    the training ranges do not name what the term reads."""
    ranges = {**training.channel_ranges, **{position_key(a): r for a, r in training.position_ranges.items()}}
    channels = list(ranges)
    corners = list(itertools.product(training.x_range, *(ranges[c] for c in channels)))
    x = np.repeat([c[0] for c in corners], 2)  # each corner held for two samples, 30 s apart
    t = np.arange(x.size, dtype=np.float64) * 30.0
    values = {c: np.repeat([corner[i + 1] for corner in corners], 2) for i, c in enumerate(channels)}
    try:
        feature = np.asarray(term.batch(t, x, values), dtype=np.float64)
    except (KeyError, ValueError):
        return None
    bound = float(np.max(np.abs(feature))) if feature.size else 0.0
    return bound if math.isfinite(bound) else None


def coefficient_digits(coef: float, bound: float | None, digits: int) -> int:
    """At least ``digits``; more until rounding moves ``coef * feature`` by < the tolerance over the box."""
    if bound is None or bound == 0.0 or not math.isfinite(coef):
        return digits
    for n in range(digits, MAX_DIGITS + 1):
        if abs(float(f"{coef:.{n}g}") - coef) * bound < ROUNDING_TOLERANCE_UM:
            return n
    return MAX_DIGITS


def equation(model: Model | Sequence[FittedTerm], *, digits: int = 4, lhs: str = "q") -> str:
    """``lhs = Σ coef·term``: each coefficient to at least ``digits`` significant digits, and with a
    model's training ranges as many more as keep its rounding under 1 nm (:func:`coefficient_digits`)."""
    terms = model.terms if isinstance(model, Model) else list(model)
    training = model.training if isinstance(model, Model) else None
    parts: list[str] = []
    for ft in terms:
        label = term_label(ft.term)
        bound = feature_bound(ft.term, training) if training is not None else None
        magnitude = f"{abs(ft.coef):.{coefficient_digits(ft.coef, bound, digits)}g}"
        body = f"{magnitude}·{label}" if label else magnitude
        negative = ft.coef < 0
        if not parts:
            parts.append(f"{MINUS}{body}" if negative else body)
        else:
            parts.append(f"{MINUS if negative else '+'} {body}")
    return f"{lhs} = " + (" ".join(parts) if parts else "0")


def training_lines(model: Model) -> list[str]:
    """The training ranges, in µm and °C: outside them the model extrapolates."""
    tr = model.training
    lines = [f"trained on x {_tenths(tr.x_range[0])}..{_tenths(tr.x_range[1])} µm"]
    lines.extend(f"  {ch}: {lo:.3f}..{hi:.3f} °C" for ch, (lo, hi) in tr.channel_ranges.items())
    return lines


def _tenths(value: float) -> str:
    text = f"{value:.1f}"
    return "0.0" if text == "-0.0" else text  # a measured -0.02 µm is the 0 µm point, not "-0.0"
