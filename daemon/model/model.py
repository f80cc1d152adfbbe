"""The calibrated model: named terms with coefficients, what it was trained on, and how to apply it.

``q = Σ coef_i · feature_i`` (eq. 3 when the terms are x^3, x^2, x, T1..T4 and 1). The same object
predicts a whole recorded series (:meth:`Model.predict`) and serves the daemon sample by sample
(:class:`Evaluator`), with identical results.

A model's ``id`` is its content: a hash of what decides the commands it serves (see
:meth:`Model.content_id`), checked on load. A file edited by hand without a new id is refused, so a
reload can never keep serving an old model under a new file's name; ``nanodrift restamp`` gives a
deliberately edited file its new id. Loading also refuses what could only serve nonsense: non-finite
numbers, powers beyond ``x^12`` and a prediction that overflows inside the training box.

Longer than most modules (~580 lines) on purpose: the model, its id and the file format's checks
live together so that what is hashed, what is written and what is checked cannot drift apart (the
covariance block's own checks and its streaming evaluation are in :mod:`nanodrift.model.uncertainty`).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
import os
import stat
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.atomic import atomic_write_text
from nanodrift.model.json_unique import DuplicateKeyError, loads_unique
from nanodrift.model.segments import features, spans_s
from nanodrift.model.series import Series
from nanodrift.model.terms import Term, TermStream, UnknownTermError, is_x_power, parse_term, position_key
from nanodrift.model.uncertainty import Covariance, SigmaStream, _finite_number

FORMAT = "nanodrift-model/1"
#: deepest nesting of [ and { a model file may have (the format itself needs 4)
MAX_NESTING = 32
#: the largest model file read: a model file is kilobytes (terms, ranges, a covariance block), so this
#: bound only stops a wrong path (a log, a disk image, /dev/zero) from filling the daemon's memory
MAX_MODEL_BYTES = 64 * 2**20


class ModelFileError(ValueError):
    """A model file that cannot be used; the message names the file and what is wrong."""


class MissingChannelError(ValueError):
    """Data or a sensor set lacks a channel the model needs."""


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
    #: a multi-axis cell: the range of every axis but x (x is ``x_range``); empty for one axis
    position_ranges: dict[str, tuple[float, float]] = field(default_factory=dict)

    @classmethod
    def of(cls, data: Series, channels: Sequence[str]) -> Training:
        positions = getattr(data, "positions", None) or {}
        return cls(
            x_range=(float(np.min(data.x)), float(np.max(data.x))),
            channel_ranges={c: (float(np.min(data.channels[c])), float(np.max(data.channels[c]))) for c in channels},
            rows=len(data),
            t_span_s=float(sum(spans_s(data))),  # several runs: the time they cover, not the gaps between
            position_ranges={a: (float(np.min(v)), float(np.max(v))) for a, v in positions.items() if a != "x"},
        )

    def ranges_dict(self) -> dict[str, Any]:
        """The ``training`` block of a model file."""
        out: dict[str, Any] = {
            "x_um": list(self.x_range),
            "channels": {c: list(r) for c, r in self.channel_ranges.items()},
            "rows": self.rows,
            "t_span_s": self.t_span_s,
        }
        if self.position_ranges:
            out["positions_um"] = {a: list(r) for a, r in self.position_ranges.items()}
        return out


@dataclass
class Model:
    terms: list[FittedTerm]
    training: Training
    fit: dict[str, Any] = field(default_factory=dict)
    selection: dict[str, Any] = field(default_factory=dict)
    provenance: dict[str, Any] = field(default_factory=dict)
    id: str = ""
    #: the coefficients' covariance and the residual RMS (None: the file has no covariance block)
    covariance: Covariance | None = None

    def __post_init__(self) -> None:
        if self.covariance is not None and self.covariance.size != len(self.terms):
            raise ValueError(f"covariance is {self.covariance.size}x{self.covariance.size} for {len(self.terms)} terms")
        if not self.id:
            self.id = self.content_id()

    def content_id(self) -> str:
        """The id this content must carry: a hash of everything that decides what the model serves.

        Covered: the format, every term's canonical name, coefficient and standard error (the
        prediction and its uncertainty), the training ranges of x and of every channel (they
        decide which commands are flagged as extrapolating) and, when the file has one, the
        covariance block (it decides every command's ``q_sigma_um``). A file without one serves
        ``fit.rmse_um`` as every command's σ (:attr:`residual_rms_um`), so then that number is covered
        (a file with neither is hashed without either key and keeps its id). Not covered: the other
        fit statistics, the selection history and provenance, which describe how the model was made;
        editing those changes nothing that is served.
        """
        content: dict[str, Any] = {
            "format": FORMAT,
            "terms": [[ft.term.name, float(ft.coef), json_float(ft.se)] for ft in self.terms],
            "x_um": [float(v) for v in self.training.x_range],
            "channels": {c: [float(lo), float(hi)] for c, (lo, hi) in sorted(self.training.channel_ranges.items())},
        }
        if self.training.position_ranges:  # multi-axis only: a one-axis model hashes as it always has
            content["positions_um"] = {a: [float(lo), float(hi)]
                                       for a, (lo, hi) in sorted(self.training.position_ranges.items())}
        if self.covariance is not None:
            content["covariance"] = self.covariance.content()
        elif math.isfinite(self.residual_rms_um):  # the σ this model serves (issue 26.9: an edit kept the id)
            content["rmse_um"] = self.residual_rms_um
        text = json.dumps(content, separators=(",", ":"), sort_keys=True, allow_nan=False)
        return "m-" + hashlib.sha256(text.encode()).hexdigest()[:12]

    @property
    def channels(self) -> tuple[str, ...]:
        return tuple(dict.fromkeys(c for ft in self.terms for c in ft.term.channels))

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

    def features(self, data: Series) -> np.ndarray:
        self.check_channels(list(data.channels), data.source)
        return np.column_stack([features(ft.term, data) for ft in self.terms])

    def predict(self, data: Series) -> np.ndarray:
        """The command q for every row; stateful terms run over the rows in order (restarting at each run's
        first row when ``data`` holds several runs: :mod:`nanodrift.model.segments`).

        Far outside the training box a row's q may overflow to inf or nan: callers that write or
        serve q check it (``nanodrift predict`` refuses such a row by number).
        """
        self.check_channels(list(data.channels), data.source)
        q = np.zeros(np.asarray(data.t).shape[0], dtype=np.float64)
        with np.errstate(over="ignore", invalid="ignore"):
            for ft in self.terms:
                q += ft.coef * features(ft.term, data)
        return q

    @property
    def residual_rms_um(self) -> float:
        """The fit's residual standard deviation: the covariance block's, else ``fit.rmse_um`` (nan if neither)."""
        if self.covariance is not None:
            return self.covariance.residual_rms_um
        value = self.fit.get("rmse_um")
        return float(value) if _finite_number(value) and value >= 0 else math.nan

    @property
    def wander_um(self) -> float:
        """The position sensor's slow wander the calibration saw (``covariance.wander_um``; 0 without it)."""
        return (self.covariance.wander_um or 0.0) if self.covariance is not None else 0.0

    def q_sigma(self, data: Series) -> np.ndarray:
        """Standard uncertainty (µm) of the command :meth:`predict` gives for every row.

        ``sqrt(f·C·f + s² + (κ·g)²)`` row-wise (:mod:`nanodrift.model.uncertainty`): C the
        coefficients' covariance (how well the calibration run pinned them; it grows away from the
        training data, so outside the training ranges), s the residual RMS a fresh run sees, κ·g the
        curvature the training range cannot rule out (0 inside it). A model file without a
        covariance block gives the fit's residual RMS alone, the same for every row (``fit.rmse_um``;
        nan if the file lacks that too): it cannot say how uncertain an extrapolation is.
        """
        if self.covariance is None:
            return np.full(np.asarray(data.t).shape[0], self.residual_rms_um)
        sigma: np.ndarray = np.sqrt(self.covariance.variance(self.features(data), data.channels))
        return sigma

    def out_of_range(self, x: float | None = None, temps: Mapping[str, float] | None = None) -> list[str]:
        """Names (``x`` or channels) whose value lies outside what the model was trained on."""
        return outside({} if x is None else {"x": x}, {"x": self.training.x_range}) + outside(
            temps or {}, self.training.channel_ranges)

    def evaluator(self) -> Evaluator:
        return Evaluator(self)

    # --- file format ----------------------------------------------------------------------

    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT,
            "id": self.id,
            "terms": [{"term": ft.term.name, "coef": ft.coef, "se": json_float(ft.se), "p": json_float(ft.p)}
                      for ft in self.terms],
            "channels": list(self.channels),
            "training": self.training.ranges_dict(),
            "fit": self.fit,
            "selection": self.selection,
            "provenance": self.provenance,
            **({} if self.covariance is None else {"covariance": self.covariance.to_dict(self.term_names())}),
        }

    @classmethod
    def from_dict(cls, doc: Any, where: str = "model", *, check_id: bool = True,
                  axes: tuple[str, ...] = ("x",)) -> Model:
        return _model_from_dict(doc, where, check_id=check_id, axes=axes)


def json_float(value: float | None) -> float | None:
    """The value for a JSON document: NaN and infinities (not JSON) become null."""
    return None if value is None or not math.isfinite(value) else float(value)


class Evaluator:
    """The model fed sample by sample, as the daemon runs it.

    Temperature-only terms are summed once per temperature sample (``observe``), so a target costs
    a cubic in Horner form plus the few terms that depend on the target or the motion; its
    uncertainty (:meth:`sigma`) likewise (see :class:`nanodrift.model.uncertainty.SigmaStream`).
    """

    __slots__ = ("_dynamic", "_poly", "_positional", "_sigma", "_sigma_const", "_static", "_static_sum", "_streams",
                 "model", "seen")

    def __init__(self, model: Model) -> None:
        self.model = model
        self._streams: list[TermStream] = [ft.term.stream() for ft in model.terms]
        degree = max((ft.term.k for ft in model.terms if is_x_power(ft.term)), default=0)
        poly = [0.0] * (degree + 1)  # poly[k] multiplies x^k
        self._static: list[tuple[float, TermStream]] = []
        self._dynamic: list[tuple[float, TermStream]] = []
        for ft, stream in zip(model.terms, self._streams, strict=True):
            if is_x_power(ft.term):
                poly[ft.term.k] += ft.coef
            elif ft.term.uses_x:
                self._dynamic.append((ft.coef, stream))
            else:
                self._static.append((ft.coef, stream))
        self._poly = tuple(reversed(poly))  # highest power first, for Horner
        #: streams of the terms that read another axis' position (multi-axis cells)
        self._positional = [stream for ft, stream in zip(model.terms, self._streams, strict=True) if ft.term.axes]
        self.seen: set[str] = set()
        self._static_sum = self._sum_static()
        cov = model.covariance
        self._sigma = None if cov is None else SigmaStream([ft.term for ft in model.terms], self._streams, cov)
        self._sigma_const = model.residual_rms_um

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
        if self._sigma is not None:
            self._sigma.observe(temps)

    def targets(self, positions: Mapping[str, float]) -> None:
        """A multi-axis target's positions (every axis, µm), before ``value``/``sigma``/``moved`` for it."""
        for stream in self._positional:
            stream.targets(positions)

    def value(self, x: float, t: float) -> float:
        """q for target ``x`` at ``t``, changing nothing: the caller may still refuse the target."""
        q = 0.0
        for c in self._poly:
            q = q * x + c
        q += self._static_sum
        for coef, stream in self._dynamic:
            q += coef * stream.value(t, x)
        return q

    def sigma(self, x: float, t: float) -> float:
        """Standard uncertainty (µm) of ``value(x, t)``: as :meth:`Model.q_sigma` for the same features.

        Call it before ``moved``/``command`` for the same target (motion-dependent terms then see
        the same state as ``value``). Without a covariance in the model file: the residual RMS.
        """
        if self._sigma is None:
            return self._sigma_const
        return self._sigma.sigma(t, x)

    def moved(self, x: float, t: float) -> None:
        """The stage was commanded to ``x`` at ``t``: motion-dependent terms (dir, creep) advance."""
        for _, stream in self._dynamic:
            stream.moved(t, x)

    def command(self, x: float, t: float) -> float:
        """q for target ``x`` at ``t``, and the move recorded (``value`` then ``moved``)."""
        q = self.value(x, t)
        self.moved(x, t)
        return q


def aim(evaluators: Iterable[Evaluator], positions: Mapping[str, float]) -> float:
    """A cell's target (every axis' position, µm) given to every axis' evaluator: the ``x`` its ``value``,
    ``sigma``, ``moved`` and ``command`` take next (a term named ``x`` always reads the x axis: nan without one)."""
    for evaluator in evaluators:
        evaluator.targets(positions)
    return positions.get("x", math.nan)


# --- model file ---------------------------------------------------------------------------------


def save_model(model: Model, path: str | os.PathLike[str]) -> None:
    """Write the model file atomically (temp file + rename), stamped with its content's id.

    The id is set from the content here, so a file written by nanodrift always loads.
    """
    model.id = model.content_id()
    atomic_write_text(path, json.dumps(model.to_dict(), indent=2, allow_nan=False) + "\n")


def load_model(path: str | os.PathLike[str], *, check_id: bool = True) -> Model:
    """Read and check a model file; :class:`ModelFileError` says what is wrong and where.

    ``check_id=False`` skips only the id check (``nanodrift restamp``): everything else is checked.
    """
    path = Path(path)
    return _model_from_dict(read_model_doc(path), str(path), check_id=check_id)


def read_model_doc(path: Path) -> Any:
    """The JSON document of a model file (one axis or several); :class:`ModelFileError` if it is not one."""
    text = _read_model_text(path)
    try:
        return loads_unique(text)
    except json.JSONDecodeError as err:
        raise ModelFileError(f"{path}: not valid JSON (line {err.lineno}, column {err.colno}: {err.msg})") from None
    except DuplicateKeyError as err:
        raise ModelFileError(f"{path}: not a model file: {err}") from None
    except RecursionError:
        raise ModelFileError(
            f"{path}: not a model file: [ and {{ nested too deeply (a model file nests at most {MAX_NESTING} levels)"
        ) from None
    except ValueError as err:  # e.g. an integer of more than 4300 digits
        raise ModelFileError(f"{path}: not valid JSON ({err})") from None


def _file_kind(mode: int) -> str:
    kinds = ((stat.S_ISDIR, "a directory"), (stat.S_ISFIFO, "a FIFO (named pipe)"),
             (stat.S_ISCHR, "a character device"), (stat.S_ISBLK, "a block device"), (stat.S_ISSOCK, "a socket"))
    return next((name for test, name in kinds if test(mode)), "not a regular file")


def _read_model_text(path: Path) -> str:
    """The text of a model file, refused unless it is a regular file of at most :data:`MAX_MODEL_BYTES`.

    Checked before reading: a FIFO would block the daemon's event loop (targets refused as stale
    while it waits for a writer) and ``/dev/zero`` would be read until memory ran out. Opened with
    O_NONBLOCK and checked again on the open file, so a FIFO swapped in after the check cannot block
    either, and at most one byte more than the bound is ever read.
    """
    try:
        _check_regular(path, os.stat(path))
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except FileNotFoundError:
        raise ModelFileError(f"{path}: no such model file") from None
    except OSError as err:
        raise ModelFileError(f"{path}: cannot read the model file ({err})") from None
    with os.fdopen(fd, "rb") as file:
        try:
            _check_regular(path, os.fstat(file.fileno()))
            data = file.read(MAX_MODEL_BYTES + 1)
            if len(data) > MAX_MODEL_BYTES:
                raise ModelFileError(f"{path}: larger than {MAX_MODEL_BYTES // 2**20} MiB: not a model file (a "
                                     "model file is a few kilobytes of JSON)")
            return data.decode("utf-8")
        except (OSError, UnicodeDecodeError) as err:
            raise ModelFileError(f"{path}: cannot read the model file ({err})") from None


def _check_regular(path: Path, info: os.stat_result) -> None:
    if not stat.S_ISREG(info.st_mode):
        raise ModelFileError(f"{path}: {_file_kind(info.st_mode)}, not a model file: expected a regular file "
                             "(nanodrift-model/1 JSON)")
    if info.st_size > MAX_MODEL_BYTES:
        raise ModelFileError(f"{path}: {info.st_size} bytes, larger than {MAX_MODEL_BYTES // 2**20} MiB: not a "
                             "model file (a model file is a few kilobytes of JSON)")


def _nesting(doc: Any) -> int:
    """How deeply lists and objects nest in ``doc`` (iterative: no recursion limit to hit)."""
    deepest = 0
    stack: list[tuple[Any, int]] = [(doc, 1)]
    while stack:
        item, depth = stack.pop()
        if isinstance(item, dict | list):
            deepest = max(deepest, depth)
            if depth > MAX_NESTING:
                return depth
            stack.extend((child, depth + 1) for child in (item.values() if isinstance(item, dict) else item))
    return deepest


def _optional_number(value: Any, what: str, fail: Any, low: float, high: float = math.inf) -> float:
    """null -> nan (unknown); else a finite number within [low, high]."""
    if value is None:
        return math.nan
    if not _finite_number(value) or not low <= value <= high:
        bounds = f">= {low:g}" if high == math.inf else f"within [{low:g}, {high:g}]"
        raise fail(f"{what} must be a finite number {bounds} or null, got {value!r}")
    return float(value)


def _model_from_dict(doc: Any, where: str, *, check_id: bool = True, axes: tuple[str, ...] = ("x",)) -> Model:
    def fail(msg: str) -> ModelFileError:
        return ModelFileError(f"{where}: {msg}")

    if not isinstance(doc, dict):
        raise fail("expected a JSON object")
    if _nesting(doc) > MAX_NESTING:
        raise fail(f"nested too deeply (a model file nests at most {MAX_NESTING} levels of [ and {{)")
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
            term = parse_term(item["term"], axes)
        except (UnknownTermError, ValueError) as err:
            raise fail(f"terms[{i}]: {err}") from None
        coef = item.get("coef")
        if not _finite_number(coef):
            raise fail(f"terms[{i}] ({item['term']}): 'coef' must be a finite number, got {coef!r}")
        se = _optional_number(item.get("se"), f"terms[{i}] ({item['term']}): 'se'", fail, 0.0)
        p = _optional_number(item.get("p"), f"terms[{i}] ({item['term']}): 'p'", fail, 0.0, 1.0)
        terms.append(FittedTerm(term, float(coef), se, p))
    names = [ft.term.name for ft in terms]
    if len(set(names)) != len(names):
        raise fail(f"duplicate terms in {names}")
    training = _training_from_dict(doc.get("training"), fail)
    sections = {}
    for key in ("fit", "selection", "provenance"):
        value = doc.get(key)
        if value is not None and not isinstance(value, dict):
            raise fail(f"'{key}' must be an object, got {type(value).__name__}")
        sections[key] = dict(value or {})
    claimed = doc.get("id")
    if claimed is not None and not isinstance(claimed, str):
        raise fail(f"'id' must be a string, got {claimed!r}")
    covariance = None
    if doc.get("covariance") is not None:
        channels = list(dict.fromkeys(c for ft in terms for c in ft.term.channels))
        covariance = Covariance.from_dict(doc["covariance"], names, channels, fail)
    model = Model(terms=terms, training=training, id=claimed or "", covariance=covariance, **sections)
    declared = doc.get("channels")
    if declared is not None and (not isinstance(declared, list) or declared != list(model.channels)):
        raise fail(f"'channels' {declared} does not match the channels its terms read {list(model.channels)}")
    unranged = [c for c in model.channels if c not in training.channel_ranges]
    if unranged:
        raise fail(f"training ranges missing for channel(s) {', '.join(unranged)}")
    read_axes = sorted({a for ft in terms for a in ft.term.axes})
    unranged = [a for a in read_axes if a not in training.position_ranges]
    if unranged:
        raise fail(f"training ranges missing for axis/axes {', '.join(unranged)} (training.positions_um)")
    problem = _box_problem(model)
    if problem:
        raise fail(problem)
    if check_id:
        _check_id(model, claimed, where)
    return model


def _check_id(model: Model, claimed: Any, where: str) -> None:
    actual = model.content_id()
    if not claimed:
        raise ModelFileError(
            f"{where}: has no 'id'; a model's id is the hash of its content ({actual} for this one): "
            f"stamp it with `nanodrift restamp {where}`"
        )
    if claimed != actual:
        raise ModelFileError(
            f"{where}: its id {claimed!r} does not match its content (its terms, coefficients, standard "
            f"errors and training ranges give {actual!r}): the file was changed after it was made. If the "
            f"change is deliberate, re-stamp it: `nanodrift restamp {where}`; otherwise restore the file "
            "or fit the model again (`nanodrift fit`)"
        )


def _box_problem(model: Model) -> str:
    """Why the model's prediction is not finite somewhere in its training box ('' if it is).

    Every term reads x and at most a few channels, and its magnitude is largest at a corner of that
    sub-box (powers, products, channels and their lags are monotone in each variable), so each
    term is evaluated at the corners of (x range) x (its channels' ranges), and the sum of the
    largest magnitudes must be finite too.
    """
    tr = model.training
    total = 0.0
    largest = [_largest_feature(ft.term, tr) for ft in model.terms]
    with np.errstate(all="ignore"):
        for ft, feature in zip(model.terms, largest, strict=True):
            worst = abs(ft.coef) * feature
            if not math.isfinite(worst):
                box = ", ".join([f"x_um {tr.x_range[0]:g}..{tr.x_range[1]:g}"]
                                + [f"{c} {tr.channel_ranges[c][0]:g}..{tr.channel_ranges[c][1]:g}"
                                   for c in ft.term.channels])
                return (f"term {ft.term.name} (coef {ft.coef:g}) is not finite inside the training box "
                        f"({box}): this model cannot give a usable command")
            total += worst
    if not math.isfinite(total):
        return "the sum of the terms overflows inside the training box: this model cannot give a usable command"
    if model.covariance is not None:
        # f·C·f <= (Σ_i |f_i| sqrt(C_ii))² for a covariance (Cauchy-Schwarz): finite bound, finite sigma
        with np.errstate(all="ignore"):
            root = np.sum(np.asarray(largest) * np.sqrt(np.diag(model.covariance.matrix)))
            s = np.float64(model.covariance.residual_rms_um)
            bound = float(root * root + s * s)
            cv = model.covariance.curvature
            if cv is not None:
                lows = [tr.channel_ranges[c][0] for c in cv.channels]
                highs = [tr.channel_ranges[c][1] for c in cv.channels]
                ends = np.array([np.mean(lows), np.mean(highs)])
                allowance = cv.sd_um_per_c2 * np.max(cv.gap(ends))
                bound += float(allowance * allowance)
        if not math.isfinite(bound):
            return ("covariance: the uncertainty of the command overflows inside the training box: "
                    "this model cannot give a usable q_sigma_um")
    return ""


def _largest_feature(term: Term, tr: Training) -> float:
    """The largest magnitude of a term's feature over the corners of (x range) x (its channels' ranges)."""
    names = [*term.channels, *(position_key(a) for a in term.axes)]
    ranges = [tr.x_range, *(tr.channel_ranges[c] for c in term.channels),
              *(tr.position_ranges[a] for a in term.axes)]
    corners = np.array(list(itertools.product(*ranges)), dtype=np.float64)
    channels = {c: corners[:, 1 + i] for i, c in enumerate(names)}
    t = np.arange(corners.shape[0], dtype=np.float64)
    with np.errstate(all="ignore"):
        values = np.asarray(term.batch(t, corners[:, 0], channels), dtype=np.float64)
        return float(np.max(np.abs(values)))


def _training_from_dict(raw: Any, fail: Any) -> Training:
    if not isinstance(raw, dict):
        raise fail("'training' must be an object with x_um and channels ranges")

    def pair(value: Any, what: str) -> tuple[float, float]:
        if not (isinstance(value, list) and len(value) == 2 and all(_finite_number(v) for v in value)
                and value[0] <= value[1]):
            raise fail(f"training range of {what} must be [low, high], got {value!r}")
        return float(value[0]), float(value[1])

    channels = raw.get("channels") or {}
    if not isinstance(channels, dict):
        raise fail("training.channels must be an object {channel: [low, high]}")
    rows = raw.get("rows") or 0
    if not isinstance(rows, int) or isinstance(rows, bool) or rows < 0:
        raise fail(f"training.rows must be a whole number >= 0, got {rows!r}")
    t_span_s = _optional_number(raw.get("t_span_s"), "training.t_span_s", fail, 0.0)
    positions = raw.get("positions_um") or {}
    if not isinstance(positions, dict):
        raise fail("training.positions_um must be an object {axis: [low, high]}")
    return Training(
        x_range=pair(raw.get("x_um"), "x_um"),
        channel_ranges={str(c): pair(r, c) for c, r in channels.items()},
        rows=rows,
        t_span_s=0.0 if math.isnan(t_span_s) else t_span_s,
        position_ranges={str(a): pair(r, f"{a}_um") for a, r in positions.items()},
    )


def outside(values: Mapping[str, float], ranges: Mapping[str, tuple[float, float]]) -> list[str]:
    """The names in ``values`` whose value lies outside its range in ``ranges`` (a name without one is not judged)."""
    return [name for name, value in values.items()
            if name in ranges and not ranges[name][0] <= value <= ranges[name][1]]
