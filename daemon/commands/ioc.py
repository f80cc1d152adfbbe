"""``nanodrift ioc``: the EPICS Channel Access bridge (README, *EPICS*; the PVs: :mod:`nanodrift.epics_ioc`).

A client of the Zenoh network, like ``status``: it finds the cells (every cell that answers ``status``
when it starts, or the ``--cell``s named) and serves each axis of each as a motor-like set of PVs until
Ctrl-C or SIGTERM. A cell that starts later needs a restart of the bridge. Channel Access' own settings
(``EPICS_CAS_INTF_ADDR_LIST``, ``EPICS_CA_SERVER_PORT``, ...) are caproto's, read from the environment.
"""

from __future__ import annotations

import argparse
import asyncio
import signal
import sys
from typing import Any

from nanodrift.async_moves import ANSWER_TIMEOUT_S
from nanodrift.cell_view import CellView
from nanodrift.client import Client
from nanodrift.commands._client import add_client_flags, open_client
from nanodrift.errors import UserError


def configure(parser: argparse.ArgumentParser) -> None:
    add_client_flags(parser, endpoint_of="a daemon or router")
    parser.add_argument("--cell", action="append", default=[], metavar="C",
                        help="serve this cell (repeatable; default: every cell that answers status at start)")
    parser.add_argument("--pv-prefix", default="nanodrift:", metavar="P",
                        help="PV names <P><cell>:SP, ... (a cell of several axes: <P><cell>:<axis>:SP)")
    parser.add_argument("--timeout", type=float, default=2.0, metavar="S",
                        help="seconds to wait for the cells' status at start")
    parser.add_argument("--answer-timeout", type=float, default=ANSWER_TIMEOUT_S, metavar="S",
                        help="seconds a put to SP waits for the daemon's answer; none: the put fails, SP in alarm "
                             f"(default {ANSWER_TIMEOUT_S:g})")


def _cells(args: argparse.Namespace) -> list[str]:
    """The cells to serve: the ``--cell``s, else every cell answering ``status``; a UserError when none does."""
    network = open_client(args, None)
    try:
        answering = [str(doc.get("cell")) for doc in network.statuses(timeout_s=args.timeout)]
    finally:
        network.close()
    if not args.cell:
        if not answering:
            raise UserError(f"no cell answered on {args.prefix}/*/status within {args.timeout:g} s "
                            "(is a daemon running? give its endpoint with -e tcp/HOST:PORT)")
        return answering
    missing = [cell for cell in args.cell if cell not in answering]
    if missing:
        raise UserError(f"cell(s) {', '.join(missing)} did not answer status within {args.timeout:g} s"
                        + (f"; the cells answering: {', '.join(answering)}" if answering else ""))
    return list(dict.fromkeys(args.cell))


def main(args: argparse.Namespace) -> int:
    try:
        import nanodrift.epics_ioc as epics_ioc
    except ImportError as error:
        raise UserError(f"nanodrift ioc needs caproto ({error}): pip install 'nanodrift[epics]'") from None
    if not args.answer_timeout > 0:  # (also refuses nan)
        raise UserError(f"--answer-timeout must be a positive number of seconds, got {args.answer_timeout:g}")
    bridges: list[Any] = []
    try:
        for cell in _cells(args):
            client: Client = open_client(args, cell)
            try:
                view = CellView.open(client, timeout_s=args.timeout)
            except (TimeoutError, ValueError) as error:  # no answer; a status without a usable axis
                client.close()
                raise UserError(str(error)) from None
            bridges.append(epics_ioc.CellBridge(client, view, args.pv_prefix, answer_timeout_s=args.answer_timeout))
        return asyncio.run(_serve(epics_ioc, bridges))
    finally:
        for bridge in bridges:
            bridge.close()


async def _serve(epics_ioc: Any, bridges: list[Any]) -> int:
    """Serve until SIGTERM or Ctrl-C (both end it cleanly: exit 0)."""
    def ready() -> None:
        for bridge in bridges:
            names = sorted(name for name in bridge.pvdb if name.endswith(":SP"))
            print(f"nanodrift ioc: serving cell {bridge.cell}: {', '.join(names)} (and RBV, DMOV, STOP, STATE, VOLT, "
                  "SIGMA, MSG beside each)", file=sys.stderr, flush=True)

    loop = asyncio.get_running_loop()
    task = asyncio.ensure_future(epics_ioc.serve(bridges, ready))
    for signum in (signal.SIGTERM, signal.SIGINT):
        loop.add_signal_handler(signum, task.cancel)
    try:
        await task
    except asyncio.CancelledError:
        pass
    return 0
