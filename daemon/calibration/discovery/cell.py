"""Discovery on a cell: the one-axis workflow per axis, over every axis' position (a cell of one axis: x).

Each axis' model is tested against that axis' commands (``Dataset.axis_view``): its residual is
checked against every axis' position as well as the temperatures and the motion, and the catalogue
adds what only a multi-axis cell shows (``crosstalk``, ``coupled_bending``) to the usual effects of
the axis' own motion (``dir(y)``, ``creep(y, τ s)``, ``y*T1`` for axis y). Each axis clears the same
bar as a one-axis cell; axes where nothing is named keep their model unchanged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.discovery.settings import DEFAULT_SETTINGS, Settings
from nanodrift.calibration.discovery.workflow import DiscoveryError, DiscoveryResult, discover
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Model


@dataclass
class CellDiscoveryResult:
    """A cell's discovery (one axis or several): per axis, the workflow's result; ``model``: the cell with every
    axis' extended (or given) model."""

    axes: dict[str, DiscoveryResult]
    model: CellModel
    given: CellModel

    @property
    def found(self) -> bool:
        return any(r.found for r in self.axes.values())

    def to_dict(self, model_out: str | None = None) -> dict[str, Any]:
        """``{"axes": {axis: the one-axis document}, "final": {"model": id}, "model_out"}``."""
        axes = {axis: {k: v for k, v in r.to_dict(None).items() if k != "model_out"} for axis, r in self.axes.items()}
        final_id = self.model.id if self.found else self.given.id
        return {"axes": axes, "final": {"model": final_id}, "model_out": model_out}


def discover_cell(data: Dataset, given: Model | CellModel, settings: Settings = DEFAULT_SETTINGS,
                  fresh: Dataset | None = None) -> CellDiscoveryResult:
    """:func:`discover` for every axis of ``given`` (a one-axis model: axis x) on the run ``data`` of the same axes
    (``fresh``: see there)."""
    model = CellModel.of(given)
    for run in (data, fresh):
        if run is not None and run.axes != model.axes:
            raise DiscoveryError(f"{run.source} positions axes {', '.join(run.axes)}, the model serves "
                                 f"{', '.join(model.axes)}")
    results = {axis: discover(data.axis_view(axis), model.models[axis], settings,
                              fresh=fresh.axis_view(axis) if fresh is not None else None)
               for axis in model.axes}
    extended = CellModel(model.axes, {a: r.model for a, r in results.items()}, dict(model.provenance))
    return CellDiscoveryResult(results, extended, model)
