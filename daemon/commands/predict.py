"""``nanodrift predict --model M.json D.csv --out P.csv``: the command the model gives for each row.

Two columns are added per axis: ``q_pred_um`` (the command) and ``q_sigma_um`` (its standard uncertainty,
:meth:`nanodrift.model.model.Model.q_sigma`; the fit's residual RMS on every row for a model file
written before nanodrift stored the covariance); a multi-axis cell names them ``q_pred_<axis>_um`` and
``q_sigma_<axis>_um``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Mapping

import numpy as np

from nanodrift.calibration.dataset import DataError, Dataset, read_csv, write_csv
from nanodrift.errors import UserError, user_errors
from nanodrift.model.cell_model import CellModel, load_any_model, one_axis
from nanodrift.model.model import MissingChannelError, ModelFileError


def extrapolating_rows(model: CellModel, data: Dataset) -> tuple[int, dict[str, int]]:
    """Rows outside the training ranges, and per quantity (an axis or a channel) how many rows leave it."""
    values: Mapping[str, np.ndarray] = {**(data.positions or {"x": data.x}), **data.channels}
    ranges = {**model.position_ranges, **model.channel_ranges}
    outside = {name: (np.asarray(values[name]) < low) | (np.asarray(values[name]) > high)
               for name, (low, high) in ranges.items() if name in values}
    counts = {name: int(mask.sum()) for name, mask in outside.items() if mask.any()}
    return int(np.logical_or.reduce(list(outside.values())).sum()), counts


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, metavar="M.json", help="the model to apply")
    parser.add_argument("data", metavar="D.csv", help="data with t_s, x_um and the model's channels")
    parser.add_argument("--out", required=True, metavar="P.csv", help="D plus columns q_pred_um and q_sigma_um (µm)")


def main(args: argparse.Namespace) -> int:
    with user_errors(DataError, ModelFileError, MissingChannelError):
        given = load_any_model(args.model)
        data = read_csv(args.data)
        model = CellModel.of(given)
        if data.axes != model.axes:
            if not isinstance(given, CellModel):
                raise UserError(f"{args.model} is a one-axis model but {args.data} positions axes "
                                f"{', '.join(data.axes)}: give the multi-axis model fitted for this cell")
            kind = "a multi-axis file" if data.multi_axis else "a one-axis file"
            raise UserError(f"{args.data} positions axes {', '.join(data.axes)} ({kind}) but {args.model} serves "
                            f"axes {', '.join(model.axes)}")
        q_pred = model.predict(data)
        q_sigma = model.q_sigma(data)
    one = one_axis(model.axes)
    # a hand-made file with neither a covariance block nor fit.rmse_um gives no σ: no q_sigma column then
    sigma_known = all(model.models[a].covariance is not None or bool(np.isfinite(q_sigma[a]).all())
                      for a in model.axes)
    columns: dict[str, np.ndarray] = {}
    for axis in model.axes:
        _refuse_non_finite(args, model, data, axis, q_pred[axis], q_sigma[axis] if sigma_known else None)
        columns["q_pred_um" if one else f"q_pred_{axis}_um"] = q_pred[axis]
        if sigma_known:
            columns["q_sigma_um" if one else f"q_sigma_{axis}_um"] = q_sigma[axis]
    for name in ("q_pred_um", "q_sigma_um") if one else columns:
        data.extra.pop(name, None)
    write_csv(data, args.out, columns)
    rows, counts = extrapolating_rows(model, data)
    outside = (f"{rows} extrapolating (outside the training range: "
               + ", ".join(f"{name} in {n}" for name, n in counts.items()) + ")") if rows else "none extrapolating"
    if one:
        sigma = (f"q_sigma_um (median {np.median(q_sigma['x']) * 1e3:.0f} nm)" if sigma_known
                 else "no q_sigma_um (the model file has neither a covariance block nor fit.rmse_um)")
        print(f"predicted q_pred_um and {sigma} for {len(data)} rows with model {model.id} -> {args.out}; {outside}")
    else:
        sigmas = ", ".join(f"{a} {np.median(q_sigma[a]) * 1e3:.0f} nm" for a in model.axes)
        print(f"predicted q_pred_<axis>_um and q_sigma_<axis>_um (median {sigmas}) for axes {', '.join(model.axes)}, "
              f"{len(data)} rows with model {model.id} -> {args.out}; {outside}")
    return 0


def _refuse_non_finite(args: argparse.Namespace, model: CellModel, data: Dataset, axis: str, q_pred: np.ndarray,
                       q_sigma: np.ndarray | None) -> None:
    """Never write inf/nan: the project's own reader would refuse the file. The error names the first such row."""
    bad = np.flatnonzero(~np.isfinite(q_pred) | (~np.isfinite(q_sigma) if q_sigma is not None else False))
    if not bad.size:
        return
    i = int(bad[0])
    if one_axis(model.axes):
        values = ", ".join([f"x_um = {data.x[i]:g}"] + [f"{c} = {data.channels[c][i]:g}" for c in model.channels])
        what = "command" if not math.isfinite(q_pred[i]) else "uncertainty (q_sigma_um)"
        low, high = model.position_ranges["x"]
        raise UserError(f"{args.data}, row {i + 2}: the model gives no finite {what} for {values} ({bad.size} such "
                        f"row(s); trained on x_um {low:g}..{high:g}); nothing written to {args.out}")
    where = ", ".join(f"{a}_um = {data.positions[a][i]:g}" for a in model.axes)
    raise UserError(f"{args.data}, row {i + 2}: the model gives no finite command or uncertainty for axis "
                    f"{axis} at {where} ({bad.size} such row(s)); nothing written to {args.out}")
