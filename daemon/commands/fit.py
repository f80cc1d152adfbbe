"""``nanodrift fit D.csv [D2.csv ...] --out M.json``: stepwise identification from recorded data.

Several files (a calibration plus days of recorded operation) are fitted together, each a run of its
own (its own time, its own held-out blocks); the model's provenance lists every file with its SHA-256.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence
from typing import Any, SupportsFloat

from nanodrift.calibration.dataset import DataError, Dataset, common_channels, concat, read_runs
from nanodrift.errors import UserError, user_errors
from nanodrift.model.cell_model import CellModel, one_axis, save_cell_model
from nanodrift.model.describe import describe_cell_model
from nanodrift.model.equation import equation
from nanodrift.model.identify import DEFAULT_SELECTION, SELECTIONS, FitError, fit_cell
from nanodrift.model.model import Model
from nanodrift.model.provenance import stamp_data
from nanodrift.model.terms import MAX_POWER, Term, UnknownTermError, parse_term


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", metavar="D.csv", nargs="+",
                        help="recorded data (CSV: t_s, x_um, q_um, one column per channel); several files (a "
                             "calibration plus recorded operation) are fitted together, each a run of its own")
    parser.add_argument("--out", required=True, metavar="M.json", help="the model file to write")
    parser.add_argument("--order", default="auto", help="geometric order n1, or auto (held-out cycles)")
    parser.add_argument("--exclude", action="append", default=[], metavar="CH",
                        help="leave a channel out (repeatable)")
    parser.add_argument("--keep", action="append", default=[], metavar="TERM",
                        help="a term kept in the model whatever the stepwise says, e.g. --keep x^3 --keep x^2 "
                             "(a refit with days of records keeping the calibration's geometry); one-axis files")
    parser.add_argument("--no-squares", action="store_true",
                        help="eq. 3 as the paper wrote it: no channel's square (T2 - c)^2 among the candidates, "
                             "which fit otherwise offers for a channel the data spans by 1 degC or more")
    parser.add_argument("--penter", type=float, default=0.05, metavar="P",
                        help="stepwise: a term enters when its p-value is below P")
    parser.add_argument("--premove", type=float, default=0.10, metavar="P",
                        help="stepwise: a term leaves when its p-value is above P (>= --penter)")
    parser.add_argument("--selection", choices=SELECTIONS, default=DEFAULT_SELECTION,
                        help="stepwise tests: paper (default; MATLAB stepwisefit's iid partial F-tests, as the "
                             "paper), hac (Wald tests under the Newey-West covariance, which allows for the "
                             "residual's autocorrelation) or coherent (paper's tests, then channels opposing the "
                             "summed thermal sensitivity dropped). Reported SEs and p-values are HAC either way")
    parser.add_argument("--json", action="store_true",
                        help="print the summary as JSON (residuals in nm, keys ending _nm)")


def _order(text: str) -> int | str:
    if text == "auto":
        return "auto"
    try:
        value = int(text)
    except ValueError:
        raise UserError(f"--order must be 'auto' or a whole number >= 1, got {text!r}") from None
    if not 1 <= value <= MAX_POWER:
        raise UserError(f"--order must be 'auto' or between 1 and {MAX_POWER}, got {value}")
    return value


def _kept_terms(names: Sequence[str], channels: Sequence[str], exclude: Sequence[str]) -> list[Term]:
    """``--keep`` names as terms; a name no term has, or one reading a channel the fit does not use, is refused."""
    terms = []
    for name in names:
        try:
            term = parse_term(name)
        except (UnknownTermError, ValueError) as err:
            raise UserError(f"--keep {name}: {err}") from None
        unused = [c for c in term.channels if c not in channels or c in exclude]
        if unused:
            raise UserError(f"--keep {name}: reads channel {', '.join(unused)}, which this fit does not use "
                            f"(channels: {', '.join(c for c in channels if c not in exclude) or 'none'})")
        terms.append(term)
    return terms


def check_fit_channels(runs: Sequence[Dataset], exclude: Sequence[str]) -> None:
    """Every file has the first file's channels (or they are excluded); others' extra channels are noted."""
    first = runs[0]
    for ds in runs[1:]:
        missing = [c for c in first.channels if c not in ds.channels and c not in exclude]
        if missing:
            raise DataError(
                f"{ds.source}: lacks channel(s) {', '.join(missing)} that {first.source} has (its channels: "
                f"{', '.join(ds.channels) or 'none'}); give --exclude {' --exclude '.join(missing)} to fit without them"
            )
        extra = [c for c in ds.channels if c not in first.channels]
        if extra:
            print(f"nanodrift: note: {ds.source}: channel(s) {', '.join(extra)} not in {first.source}, left out",
                  file=sys.stderr)


def main(args: argparse.Namespace) -> int:
    paths = [str(p) for p in args.data]
    with user_errors(DataError, FitError, ValueError):
        runs = read_runs(paths)
        check_fit_channels(runs, args.exclude)
        channels = common_channels(runs)
        data = concat(runs, channels)
        # a channel excluded because some file lacks it is already out; one no file has is a typo (refused)
        exclude = [c for c in args.exclude if c in channels or not any(c in ds.channels for ds in runs)]
        files = [(p, len(ds)) for p, ds in zip(paths, runs, strict=True)]
        options: dict[str, Any] = {"order": _order(args.order), "exclude": exclude, "penter": args.penter,
                                   "premove": args.premove, "source": ", ".join(paths), "squares": not args.no_squares,
                                   "selection": args.selection}
        if data.multi_axis and args.keep:
            raise UserError("--keep is for one-axis files: a multi-axis file's axes choose their terms each")
        cell = fit_cell(data, keep=_kept_terms(args.keep, channels, exclude), **options).model
    for one in cell.models.values():
        one.selection["excluded"] = list(args.exclude)
    stamp_data(cell, files)
    save_cell_model(cell, args.out)
    print(json.dumps(cell_fit_summary(cell, args.out), indent=2) if args.json else describe_cell_model(cell, args.out))
    return 0


def cell_fit_summary(cell: CellModel, path: str) -> dict[str, Any]:
    """``fit --json``: the cell's id and, per axis, what :func:`fit_summary` gives for one (a cell of one axis:
    :func:`fit_summary` of its model)."""
    if one_axis(cell.axes):
        return fit_summary(cell.models["x"], path)
    axes = {axis: {**fit_summary(model, path), "equation": equation(model, lhs=f"q_{axis}")}  # the key keeps its place
            for axis, model in cell.models.items()}
    return {"model": cell.id, "model_out": str(path), "axes": axes}


def _nm(value_um: SupportsFloat | None) -> float | None:
    return None if value_um is None else float(value_um) * 1000.0


def fit_summary(model: Model, path: str) -> dict[str, Any]:
    """Everything :func:`describe_model` prints, as JSON.

    One unit per quantity: residuals and RMS errors are in nm, always in keys ending ``_nm`` (also
    inside ``fit``, the model file's fit statistics, whose ``_um`` figures are given here in nm);
    coefficients are in µm of command per unit of their term (x in µm, channels in °C).
    """
    sel, stats = model.selection, model.fit
    scores = sel.get("order_holdout_rms_um") or {}
    dropped = sel.get("not_selected") or {}
    return {
        "model": model.id,
        "model_out": str(path),
        "equation": equation(model),
        "order": sel.get("order"),
        "order_choice": sel.get("order_choice", "auto (held-out cycles)" if scores else "fixed"),
        "order_holdout_rms_nm": {k: _nm(v) for k, v in scores.items()},
        "terms": [{"term": ft.term.name, "coef": ft.coef, "se": ft.se, "p": ft.p} for ft in model.terms],
        "not_selected": [
            {"term": name, "coef_if_added": v.get("coef_if_added"), "p_if_added": v.get("p_if_added")}
            for name, v in dropped.items()
        ],
        "excluded": sel.get("excluded", []),
        "penter": sel.get("penter"),
        "premove": sel.get("premove"),
        "selection": sel.get("mode", "paper"),
        "se_method": stats.get("se_method", "iid (a model file from before HAC standard errors)"),
        "thermal_sensitivity": stats.get("thermal_sensitivity"),
        "rows": stats.get("rows"),
        "residual_rms_nm": stats.get("residual_rms_nm"),
        "rmse_nm": _nm(stats.get("rmse_um")),
        "holdout_rms_nm": _nm(stats.get("holdout_rms_um")),
        "r2": stats.get("r2"),
        "dof": stats.get("dof"),
        "fit": {(k[:-3] + "_nm" if k.endswith("_um") else k): (_nm(v) if k.endswith("_um") else v)
                for k, v in stats.items()},  # every _um figure (an RMS) in nm, in their order
        "training": model.to_dict()["training"],
        "data_files": model.provenance.get("data_files", []),
    }
