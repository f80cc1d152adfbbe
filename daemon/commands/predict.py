"""``nanodrift predict --model M.json D.csv --out P.csv``: the command the model gives for each row.

Two columns are added: ``q_pred_um`` (the command) and ``q_sigma_um`` (its standard uncertainty,
:meth:`nanodrift.model.model.Model.q_sigma`; the fit's residual RMS on every row for a model file
written before nanodrift stored the covariance).
"""

from __future__ import annotations

import argparse
import math

import numpy as np

from nanodrift.calibration.dataset import DataError, Dataset, read_csv, write_csv
from nanodrift.errors import UserError
from nanodrift.model.cell_model import CellModel, load_any_model
from nanodrift.model.model import MissingChannelError, Model, ModelFileError
from nanodrift.model.series import Series


def extrapolating_rows(model: Model, data: Series) -> tuple[int, dict[str, int]]:
    """Rows outside the training ranges, and per quantity (``x`` or a channel) how many rows leave it."""
    x = np.asarray(data.x, dtype=np.float64)
    outside = {"x": (x < model.training.x_range[0]) | (x > model.training.x_range[1])}
    for channel, (low, high) in model.training.channel_ranges.items():
        if channel in data.channels:
            values = np.asarray(data.channels[channel], dtype=np.float64)
            outside[channel] = (values < low) | (values > high)
    counts = {name: int(mask.sum()) for name, mask in outside.items() if mask.any()}
    rows = int(np.logical_or.reduce(list(outside.values())).sum())
    return rows, counts


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", required=True, metavar="M.json", help="the model to apply")
    parser.add_argument("data", metavar="D.csv", help="data with t_s, x_um and the model's channels")
    parser.add_argument("--out", required=True, metavar="P.csv", help="D plus columns q_pred_um and q_sigma_um (µm)")


def main(args: argparse.Namespace) -> int:
    try:
        any_model = load_any_model(args.model)
        data = read_csv(args.data)
        if isinstance(any_model, CellModel) or data.multi_axis:
            return _predict_cell(args, any_model, data)
        model = any_model
        q_pred = model.predict(data)
        q_sigma = model.q_sigma(data)
    except (DataError, ModelFileError, MissingChannelError) as err:
        raise UserError(str(err)) from None
    columns = {"q_pred_um": q_pred, "q_sigma_um": q_sigma}
    sigma_known = model.covariance is not None or bool(np.isfinite(q_sigma).all())
    if not sigma_known:  # a hand-made file with neither a covariance block nor fit.rmse_um
        del columns["q_sigma_um"]
    bad = np.flatnonzero(~np.isfinite(q_pred) | (~np.isfinite(q_sigma) if sigma_known else False))
    if bad.size:  # never write inf/nan: the project's own reader would refuse the file
        i = int(bad[0])
        values = ", ".join([f"x_um = {data.x[i]:g}"] + [f"{c} = {data.channels[c][i]:g}" for c in model.channels])
        what = "command" if not math.isfinite(q_pred[i]) else "uncertainty (q_sigma_um)"
        raise UserError(
            f"{args.data}, row {i + 2}: the model gives no finite {what} for {values} "
            f"({bad.size} such row(s); trained on x_um {model.training.x_range[0]:g}..{model.training.x_range[1]:g}); "
            f"nothing written to {args.out}"
        )
    for name in ("q_pred_um", "q_sigma_um"):
        data.extra.pop(name, None)
    write_csv(data, args.out, columns)
    rows, counts = extrapolating_rows(model, data)
    outside = (f"{rows} extrapolating (outside the training range: "
               + ", ".join(f"{name} in {n}" for name, n in counts.items()) + ")") if rows else "none extrapolating"
    sigma = (f"q_sigma_um (median {np.median(q_sigma) * 1e3:.0f} nm)" if sigma_known
             else "no q_sigma_um (the model file has neither a covariance block nor fit.rmse_um)")
    print(f"predicted q_pred_um and {sigma} for {len(q_pred)} rows with model {model.id} -> {args.out}; {outside}")
    return 0


def _predict_cell(args: argparse.Namespace, model: Model | CellModel, data: Dataset) -> int:
    """A multi-axis model on a multi-axis file: ``q_pred_<axis>_um`` and ``q_sigma_<axis>_um`` per axis."""
    if not isinstance(model, CellModel):
        raise UserError(f"{args.model} is a one-axis model but {args.data} positions axes {', '.join(data.axes)}: "
                        "give the multi-axis model fitted for this cell")
    if data.axes != model.axes:
        kind = "a multi-axis file" if data.multi_axis else "a one-axis file"
        raise UserError(f"{args.data} positions axes {', '.join(data.axes)} ({kind}) but {args.model} serves axes "
                        f"{', '.join(model.axes)}")
    try:
        q_pred = model.predict(data)
        q_sigma = model.q_sigma(data)
    except MissingChannelError as err:
        raise UserError(str(err)) from None
    columns: dict[str, np.ndarray] = {}
    for axis in model.axes:
        bad = np.flatnonzero(~np.isfinite(q_pred[axis]) | ~np.isfinite(q_sigma[axis]))
        if bad.size:  # never write inf/nan: the project's own reader would refuse the file
            i = int(bad[0])
            where = ", ".join(f"{a}_um = {data.positions[a][i]:g}" for a in model.axes)
            raise UserError(f"{args.data}, row {i + 2}: the model gives no finite command or uncertainty for axis "
                            f"{axis} at {where} ({bad.size} such row(s)); nothing written to {args.out}")
        columns[f"q_pred_{axis}_um"] = q_pred[axis]
        columns[f"q_sigma_{axis}_um"] = q_sigma[axis]
    for name in columns:
        data.extra.pop(name, None)
    write_csv(data, args.out, columns)
    outside = np.zeros(len(data), dtype=bool)
    counts: dict[str, int] = {}
    for axis, (low, high) in model.position_ranges.items():
        mask = (data.positions[axis] < low) | (data.positions[axis] > high)
        counts[axis] = int(mask.sum())
        outside |= mask
    for channel, (low, high) in model.channel_ranges.items():
        if channel in data.channels:
            mask = (data.channels[channel] < low) | (data.channels[channel] > high)
            counts[channel] = int(mask.sum())
            outside |= mask
    counts = {k: v for k, v in counts.items() if v}
    rows = int(outside.sum())
    listed = ", ".join(f"{name} in {n}" for name, n in counts.items())
    extrapolating = f"{rows} extrapolating (outside the training range: {listed})" if rows else "none extrapolating"
    sigmas = ", ".join(f"{a} {np.median(q_sigma[a]) * 1e3:.0f} nm" for a in model.axes)
    print(f"predicted q_pred_<axis>_um and q_sigma_<axis>_um (median {sigmas}) for axes {', '.join(model.axes)}, "
          f"{len(data)} rows with model {model.id} -> {args.out}; {extrapolating}")
    return 0
