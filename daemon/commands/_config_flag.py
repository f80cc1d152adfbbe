"""``--config F``: the one option ``run`` shares with the procedures (``_cell.py``), apart from what a procedure
needs (the simulated cell's overrides, the preflight checks), which ``nanodrift run`` does not import."""

from __future__ import annotations

import argparse


def add_config_flag(parser: argparse.ArgumentParser) -> None:
    """``--config F``: the operator's cell; without it, the built-in simulated cell."""
    parser.add_argument("--config", metavar="F", help="operator config (TOML); none: the built-in simulated cell")
