"""nanodrift: keeps a piezo nanopositioning stage accurate while the room's temperature drifts.

What a lab script imports (README, *Python API*)::

    from nanodrift import Client, Refused, MoveEnded     # the Zenoh client of a running daemon
    model = nanodrift.load_model("model.json")          # offline: a model file, one axis or several
    data = nanodrift.read_csv("run.csv")                 # the data contract; nanodrift.write_csv(data, path)

Every name is loaded on first use (PEP 562 ``__getattr__``): ``import nanodrift`` and
``import nanodrift.model...`` load neither zenoh nor numpy, so the CLI, the pure core and the daemon's
own imports pay only for what they use.
"""

from __future__ import annotations

import os
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from nanodrift.calibration.dataset import Dataset
    from nanodrift.client import Client, Command, MoveEnded, Refused
    from nanodrift.model.cell_model import CellModel
    from nanodrift.model.model import Model

__all__ = ["Client", "Command", "Dataset", "MoveEnded", "Refused", "load_model", "read_csv", "write_csv"]


def __getattr__(name: str) -> Any:
    """The client's names from :mod:`nanodrift.client`, the offline helpers from the pure core, on first use."""
    if name in ("Client", "Command", "MoveEnded", "Refused"):
        import nanodrift.client as client_module

        return getattr(client_module, name)
    if name in ("Dataset", "read_csv", "write_csv"):
        import nanodrift.calibration.dataset as dataset_module

        return getattr(dataset_module, name)
    raise AttributeError(f"module 'nanodrift' has no attribute {name!r}")


def load_model(path: str | os.PathLike[str]) -> Model | CellModel:
    """The model file at ``path``: a one-axis file as a :class:`nanodrift.model.model.Model`, a file of several
    axes as a :class:`nanodrift.model.cell_model.CellModel`. Both have ``predict(data)`` (the command for
    every row of a :class:`Dataset` from :func:`read_csv`: an array, or one per axis) and ``q_sigma(data)``
    (its standard uncertainty), and ``evaluator()`` / ``evaluators()`` (the daemon's sample-by-sample
    evaluation: a :class:`nanodrift.model.model.Evaluator` per axis). A file that does not follow the model
    format is refused with a :class:`nanodrift.model.model.ModelFileError`."""
    from nanodrift.model.cell_model import load_any_model

    return load_any_model(path)
