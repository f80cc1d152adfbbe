"""``nanodrift run``: the daemon for one cell (the simulated cell when there is no ``--config``).

With no ``--config`` and no ``-l`` it listens on :data:`TRYOUT_LISTEN` (zenoh's conventional port,
on loopback: the simulated cell is a try-out, not a service for the network), so the README's
``nanodrift target 0 240 480 -e tcp/127.0.0.1:7447`` reaches it.
"""

from __future__ import annotations

import argparse
from typing import Any

from nanodrift.assembly import build_drivers
from nanodrift.commands._config_flag import add_config_flag
from nanodrift.config import load_config
from nanodrift.logs import configure_logging
from nanodrift.service import run_service

#: where the built-in simulated cell listens unless ``-l`` says otherwise
TRYOUT_LISTEN = "tcp/127.0.0.1:7447"


def configure(parser: argparse.ArgumentParser) -> None:
    add_config_flag(parser)
    # the zenoh-python examples' conventions; they override the config file
    parser.add_argument("-l", "--listen", action="append", default=[], metavar="EP",
                        help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable; overrides [zenoh] listen)")
    parser.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                        help="endpoint to connect to (repeatable; overrides [zenoh] connect)")
    parser.add_argument("--mode", choices=["peer", "client", "router"],
                        help="zenoh session mode (overrides [zenoh] mode, whose default is peer)")
    parser.add_argument("--no-multicast-scouting", action="store_true",
                        help="do not look for peers by UDP multicast")
    parser.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                        help="the least severe log lines printed")


def zenoh_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``-l``/``-e``/``--mode``: they replace what the config file says (zenoh examples' rule)."""
    overrides: dict[str, Any] = {"mode": args.mode, "listen": list(args.listen), "connect": list(args.connect)}
    if args.config is None and not overrides["listen"]:
        overrides["listen"] = [TRYOUT_LISTEN]
    if args.no_multicast_scouting:
        overrides["multicast_scouting"] = False
    return overrides


def main(args: argparse.Namespace) -> int:
    configure_logging(args.log_level)
    config = load_config(args.config)
    return run_service(config, build_drivers, config_path=args.config, zenoh_overrides=zenoh_overrides(args))
