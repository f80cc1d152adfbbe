"""``nanodrift discover D.csv --model M.json --out M2.json [--report DIR] [--json]``: read, discover, write.

When nothing clears the bar no model is written (an "extended" model with the given terms would only
be a new id for the same model): "nothing found; no model written", exit 0, ``"steps": []`` and
``"model_out": null`` in ``--json``. Effects the run's trajectory cannot show (hysteresis in
forward-only sweeps) are named with the run that would show them, found or not.
"""

from __future__ import annotations

import argparse
import json

from daemon.atomic import file_sha256
from daemon.calibration.dataset import DataError, read_csv
from daemon.calibration.discovery import DiscoveryError, DiscoveryResult, discover
from daemon.errors import UserError
from daemon.model.model import MissingChannelError, ModelFileError, load_model, save_model

NOTHING_FOUND = "nothing found; no model written"


def main(args: argparse.Namespace) -> int:
    try:
        data = read_csv(args.data)
        model = load_model(args.model)
        result = discover(data, model)
    except (DataError, ModelFileError, MissingChannelError, DiscoveryError) as err:
        raise UserError(str(err)) from None
    model_out: str | None = None
    if result.found:
        extended = result.model
        extended.provenance["data_file"] = str(args.data)
        extended.provenance["data_sha256"] = file_sha256(args.data)
        extended.id = extended.content_id()
        result.final["model"] = extended.id
        save_model(extended, args.out)
        model_out = str(args.out)
    if args.report:
        # matplotlib (slow to import) only when a report is asked for; not a cycle
        from daemon.reports.discovery import write_report

        write_report(result, args.report, model_out)
    if args.json:
        print(json.dumps(result.to_dict(model_out), indent=2, allow_nan=False))
    else:
        print(describe(result, model_out))
    return 0


def describe(result: DiscoveryResult, model_out: str | None) -> str:
    lines = [result.summary, ""]
    if result.steps:
        lines.append(f"{'effect':>26} {'p':>9} {'held-out before':>16} {'after':>9}  terms")
        for s in result.steps:
            lines.append(
                f"{s.effect:>26} {s.p_value:>9.2g} {s.holdout_rms_before_um * 1000:>13.1f} nm "
                f"{s.holdout_rms_after_um * 1000:>6.1f} nm  {', '.join(t.name for t in s.add) or '-'}"
                + (f" (removed {', '.join(t.name for t in s.remove)})" if s.remove else "")
            )
    if model_out is None:
        lines.append(f"{NOTHING_FOUND} (the model {result.final['model']} stands)")
    else:
        lines.append(f"extended model {result.final['model']} -> {model_out}: {', '.join(result.final['terms'])}")
    return "\n".join(lines)
