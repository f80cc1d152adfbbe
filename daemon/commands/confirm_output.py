"""``nanodrift confirm-output --config F --axis x --voltage V``: an operator says where an output is.

At start the daemon believes an output's read-back only when its state directory's record of what it last
wrote confirms it (or, on a first start, when it is the output's ``power_up_voltage_v``). When nothing
does (a module another program wrote, a state file lost, a read-back that lies) the output is not moved
and targets are refused until someone checks what the amplifier's input really holds and confirms it
here. This writes the record the daemon reads (:mod:`nanodrift.output_record`) for that axis' device, as
if the daemon had written ``V`` itself; a running daemon retries on its own and believes a read-back
within ``read_back_tolerance_v`` of it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from nanodrift.assembly import build_drivers
from nanodrift.config import load_config
from nanodrift.errors import UserError
from nanodrift.output_record import OutputRecords, state_directory


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--config", required=True, metavar="F", help="the daemon's operator config")
    parser.add_argument("--axis", default="x", help="the axis whose output was checked (a one-axis cell's is x)")
    parser.add_argument("--voltage", required=True, type=float, metavar="V",
                        help="what the output holds, as measured (V)")
    parser.add_argument("--state-dir", type=Path, default=None, metavar="DIR",
                        help="the daemon's state directory (default: $STATE_DIRECTORY, else [daemon] state_dir; "
                             "under systemd: /var/lib/nanodrift, or /var/lib/nanodrift/<instance>)")


def main(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.axis not in config.axis_names:
        raise UserError(f"--axis {args.axis}: the cell's axes are {', '.join(config.axis_names)}")
    actuator = config.axis_actuators()[args.axis]
    if not actuator.within_limits(args.voltage):
        raise UserError(f"--voltage {args.voltage:g}: outside axis {args.axis}'s [v_min, v_max] = "
                        f"[{actuator.v_min:g}, {actuator.v_max:g}] V; the daemon never moves an output from there")
    directory = args.state_dir or state_directory(config.daemon.state_dir)
    if directory is None:
        raise UserError("no state directory: pass --state-dir, or set [daemon] state_dir in the config")
    device = build_drivers(config).actuators.get(args.axis)  # built, never opened: its name is what is recorded
    if device is None:
        raise UserError(f"axis {args.axis} has no output device (kind = {actuator.kind!r}): nothing to confirm")
    records = OutputRecords(Path(directory), config.cell)
    try:
        records.save(args.axis, device.description, args.voltage, args.voltage, by="operator")
    except OSError as error:
        raise UserError(f"{records.path(args.axis)}: cannot write the state file ({error})") from None
    print(f"axis {args.axis} ({device.description}) confirmed at {args.voltage:g} V: {records.path(args.axis)}; "
          "the daemon believes a read-back of it at its next open (a daemon refusing targets retries on its own)")
    return 0
