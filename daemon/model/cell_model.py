"""A cell's model: one :class:`Model` per axis, each over every axis' position, in one file.

An XY or XYZ stage is one cell: the command of each axis depends on where the others are
(crosstalk, non-orthogonality, coupled bending: :mod:`nanodrift.model.axis_terms`), so each axis has
its own term list, chosen by the same stepwise selection, and reads the positions of all axes.
Each axis' model is an ordinary :class:`Model` (its covariance, ``q_sigma``, stateful terms and file
checks are the one-axis ones); this class only keeps them together under one id and one file.

File layout (``"format": "nanodrift-model/1"`` with ``"axes"``)::

    {"format", "id", "axes": ["x", "y"], "channels": [...],
     "training": {"positions_um": {"x": [lo, hi], "y": [lo, hi]}},
     "models": {"x": <a one-axis model document>, "y": <...>}, "provenance": {...}}

A one-axis file has no ``axes`` and loads as a :class:`Model`, exactly as before
(:func:`load_any_model` reads either). The cell's id hashes the axes and every axis model's id.
A cell of one axis (``CellModel.of(model)``) is that file's model: its id and its document are the
one-axis model's, so code over a cell's axes serves one axis or several the same way.
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from nanodrift.atomic import atomic_write_text
from nanodrift.model.model import FORMAT, Evaluator, Model, ModelFileError, outside, read_model_doc
from nanodrift.model.series import Series

#: letters an axis may take: not q (``q_um`` is the one-axis command column)
AXIS_LETTERS = "abcdefghijklmnoprstuvwxyz"
#: the axes of a cell of one axis, whose model file is the one-axis document
ONE_AXIS = ("x",)


def one_axis(axes: Iterable[str]) -> bool:
    """A one-axis cell's axes (a config without ``[[axes]]``; a cell of several has two at least): the one test
    for the shapes only such a cell keeps, at the edges (scalar payloads, its log lines, its model file)."""
    return tuple(axes) == ONE_AXIS


@dataclass
class CellModel:
    """One model per axis of a multi-axis cell, applied together."""

    axes: tuple[str, ...]
    models: dict[str, Model]
    provenance: dict[str, Any] = field(default_factory=dict)
    id: str = ""

    def __post_init__(self) -> None:
        if not self.axes or tuple(self.models) != self.axes or (len(self.axes) == 1 and self.axes != ONE_AXIS):
            raise ValueError(f"a cell model needs a model per axis in order (one axis: x), got axes {self.axes} and "
                             f"models for {tuple(self.models)}")
        if not self.id:
            self.id = self.content_id()

    @classmethod
    def of(cls, model: Model | CellModel) -> CellModel:
        """``model`` as a cell's: a one-axis :class:`Model` is the model of a cell of one axis, ``x``."""
        if isinstance(model, CellModel):
            return model
        return cls(ONE_AXIS, {"x": model}, model.provenance, model.id)

    def content_id(self) -> str:
        """Hash of the axes and every axis model's content id (what decides every command); one axis: that
        axis model's own id (the one-axis file's)."""
        if one_axis(self.axes):
            return self.models["x"].content_id()
        content = {"format": FORMAT, "axes": list(self.axes),
                   "models": {a: self.models[a].content_id() for a in self.axes}}
        text = json.dumps(content, separators=(",", ":"), sort_keys=True)
        return "m-" + hashlib.sha256(text.encode()).hexdigest()[:12]

    @property
    def channels(self) -> tuple[str, ...]:
        """Every temperature channel some axis' model reads, in first-use order."""
        return tuple(dict.fromkeys(c for a in self.axes for c in self.models[a].channels))

    @property
    def position_ranges(self) -> dict[str, tuple[float, float]]:
        """The training range of every axis' position."""
        first = self.models[self.axes[0]].training
        return {a: (first.x_range if a == "x" else first.position_ranges[a]) for a in self.axes}

    @property
    def channel_ranges(self) -> dict[str, tuple[float, float]]:
        return {c: r for a in self.axes for c, r in self.models[a].training.channel_ranges.items()}

    def predict(self, data: Series) -> dict[str, np.ndarray]:
        """The command per axis for every row (``data``: a multi-axis series)."""
        return {a: self.models[a].predict(data) for a in self.axes}

    def q_sigma(self, data: Series) -> dict[str, np.ndarray]:
        return {a: self.models[a].q_sigma(data) for a in self.axes}

    def out_of_range(self, positions: Mapping[str, float] | None = None,
                     temps: Mapping[str, float] | None = None) -> list[str]:
        """Axis names and channels whose value lies outside what the models were trained on."""
        return outside(positions or {}, self.position_ranges) + outside(temps or {}, self.channel_ranges)

    def evaluators(self) -> dict[str, Evaluator]:
        """Every axis' :class:`Evaluator`; a target reaches them all through :func:`aim`."""
        return {a: self.models[a].evaluator() for a in self.axes}

    def to_dict(self) -> dict[str, Any]:
        """The model file: one axis, the one-axis document (no ``axes``); several, the layout above."""
        if one_axis(self.axes):
            return self.models["x"].to_dict()
        return {
            "format": FORMAT,
            "id": self.id,
            "axes": list(self.axes),
            "channels": list(self.channels),
            "training": {"positions_um": {a: list(r) for a, r in self.position_ranges.items()}},
            "models": {a: self.models[a].to_dict() for a in self.axes},
            "provenance": self.provenance,
        }

    @classmethod
    def from_dict(cls, doc: Any, where: str = "model", *, check_id: bool = True) -> CellModel:
        return _cell_model_from_dict(doc, where, check_id=check_id)


def save_cell_model(model: CellModel, path: str | os.PathLike[str]) -> None:
    """Write the file atomically, every axis model and the cell stamped with their content's id (a cell of one
    axis: the one-axis file, byte for byte what :func:`save_model` writes)."""
    for m in model.models.values():
        m.id = m.content_id()
    model.id = model.content_id()
    atomic_write_text(path, json.dumps(model.to_dict(), indent=2, allow_nan=False) + "\n")


def load_any_model(path: str | os.PathLike[str], *, check_id: bool = True) -> Model | CellModel:
    """A one-axis model file as a :class:`Model`, a multi-axis one (``"axes"``) as a :class:`CellModel`."""
    path = Path(path)
    doc = read_model_doc(path)
    if isinstance(doc, dict) and "axes" in doc:
        return _cell_model_from_dict(doc, str(path), check_id=check_id)
    return Model.from_dict(doc, str(path), check_id=check_id)


def _cell_model_from_dict(doc: Any, where: str, *, check_id: bool = True) -> CellModel:
    def fail(msg: str) -> ModelFileError:
        return ModelFileError(f"{where}: {msg}")

    def stale(what: str, claimed: Any, actual: str) -> ModelFileError:
        return fail(f"{what}its id {claimed!r} does not match its content ({actual!r}): the file was changed after "
                    f"it was made; if deliberately, re-stamp it: `nanodrift restamp {where}`")

    if not isinstance(doc, dict):
        raise fail("expected a JSON object")
    if doc.get("format") != FORMAT:
        raise fail(f"format is {doc.get('format')!r}, expected {FORMAT!r}")
    axes = doc.get("axes")
    if (not isinstance(axes, list) or len(axes) < 2 or len(set(axes)) != len(axes)
            or not all(isinstance(a, str) and len(a) == 1 and a in AXIS_LETTERS for a in axes) or "x" not in axes):
        raise fail(f"'axes' must list 2 or more distinct lowercase letters including x, got {axes!r}")
    raw_models = doc.get("models")
    if not isinstance(raw_models, dict) or sorted(raw_models) != sorted(axes):
        raise fail(f"'models' must hold one model per axis ({', '.join(axes)}), got "
                   f"{sorted(raw_models) if isinstance(raw_models, dict) else type(raw_models).__name__}")
    cell_axes = tuple(axes)
    models = {a: Model.from_dict(raw_models[a], f"{where}: models.{a}", check_id=False, axes=cell_axes)
              for a in cell_axes}
    for a, m in models.items():
        if check_id and raw_models[a].get("id") != m.content_id():
            raise stale(f"models.{a}: ", raw_models[a].get("id"), m.content_id())
    for a, m in models.items():
        missing = [b for b in cell_axes if b != "x" and b not in m.training.position_ranges]
        if missing:
            raise fail(f"models.{a}: training ranges missing for axis/axes {', '.join(missing)} "
                       "(training.positions_um)")
    provenance = doc.get("provenance") or {}
    if not isinstance(provenance, dict):
        raise fail(f"'provenance' must be an object, got {type(provenance).__name__}")
    claimed = doc.get("id")
    if claimed is not None and not isinstance(claimed, str):
        raise fail(f"'id' must be a string, got {claimed!r}")
    model = CellModel(cell_axes, models, dict(provenance), claimed or "")
    if check_id and claimed != model.content_id():
        raise stale("", claimed, model.content_id())
    return model
