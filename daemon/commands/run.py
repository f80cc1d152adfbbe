"""``nanodrift run``: the daemon for one cell (the simulated cell when there is no ``--config``).

With no ``--config`` and no ``-l`` it listens on :data:`TRYOUT_LISTEN` (zenoh's conventional port,
on loopback: the simulated cell is a try-out, not a service for the network), so the README's
``nanodrift target 0 240 480 -e tcp/127.0.0.1:7447`` reaches it.
"""

from __future__ import annotations

import argparse
from typing import Any

from daemon.assembly import build_drivers
from daemon.config import load_config
from daemon.logs import configure_logging
from daemon.service import run_service

#: where the built-in simulated cell listens unless ``-l`` says otherwise
TRYOUT_LISTEN = "tcp/127.0.0.1:7447"


def zenoh_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``-l``/``-e``/``--mode``: they replace what the config file says (zenoh examples' rule)."""
    overrides: dict[str, Any] = {
        "mode": getattr(args, "mode", None),
        "listen": list(getattr(args, "listen", None) or []),
        "connect": list(getattr(args, "connect", None) or []),
    }
    if getattr(args, "config", None) is None and not overrides["listen"]:
        overrides["listen"] = [TRYOUT_LISTEN]
    if getattr(args, "no_multicast_scouting", False):
        overrides["multicast_scouting"] = False
    return overrides


def main(args: argparse.Namespace) -> int:
    configure_logging(getattr(args, "log_level", None) or "info")
    config = load_config(args.config)
    return run_service(config, build_drivers, config_path=args.config, zenoh_overrides=zenoh_overrides(args))
