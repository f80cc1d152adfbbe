"""``nanodrift discover D.csv --model M.json --out M2.json [--report DIR] [--json]``."""

from __future__ import annotations

import argparse
import json

from daemon.calibration.dataset import DataError, read_csv
from daemon.calibration.discovery import DiscoveryError, DiscoveryResult, discover
from daemon.errors import UserError
from daemon.model.model import MissingChannelError, ModelFileError, load_model, save_model
from daemon.model_commands import file_sha256


def discover_command(args: argparse.Namespace) -> int:
    try:
        data = read_csv(args.data)
        model = load_model(args.model)
        result = discover(data, model)
    except (DataError, ModelFileError, MissingChannelError, DiscoveryError) as err:
        raise UserError(str(err)) from None
    extended = result.model
    extended.provenance["data_file"] = str(args.data)
    extended.provenance["data_sha256"] = file_sha256(args.data)
    extended.id = extended.content_id()
    result.final["model"] = extended.id
    save_model(extended, args.out)
    if args.report:
        from daemon.calibration.discovery_report import write_report  # matplotlib only when asked

        write_report(result, args.report, str(args.out))
    if args.json:
        print(json.dumps(result.to_dict(str(args.out)), indent=2, allow_nan=False))
    else:
        print(describe(result, str(args.out)))
    return 0


def describe(result: DiscoveryResult, model_out: str) -> str:
    lines = [result.summary, ""]
    if result.steps:
        lines.append(f"{'effect':>26} {'p':>9} {'held-out before':>16} {'after':>9}  terms")
        for s in result.steps:
            lines.append(
                f"{s.effect:>26} {s.p_value:>9.2g} {s.holdout_rms_before_um * 1000:>13.1f} nm "
                f"{s.holdout_rms_after_um * 1000:>6.1f} nm  {', '.join(t.name for t in s.add) or '-'}"
                + (f" (removed {', '.join(t.name for t in s.remove)})" if s.remove else "")
            )
    lines.append(f"extended model {result.final['model']} -> {model_out}: {', '.join(result.final['terms'])}")
    return "\n".join(lines)
