"""``nanodrift``: one command line for the service, the procedures and the model tools.

The parser lists every command of the public contract; each handler lives in the module that owns
the job and is imported only when its command runs, so ``nanodrift fit`` never loads zenoh.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence

from daemon.errors import UserError

HANDLERS = {
    "run": "daemon.service_commands:run_command",
    "demo": "daemon.service_commands:demo_command",
    "target": "daemon.service_commands:target_command",
    "check-config": "daemon.service_commands:check_config_command",
    "simulate": "daemon.calibration.commands:simulate_command",
    "calibrate": "daemon.calibration.commands:calibrate_command",
    "validate": "daemon.calibration.commands:validate_command",
    "fit": "daemon.model_commands:fit_command",
    "predict": "daemon.model_commands:predict_command",
    "discover": "daemon.calibration.discovery_command:discover_command",
}


def _zenoh_flags(p: argparse.ArgumentParser) -> None:
    """The zenoh-python examples' conventions; they override the config file."""
    p.add_argument("-l", "--listen", action="append", default=[], metavar="EP", help="endpoint to listen on")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="EP", help="endpoint to connect to")
    p.add_argument("--mode", choices=["peer", "client", "router"], help="zenoh session mode")


def _simulation_flags(p: argparse.ArgumentParser) -> None:
    """For the simulated cell (no --config, or a config with simulated sensors): override [simulation]."""
    p.add_argument("--scenario", metavar="S", help="simulated room history (default: train / test2)")
    p.add_argument("--effects", metavar="a,b", help="hidden effects of the simulated cell")
    p.add_argument("--seed", type=int, metavar="N", help="simulation seed")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="nanodrift", description="Thermal-drift compensation for a piezo nanopositioning stage."
    )
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    # --- service (daemon helper) ---
    p = sub.add_parser("run", help="the daemon (simulated cell when no --config)")
    p.add_argument("--config", metavar="F", help="operator config (TOML)")
    _zenoh_flags(p)
    p.add_argument("--no-multicast-scouting", action="store_true", help="do not look for peers by UDP multicast")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])

    p = sub.add_parser("demo", help="calibrate, serve and validate on the simulated cell (~1 min)")
    _zenoh_flags(p)
    p.add_argument("--tests", nargs="+", default=["test2", "test4", "test5"], metavar="T",
                   help="validation scenarios to run through the daemon")
    p.add_argument("--cycles", type=int, default=10, metavar="N", help="validation sweeps per test")
    p.add_argument("--calibration-cycles", type=int, default=24, metavar="N")
    p.add_argument("--speed", type=float, default=300.0, help="simulated seconds per wall second while serving")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--keep", metavar="DIR", help="keep the model, data, configs and daemon logs in DIR")

    p = sub.add_parser("target", help="send targets to a running daemon and print the commands")
    p.add_argument("x", nargs="+", type=float, metavar="X", help="target positions (um)")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="EP", help="endpoint to connect to")
    p.add_argument("--mode", choices=["peer", "client"], default=None, help="zenoh session mode")
    p.add_argument("--cell", default="cell0", help="cell name (key prefix nanodrift/<cell>)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for each answer")
    p.add_argument("--json", action="store_true", help="print JSON lines")

    p = sub.add_parser("check-config", help="validate an operator config")
    p.add_argument("file", metavar="F")

    # --- procedures (sim helper) ---
    p = sub.add_parser("simulate", help="data from the simulated cell")
    p.add_argument("--scenario", required=True, metavar="S")
    p.add_argument("--effects", default="", metavar="a,b", help="hidden effects, e.g. thermal_lag:tau_s=1800,creep")
    p.add_argument("--cycles", type=int, metavar="N")
    p.add_argument("--seed", type=int, default=0, metavar="N")
    p.add_argument("--out", required=True, metavar="F.csv")

    p = sub.add_parser("calibrate", help="the paper's calibration procedure (Fig. 6, 7)")
    p.add_argument("--config", metavar="F")
    p.add_argument("--out", required=True, metavar="M.json")
    p.add_argument("--data", metavar="D.csv", help="where the recorded steps go (default: beside --out)")
    p.add_argument("--cycles", type=int, default=24, metavar="N")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from --data")
    _simulation_flags(p)

    p = sub.add_parser("validate", help="ISO 9283 validation, Table I")
    p.add_argument("--config", metavar="F")
    p.add_argument("--model", required=True, metavar="M.json")
    p.add_argument("--cycles", type=int, default=30, metavar="N")
    p.add_argument("--json", action="store_true")
    p.add_argument("--report", metavar="DIR")
    p.add_argument("--no-compensation", action="store_true", help="command the targets as they are (test 1)")
    _simulation_flags(p)

    # --- model tools (lead) ---
    p = sub.add_parser("fit", help="identify the model from recorded data")
    p.add_argument("data", metavar="D.csv")
    p.add_argument("--out", required=True, metavar="M.json")
    p.add_argument("--order", default="auto", help="geometric order n1, or auto (held-out cycles)")
    p.add_argument("--exclude", action="append", default=[], metavar="CH", help="leave a channel out")
    p.add_argument("--penter", type=float, default=0.05, metavar="P")
    p.add_argument("--premove", type=float, default=0.10, metavar="P")
    p.add_argument("--json", action="store_true")

    p = sub.add_parser("predict", help="the command the model gives for each row")
    p.add_argument("--model", required=True, metavar="M.json")
    p.add_argument("data", metavar="D.csv")
    p.add_argument("--out", required=True, metavar="P.csv")

    # --- discovery (discovery helper) ---
    p = sub.add_parser("discover", help="find what the model misses, add it, show the gap shrink")
    p.add_argument("data", metavar="D.csv")
    p.add_argument("--model", required=True, metavar="M.json")
    p.add_argument("--out", required=True, metavar="M2.json")
    p.add_argument("--report", metavar="DIR")
    p.add_argument("--json", action="store_true")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    module_name, func_name = HANDLERS[args.command].split(":")
    handler = getattr(importlib.import_module(module_name), func_name)
    try:
        return int(handler(args) or 0)
    except UserError as err:
        print(f"nanodrift {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"nanodrift {args.command}: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
