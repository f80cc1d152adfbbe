"""The calibrated model: named terms with coefficients, what it was trained on, and how to apply it.

``q = Σ coef_i · feature_i`` (eq. 3 when the terms are x^3, x^2, x, T1..T4 and 1). The same object
predicts a whole recorded series (:meth:`Model.predict`) and serves the daemon sample by sample
(:class:`Evaluator`), with identical results.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from daemon.model.terms import Power, Term, TermStream, UnknownTermError, parse_term

FORMAT = "nanodrift-model/1"


class ModelFileError(ValueError):
    """A model file that cannot be used; the message names the file and what is wrong."""


class MissingChannelError(ValueError):
    """Data or a sensor set lacks a channel the model needs."""


class SeriesLike(Protocol):
    t: np.ndarray
    x: np.ndarray
    channels: Mapping[str, np.ndarray]


@dataclass(frozen=True)
class FittedTerm:
    term: Term
    coef: float
    se: float = math.nan
    p: float = math.nan


@dataclass(frozen=True)
class Training:
    """What the model has seen: outside these ranges it extrapolates (the paper's test 5)."""

    x_range: tuple[float, float]
    channel_ranges: dict[str, tuple[float, float]]
    rows: int
    t_span_s: float

    @classmethod
    def of(cls, data: SeriesLike, channels: Sequence[str]) -> Training:
        t = np.asarray(data.t)
        return cls(
            x_range=(float(np.min(data.x)), float(np.max(data.x))),
            channel_ranges={c: (float(np.min(data.channels[c])), float(np.max(data.channels[c]))) for c in channels},
            rows=int(t.shape[0]),
            t_span_s=float(t[-1] - t[0]) if t.shape[0] else 0.0,
        )


@dataclass
class Model:
    terms: list[FittedTerm]
    training: Training
    fit: dict[str, Any] = field(default_factory=dict)
    selection: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    id: str = ""

    def __post_init__(self) -> None:
        if not self.id:
            self.id = self.content_id()

    def content_id(self) -> str:
        """A short id that changes whenever a term or coefficient does."""
        text = json.dumps([[ft.term.name, ft.coef] for ft in self.terms])
        return "m-" + hashlib.sha256(text.encode()).hexdigest()[:12]

    @property
    def channels(self) -> tuple[str, ...]:
        seen: dict[str, None] = {}
        for ft in self.terms:
            for c in ft.term.channels:
                seen[c] = None
        return tuple(seen)

    @property
    def coefs(self) -> np.ndarray:
        return np.array([ft.coef for ft in self.terms], dtype=np.float64)

    def term_names(self) -> list[str]:
        return [ft.term.name for ft in self.terms]

    def check_channels(self, available: Sequence[str], where: str = "data") -> None:
        missing = [c for c in self.channels if c not in available]
        if missing:
            raise MissingChannelError(
                f"{where} lacks channel(s) {', '.join(missing)} that the model needs "
                f"(model channels: {', '.join(self.channels)}; available: {', '.join(available) or 'none'})"
            )

    def features(self, data: SeriesLike) -> np.ndarray:
        self.check_channels(list(data.channels), getattr(data, "source", "data"))
        return np.column_stack([ft.term.batch(data.t, data.x, data.channels) for ft in self.terms])

    def predict(self, data: SeriesLike) -> np.ndarray:
        """The command q for every row; stateful terms run over the rows in order."""
        self.check_channels(list(data.channels), getattr(data, "source", "data"))
        q = np.zeros(np.asarray(data.t).shape[0], dtype=np.float64)
        for ft in self.terms:
            q += ft.coef * ft.term.batch(data.t, data.x, data.channels)
        return q

    def out_of_range(self, x: float | None = None, temps: Mapping[str, float] | None = None) -> list[str]:
        """Names (``x`` or channels) whose value lies outside what the model was trained on."""
        out = []
        if x is not None and not (self.training.x_range[0] <= x <= self.training.x_range[1]):
            out.append("x")
        for name, value in (temps or {}).items():
            bounds = self.training.channel_ranges.get(name)
            if bounds is not None and not (bounds[0] <= value <= bounds[1]):
                out.append(name)
        return out

    def evaluator(self) -> Evaluator:
        return Evaluator(self)

    # --- file format ----------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "id": self.id,
            "terms": [{"term": ft.term.name, "coef": ft.coef, "se": _num(ft.se), "p": _num(ft.p)} for ft in self.terms],
            "channels": list(self.channels),
            "training": {
                "x_um": list(self.training.x_range),
                "channels": {c: list(r) for c, r in self.training.channel_ranges.items()},
                "rows": self.training.rows,
                "t_span_s": self.training.t_span_s,
            },
            "fit": self.fit,
            "selection": self.selection,
            "provenance": self.provenance,
        }

    @classmethod
    def from_dict(cls, doc: Any, where: str = "model") -> Model:
        return _model_from_dict(doc, where)


def _num(value: float) -> float | None:
    return None if value is None or not math.isfinite(value) else float(value)


class Evaluator:
    """The model fed sample by sample, as the daemon runs it.

    Temperature-only terms are summed once per temperature sample (``observe``), so a target costs
    a cubic in Horner form plus the few terms that depend on the target or the motion.
    """

    __slots__ = ("_dynamic", "_poly", "_static", "_static_sum", "_streams", "model", "seen")

    def __init__(self, model: Model) -> None:
        self.model = model
        self._streams: list[TermStream] = [ft.term.stream() for ft in model.terms]
        degree = max((ft.term.k for ft in model.terms if isinstance(ft.term, Power)), default=0)
        poly = [0.0] * (degree + 1)  # poly[k] multiplies x^k
        self._static: list[tuple[float, TermStream]] = []
        self._dynamic: list[tuple[float, TermStream]] = []
        for ft, stream in zip(model.terms, self._streams, strict=True):
            if isinstance(ft.term, Power):
                poly[ft.term.k] += ft.coef
            elif ft.term.uses_x:
                self._dynamic.append((ft.coef, stream))
            else:
                self._static.append((ft.coef, stream))
        self._poly = tuple(reversed(poly))  # highest power first, for Horner
        self.seen: set[str] = set()
        self._static_sum = self._sum_static()

    @property
    def ready(self) -> bool:
        """Every channel the model needs has been observed at least once."""
        return all(c in self.seen for c in self.model.channels)

    def _sum_static(self) -> float:
        total = 0.0
        for coef, stream in self._static:
            total += coef * stream.value(0.0, 0.0)
        return total

    def observe(self, t: float, temps: Mapping[str, float]) -> None:
        for stream in self._streams:
            stream.observe(t, temps)
        self.seen.update(temps)
        self._static_sum = self._sum_static()

    def value(self, x: float, t: float) -> float:
        """q for target ``x`` at ``t``, changing nothing: the caller may still refuse the target."""
        q = 0.0
        for c in self._poly:
            q = q * x + c
        q += self._static_sum
        for coef, stream in self._dynamic:
            q += coef * stream.value(t, x)
        return q

    def moved(self, x: float, t: float) -> None:
        """The stage was commanded to ``x`` at ``t``: motion-dependent terms (dir, creep) advance."""
        for _, stream in self._dynamic:
            stream.moved(t, x)

    def command(self, x: float, t: float) -> float:
        """q for target ``x`` at ``t``, and the move recorded (``value`` then ``moved``)."""
        q = self.value(x, t)
        self.moved(x, t)
        return q

    def row(self, t: float, x: float, temps: Mapping[str, float]) -> float:
        self.observe(t, temps)
        return self.command(x, t)


# --- model file ---------------------------------------------------------------------------------


def save_model(model: Model, path: str | os.PathLike[str]) -> None:
    """Write the model file atomically (temp file + rename)."""
    from daemon.atomic import atomic_write_text  # local: keep model/ importable on its own

    atomic_write_text(path, json.dumps(model.to_dict(), indent=2, allow_nan=False) + "\n")


def load_model(path: str | os.PathLike[str]) -> Model:
    """Read and check a model file; :class:`ModelFileError` says what is wrong and where."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ModelFileError(f"{path}: no such model file") from None
    except (OSError, UnicodeDecodeError) as err:
        raise ModelFileError(f"{path}: cannot read the model file ({err})") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as err:
        raise ModelFileError(f"{path}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    return _model_from_dict(doc, str(path))


def _model_from_dict(doc: Any, where: str) -> Model:
    def fail(msg: str) -> ModelFileError:
        return ModelFileError(f"{where}: {msg}")

    if not isinstance(doc, dict):
        raise fail("expected a JSON object")
    if doc.get("format") != FORMAT:
        raise fail(f"format is {doc.get('format')!r}, expected {FORMAT!r}")
    raw_terms = doc.get("terms")
    if not isinstance(raw_terms, list) or not raw_terms:
        raise fail("'terms' must be a non-empty list")
    terms: list[FittedTerm] = []
    for i, item in enumerate(raw_terms):
        if not isinstance(item, dict) or not isinstance(item.get("term"), str):
            raise fail(f"terms[{i}]: expected an object with a 'term' name")
        try:
            term = parse_term(item["term"])
        except (UnknownTermError, ValueError) as err:
            raise fail(f"terms[{i}]: {err}") from None
        coef = item.get("coef")
        if isinstance(coef, bool) or not isinstance(coef, int | float) or not math.isfinite(coef):
            raise fail(f"terms[{i}] ({item['term']}): 'coef' must be a finite number, got {coef!r}")
        se, p = item.get("se"), item.get("p")
        terms.append(
            FittedTerm(term, float(coef), math.nan if se is None else float(se), math.nan if p is None else float(p))
        )
    names = [ft.term.name for ft in terms]
    if len(set(names)) != len(names):
        raise fail(f"duplicate terms in {names}")
    training = _training_from_dict(doc.get("training"), fail)
    model = Model(
        terms=terms,
        training=training,
        fit=dict(doc.get("fit") or {}),
        selection=dict(doc.get("selection") or {}),
        provenance=dict(doc.get("provenance") or {}),
        id=str(doc.get("id") or ""),
    )
    declared = doc.get("channels")
    if declared is not None and list(declared) != list(model.channels):
        raise fail(f"'channels' {declared} does not match the channels its terms read {list(model.channels)}")
    unranged = [c for c in model.channels if c not in training.channel_ranges]
    if unranged:
        raise fail(f"training ranges missing for channel(s) {', '.join(unranged)}")
    return model


def _training_from_dict(raw: Any, fail: Any) -> Training:
    if not isinstance(raw, dict):
        raise fail("'training' must be an object with x_um and channels ranges")

    def pair(value: Any, what: str) -> tuple[float, float]:
        ok = (
            isinstance(value, list)
            and len(value) == 2
            and all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v) for v in value)
            and value[0] <= value[1]
        )
        if not ok:
            raise fail(f"training range of {what} must be [low, high], got {value!r}")
        return float(value[0]), float(value[1])

    channels = raw.get("channels") or {}
    if not isinstance(channels, dict):
        raise fail("training.channels must be an object {channel: [low, high]}")
    return Training(
        x_range=pair(raw.get("x_um"), "x_um"),
        channel_ranges={str(c): pair(r, c) for c, r in channels.items()},
        rows=int(raw.get("rows") or 0),
        t_span_s=float(raw.get("t_span_s") or 0.0),
    )
