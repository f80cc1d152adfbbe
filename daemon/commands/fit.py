"""``nanodrift fit D.csv --out M.json``: stepwise identification from recorded data."""

from __future__ import annotations

import argparse
import json
from typing import Any

from daemon.atomic import file_sha256
from daemon.calibration.dataset import DataError, read_csv
from daemon.errors import UserError
from daemon.model.equation import equation
from daemon.model.identify import FitError, fit
from daemon.model.model import Model, save_model
from daemon.model.terms import MAX_POWER


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


def main(args: argparse.Namespace) -> int:
    try:
        data = read_csv(args.data)
        result = fit(
            data, order=_order(args.order), exclude=args.exclude, penter=args.penter, premove=args.premove,
            source=str(args.data),
        )
    except (DataError, FitError, ValueError) as err:
        raise UserError(str(err)) from None
    model = result.model
    model.provenance["data_sha256"] = file_sha256(args.data)
    model.id = model.content_id()
    save_model(model, args.out)
    if args.json:
        print(json.dumps(fit_summary(model, args.out), indent=2))
    else:
        print(describe_model(model, args.out))
    return 0


def _nm(value_um: object) -> float | None:
    return None if value_um is None else float(value_um) * 1000.0  # type: ignore[arg-type]


def fit_summary(model: Model, path: str) -> dict[str, Any]:
    """Everything :func:`describe_model` prints, as JSON.

    Residuals and RMS errors are in nm, always in keys ending ``_nm``; coefficients are in µm of
    command per unit of their term (x in µm, channels in °C). ``order_holdout_rms_um`` and ``fit``
    (``rmse_um`` beside ``residual_rms_nm``) are kept as they were for scripts that read them.
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
        "order_holdout_rms_um": scores,
        "terms": [{"term": ft.term.name, "coef": ft.coef, "se": ft.se, "p": ft.p} for ft in model.terms],
        "not_selected": [
            {"term": name, "coef_if_added": v.get("coef_if_added"), "p_if_added": v.get("p_if_added")}
            for name, v in dropped.items()
        ],
        "excluded": sel.get("excluded", []),
        "penter": sel.get("penter"),
        "premove": sel.get("premove"),
        "rows": stats.get("rows"),
        "residual_rms_nm": stats.get("residual_rms_nm"),
        "rmse_nm": _nm(stats.get("rmse_um")),
        "holdout_rms_nm": _nm(stats.get("holdout_rms_um")),
        "r2": stats.get("r2"),
        "dof": stats.get("dof"),
        "fit": stats,
        "training": model.to_dict()["training"],
    }


def describe_model(model: Model, path: str | None = None) -> str:
    """The human summary an operator reads: order, terms, residual, ranges."""
    sel, fit_stats = model.selection, model.fit
    lines = [f"model {model.id}" + (f" -> {path}" if path else ""), equation(model)]
    scores = sel.get("order_holdout_rms_um") or {}
    if scores:
        tried = ", ".join(f"n1={k}: {float(v) * 1000:.1f} nm" for k, v in scores.items())
        lines.append(f"geometric order n1 = {sel.get('order')} (chosen on held-out cycles; {tried})")
    elif sel.get("order"):
        lines.append(f"geometric order n1 = {sel.get('order')} (fixed)")
    if sel.get("excluded"):
        lines.append(f"excluded channels: {', '.join(sel['excluded'])}")
    lines.append(f"{'term':>16} {'coef':>14} {'SE':>11} {'p':>9}")
    for ft in model.terms:
        lines.append(f"{ft.term.name:>16} {ft.coef:>14.6g} {ft.se:>11.3g} {ft.p:>9.2g}")
    dropped = sel.get("not_selected") or {}
    if dropped:
        lines.append("not selected: " + ", ".join(
            f"{name} (p if added {v['p_if_added']:.2g})" if v.get("p_if_added") is not None else name
            for name, v in dropped.items()
        ))
    if "residual_rms_nm" in fit_stats:
        lines.append(f"residual RMS {fit_stats['residual_rms_nm']:.1f} nm over {fit_stats.get('rows')} rows")
    lines.extend(training_lines(model))
    return "\n".join(lines)


def training_lines(model: Model) -> list[str]:
    """The training ranges, in µm and °C: outside them the model extrapolates."""
    tr = model.training
    lines = [f"trained on x {_tenths(tr.x_range[0])}..{_tenths(tr.x_range[1])} µm"]
    lines.extend(f"  {ch}: {lo:.3f}..{hi:.3f} °C" for ch, (lo, hi) in tr.channel_ranges.items())
    return lines


def _tenths(value: float) -> str:
    text = f"{value:.1f}"
    return "0.0" if text == "-0.0" else text  # a measured -0.02 µm is the 0 µm point, not "-0.0"
