"""``nanodrift simulate``: a recorded run of the simulated cell, as a CSV of the data contract."""

from __future__ import annotations

import argparse
import sys

from nanodrift.calibration.dataset import write_csv
from nanodrift.commands._catalogues import effects_epilog, scenario_epilog, scenario_names
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.effects import CROSS_AXIS_EFFECTS, EFFECTS, UnknownNameError, resolve_effects
from nanodrift.drivers.simulated.physics import CELL_AXES, CELLS
from nanodrift.errors import UserError


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
    parser.add_argument("--cell", choices=list(CELLS), default="ideal",
                        help="ideal (default): the paper's model form, what a fit can represent exactly; realistic: "
                             "a lab's cell no candidate term reproduces (asymmetric, lagging bracket bending, an "
                             "unmonitored heat source, interferometer refraction, hysteresis and creep, thermocouple "
                             "noise and lags; drivers/simulated/README.md)")
    parser.add_argument("--axes", choices=sorted(CELL_AXES), metavar="xy|xyz",
                        help="a multi-axis cell (stacked stages): columns x_um, y_um[, z_um], q_x_um, ... and the "
                             "true positions x_true_um, ...; calibration scenarios run the space-filling plan, "
                             "validation scenarios the ISO 9283 points; --effects then names the cross-axis "
                             f"effects ({', '.join(CROSS_AXIS_EFFECTS)}: all on; a parameter 0 switches one off). "
                             "Default: one axis")


def main(args: argparse.Namespace) -> int:
    if args.cycles is not None and args.cycles < 1:
        raise UserError(f"--cycles must be at least 1, got {args.cycles}")
    try:
        ds = simulate_dataset(args.scenario, args.effects or None, axes=args.axes or "", cycles=args.cycles,
                              seed=args.seed, cell=args.cell)
    except UnknownNameError as err:
        other = [name for name in (EFFECTS if args.axes else CROSS_AXIS_EFFECTS) if name in (args.effects or "")]
        hint = (f" ({', '.join(other)}: a one-axis effect; the multi-axis cell simulates the cross-axis effects only)"
                if args.axes else f" (the cross-axis effects {', '.join(CROSS_AXIS_EFFECTS)} need --axes xy or xyz)")
        raise UserError(f"{err}{hint if other else ''}") from None
    write_csv(ds, args.out)
    span = (ds.t[-1] - ds.t[0]) / 3600.0
    cycles = len(set(ds.extra["cycle"].tolist()))
    what = f"of axes {','.join(ds.axes)} " if args.axes else ""
    effects = "" if args.axes else f", effects {','.join(resolve_effects(args.effects or None)) or 'none'}"
    print(f"wrote {args.out}: {len(ds)} steps {what}({len(ds) // max(1, cycles)} per cycle, {span:.2f} h), "
          f"scenario {args.scenario}{effects}, seed {args.seed}{'' if args.cell == 'ideal' else ', realistic cell'}",
          file=sys.stderr)
    return 0
