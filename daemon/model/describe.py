"""A fitted model as an operator reads it: what ``fit`` and ``calibrate`` print (one axis or a cell)."""

from __future__ import annotations

from nanodrift.model.cell_model import CellModel, one_axis
from nanodrift.model.equation import equation, training_lines
from nanodrift.model.model import Model


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
    if sel.get("forced"):
        lines.append(f"kept whatever the stepwise says (--keep): {', '.join(sel['forced'])}")
    if sel.get("mode"):
        lines.append(f"selection: {sel['mode']}: {sel.get('test', '')}")
    lines.append(f"SE and p: {fit_stats.get('se_method', 'iid (a model file from before HAC standard errors)')}")
    lines.append(f"{'term':>16} {'coef':>14} {'SE':>11} {'p':>9}")
    lines += [f"{ft.term.name:>16} {ft.coef:>14.6g} {ft.se:>11.3g} {ft.p:>9.2g}" for ft in model.terms]
    sensitivity = fit_stats.get("thermal_sensitivity")
    if sensitivity and sensitivity.get("channels"):
        lines.append(f"thermal sensitivity (a common change of {', '.join(sensitivity['channels'])}): "
                     f"{sensitivity['um_per_c']:.4g} ± {sensitivity['se_um_per_c']:.2g} µm/°C (SE); what the data "
                     "identifies where it cannot separate the channels")
    if sel.get("opposing_dropped"):
        lines.append(f"dropped as opposing the summed sensitivity: {', '.join(sel['opposing_dropped'])}")
    dropped = sel.get("not_selected") or {}
    if dropped:
        lines.append("not selected: " + ", ".join(
            f"{name} (p if added {v['p_if_added']:.2g})" if v.get("p_if_added") is not None else name
            for name, v in dropped.items()
        ))
    if "residual_rms_nm" in fit_stats:
        lines.append(f"residual RMS {fit_stats['residual_rms_nm']:.1f} nm over {fit_stats.get('rows')} rows")
    files = model.provenance.get("data_files") or []
    if len(files) > 1:
        lines.append(f"from {len(files)} runs, each with its own time and held-out blocks: "
                     + ", ".join(f"{f['path']} ({f['rows']} rows)" for f in files))
    lines.extend(training_lines(model))
    return "\n".join(lines)


def describe_cell_model(cell: CellModel, path: str | None = None) -> str:
    """Per axis, the one-axis summary with that axis' command on the left (``q_x = ...``); a cell of one axis:
    its model's own summary."""
    if one_axis(cell.axes):
        return describe_model(cell.models["x"], path)
    ranges = ", ".join(f"{a} {lo:.1f}..{hi:.1f} µm" for a, (lo, hi) in cell.position_ranges.items())
    lines = [f"model {cell.id} (axes {', '.join(cell.axes)})" + (f" -> {path}" if path else ""),
             f"trained on positions {ranges}"]
    for axis, model in cell.models.items():
        own = [line for line in describe_model(model).split("\n")[2:] if not line.startswith("trained on x ")]
        lines += ["", f"axis {axis} (model {model.id}):", equation(model, lhs=f"q_{axis}"), *own]
    return "\n".join(lines)
