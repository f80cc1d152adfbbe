"""``nanodrift simulate``: a recorded run of the simulated cell, as a CSV of the data contract."""

from __future__ import annotations

import argparse
import sys

from daemon.calibration.dataset import write_csv
from daemon.commands._catalogues import effects_epilog, scenario_epilog, scenario_names
from daemon.errors import UserError
from drivers.simulated.datasets import simulate_dataset
from drivers.simulated.effects import UnknownNameError, resolve_effects


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = scenario_epilog() + "\n\n" + effects_epilog()
    parser.add_argument("--scenario", required=True, metavar="S",
                        help=f"room history and trajectory, one of {scenario_names()} (see below)")
    parser.add_argument("--effects", default="", metavar="a,b",
                        help="hidden effects to switch on, with optional parameters, e.g. "
                             "thermal_lag:tau_s=1800,creep (see below; default: none)")
    parser.add_argument("--cycles", type=int, metavar="N",
                        help="sweeps to record (default: the scenario's: 24 calibration or 30 validation sweeps)")
    parser.add_argument("--seed", type=int, default=0, metavar="N", help="noise and room seed: same seed, same data")
    parser.add_argument("--out", required=True, metavar="F.csv", help="the CSV to write (data contract columns)")


def main(args: argparse.Namespace) -> int:
    if args.cycles is not None and args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    try:
        effects = resolve_effects(args.effects or None)
        ds = simulate_dataset(args.scenario, effects, cycles=args.cycles, seed=args.seed)
    except UnknownNameError as err:
        raise UserError(str(err)) from None
    write_csv(ds, args.out)
    cycles = ds.extra["cycle"]
    span = (ds.t[-1] - ds.t[0]) / 3600.0
    print(f"wrote {args.out}: {len(ds)} steps ({len(ds) // max(1, len(set(cycles.tolist())))} per cycle, "
          f"{span:.2f} h), scenario {args.scenario}, effects {','.join(effects) or 'none'}, seed {args.seed}",
          file=sys.stderr)
    return 0
