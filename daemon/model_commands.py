"""``nanodrift fit`` and ``nanodrift predict``: identification and prediction from recorded files."""

from __future__ import annotations

import argparse
import hashlib
import json
from pathlib import Path
from typing import Any

from daemon.calibration.dataset import DataError, read_csv, write_csv
from daemon.errors import UserError
from daemon.model.identify import FitError, fit
from daemon.model.model import MissingChannelError, Model, ModelFileError, load_model, save_model


def file_sha256(path: str | Path) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        for block in iter(lambda: handle.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()


def _order(text: str) -> int | str:
    if text == "auto":
        return "auto"
    try:
        value = int(text)
    except ValueError:
        raise UserError(f"--order must be 'auto' or a whole number >= 1, got {text!r}") from None
    if value < 1:
        raise UserError(f"--order must be >= 1, got {value}")
    return value


def fit_command(args: argparse.Namespace) -> int:
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


def fit_summary(model: Model, path: str) -> dict[str, Any]:
    return {
        "model": model.id,
        "model_out": str(path),
        "order": model.selection.get("order"),
        "order_holdout_rms_um": model.selection.get("order_holdout_rms_um", {}),
        "terms": [{"term": ft.term.name, "coef": ft.coef, "se": ft.se, "p": ft.p} for ft in model.terms],
        "excluded": model.selection.get("excluded", []),
        "fit": model.fit,
        "training": model.to_dict()["training"],
    }


def describe_model(model: Model, path: str | None = None) -> str:
    """The human summary an operator reads: order, terms, residual, ranges."""
    sel, fit_stats = model.selection, model.fit
    lines = [f"model {model.id}" + (f" -> {path}" if path else "")]
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
    tr = model.training
    lines.append(f"trained on x {tr.x_range[0]:.1f}..{tr.x_range[1]:.1f} um")
    for ch, (lo, hi) in tr.channel_ranges.items():
        lines.append(f"  {ch}: {lo:.3f}..{hi:.3f} degC")
    return "\n".join(lines)


def predict_command(args: argparse.Namespace) -> int:
    try:
        model = load_model(args.model)
        data = read_csv(args.data)
        q_pred = model.predict(data)
    except (DataError, ModelFileError, MissingChannelError) as err:
        raise UserError(str(err)) from None
    if "q_pred_um" in data.extra:
        del data.extra["q_pred_um"]
    write_csv(data, args.out, {"q_pred_um": q_pred})
    return 0
