"""What a model file records about how it was made (``provenance``): never part of its id.

One function stamps the data a model was made from (:func:`stamp_data`), so ``fit``, ``discover`` and
``calibrate`` (and the demo's calibration) record it alike: the first file as ``data_file`` with its
SHA-256 as ``data_sha256``, and every file with its SHA-256 and rows as ``data_files``.
"""

from __future__ import annotations

import datetime as dt
import importlib.metadata
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING

from nanodrift.atomic import file_sha256
from nanodrift.model.model import Model

if TYPE_CHECKING:
    from nanodrift.model.cell_model import CellModel


def version() -> str:
    """The installed distribution's version (also ``nanodrift_build_info``'s)."""
    try:
        return importlib.metadata.version("nanodrift")
    except importlib.metadata.PackageNotFoundError:  # a source tree that was never installed
        return "0+unknown"


def software() -> str:
    """What a model file records as the software that fitted it: ``"nanodrift <version>"``.

    Provenance only: never part of the model's id (the same terms and coefficients are the same model).
    """
    return f"nanodrift {version()}"


def created_now() -> str:
    """When a model is made: UTC, to the second."""
    return dt.datetime.now(dt.UTC).isoformat(timespec="seconds")


def stamp_data(model: Model | CellModel, files: Sequence[tuple[str | Path, int]]) -> None:
    """Record the data files ``model`` was made from, ``(path, rows)`` each, the first the main one (a
    calibration; recorded operation after it): ``data_file``, ``data_sha256`` and ``data_files``.

    A model of several axes: in every axis' model, and the cell's provenance is the first axis'."""
    if not isinstance(model, Model):
        for axis_model in model.models.values():
            stamp_data(axis_model, files)
        model.provenance = dict(model.models[model.axes[0]].provenance)
        return
    if not files:
        raise ValueError("a model is made from at least one data file")
    records = [{"path": str(path), "sha256": file_sha256(path), "rows": rows} for path, rows in files]
    model.provenance.update(data_file=records[0]["path"], data_sha256=records[0]["sha256"], data_files=records)
