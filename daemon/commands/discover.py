"""``nanodrift discover D.csv [D2.csv ...] --model M.json --out M2.json [--fresh F.csv] [--report DIR] [--json]``.

Read, discover, write.

Several files are runs of their own: stateful terms restart and held-out blocks stay within each
file (:mod:`nanodrift.model.segments`); every file must hold the model's channels, and channels that
only some files have are left out. The extended model's provenance lists every file's SHA-256.

When nothing clears the bar no model is written (an "extended" model with the given terms would only
be a new id for the same model). What is printed then, and the fresh-run figures of each named step,
are the README's (*Finding what the model misses*).
"""

from __future__ import annotations

import argparse
import json
import sys

from nanodrift.calibration.dataset import DataError, common_channels, concat, read_runs
from nanodrift.calibration.discovery import CellDiscoveryResult, DiscoveryError, DiscoveryResult, discover_cell
from nanodrift.errors import user_errors
from nanodrift.model.cell_model import CellModel, load_any_model, one_axis, save_cell_model
from nanodrift.model.model import MissingChannelError, ModelFileError
from nanodrift.model.provenance import stamp_data

NOTHING_FOUND = "nothing found; no model written"


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("data", metavar="D.csv", nargs="+",
                        help="recorded data (CSV) the model is tested against; several files are runs of their own")
    parser.add_argument("--model", required=True, metavar="M.json", help="the model to extend")
    parser.add_argument("--out", required=True, metavar="M2.json", help="the extended model file to write")
    parser.add_argument("--fresh", metavar="F.csv",
                        help="a run discovery does not see (e.g. recorded later): each step's gain is measured on it")
    parser.add_argument("--report", metavar="DIR", help="also write report.md and figures into DIR")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")


def main(args: argparse.Namespace) -> int:
    paths = [str(p) for p in args.data]
    with user_errors(DataError, ModelFileError, MissingChannelError, DiscoveryError):
        runs = read_runs(paths, "to compare with")
        given = CellModel.of(load_any_model(args.model))
        for ds in runs:
            for axis_model in given.models.values():
                axis_model.check_channels(list(ds.channels), ds.source)
        channels = common_channels(runs)
        left_out = sorted({c for ds in runs for c in ds.channels} - set(channels))
        if left_out:
            print(f"nanodrift: note: channel(s) {', '.join(left_out)} not in every file, left out", file=sys.stderr)
        data = concat(runs, channels)
        fresh = read_runs([str(args.fresh)], "to measure the fresh-run gain on")[0] if args.fresh else None
        result = discover_cell(data, given, fresh=fresh)
    model_out: str | None = None
    if result.found:
        extended = result.model
        for axis, axis_result in result.axes.items():
            if axis_result.found:
                stamp_data(extended.models[axis], [(p, len(ds)) for p, ds in zip(paths, runs, strict=True)])
        save_cell_model(extended, args.out)
        model_out = str(args.out)
        for axis, axis_result in result.axes.items():
            axis_result.final["model"] = extended.models[axis].id
    if args.report:
        _write_reports(args.report, result, model_out, paths)
    if one_axis(given.axes):  # a one-axis model's output keeps the one-axis shape
        (only,) = result.axes.values()
        print(json.dumps(only.to_dict(model_out), indent=2, allow_nan=False) if args.json
              else describe(only, model_out))
    elif args.json:
        print(json.dumps(result.to_dict(model_out), indent=2, allow_nan=False))
    else:
        _print_cell(result, model_out)
    return 0


def _write_reports(directory: str, result: CellDiscoveryResult, model_out: str | None, paths: list[str]) -> None:
    """The report of every axis (a cell of several: in ``axis_<name>/``), with the given model's provenance."""
    # matplotlib (slow to import) only when a report is asked for; not a cycle
    from nanodrift.reports.discovery import write_report
    from nanodrift.reports.validation import provenance_text

    given = result.given
    footer = provenance_text(given.id, given.provenance.get("data_file"), f"discovered on {', '.join(paths)}")
    for axis, axis_result in result.axes.items():
        where = directory if one_axis(given.axes) else f"{directory}/axis_{axis}"
        write_report(axis_result, where, model_out, provenance=footer)


def describe(result: DiscoveryResult, model_out: str | None) -> str:
    lines = [result.summary, ""]
    if result.steps:
        lines.append(f"{'effect':>26} {'p':>9} {'held-out before':>16} {'after':>9} {'fresh run x':>11}  terms")
        for s in result.steps:
            expected = f"{s.fresh_expected.ratio:.2f}" if s.fresh_expected is not None else "-"
            lines.append(
                f"{s.effect:>26} {s.bar_p:>9.2g} {s.holdout_rms_before_um * 1000:>13.1f} nm "
                f"{s.holdout_rms_after_um * 1000:>6.1f} nm {expected:>11}  {', '.join(t.name for t in s.add) or '-'}"
                + (f" (removed {', '.join(t.name for t in s.remove)})" if s.remove else "")
            )
        lines.append("(fresh run x: the RMS ratio after / before expected on a fresh run of the same kind; "
                     "held-out blocks of this run flatter it)")
    if model_out is None:
        lines.append(f"{NOTHING_FOUND} (the model {result.final['model']} stands)")
    else:
        lines.append(f"extended model {result.final['model']} -> {model_out}: {', '.join(result.final['terms'])}")
    return "\n".join(lines)


def _print_cell(result: CellDiscoveryResult, model_out: str | None) -> None:
    """A cell of several axes: every axis' discovery, then the cell model written (or the given one standing)."""
    for axis, axis_result in result.axes.items():
        print(f"== axis {axis}")
        print(describe(axis_result, model_out if axis_result.found else None))
        print()
    if model_out is None:
        print(f"{NOTHING_FOUND} (the cell model {result.given.id} stands)")
    else:
        print(f"extended cell model {result.model.id} -> {model_out}")
