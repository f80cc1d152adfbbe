"""The command-line side of ``target``, ``status`` and ``ioc``: their shared options (:func:`add_client_flags`),
and the :class:`nanodrift.Client` they open from them (:func:`open_client`). What a client does is the library's
(:mod:`nanodrift.client`), which a lab's script uses the same way; here are only argparse and the one-sentence
:class:`UserError`.
"""

from __future__ import annotations

import argparse
import functools

from nanodrift.bus.protocol import DEFAULT_PREFIX
from nanodrift.client import Client
from nanodrift.errors import UserError
from nanodrift.settings import checked_prefix


def add_client_flags(parser: argparse.ArgumentParser, *, endpoint_of: str) -> None:
    """``-e EP`` (``endpoint_of``: whom it reaches, for the help), ``--mode``, ``--zenoh-config F``, ``--prefix P``."""
    parser.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                        help=f"endpoint of {endpoint_of}, e.g. tcp/127.0.0.1:7447 (repeatable; default: scouting)")
    parser.add_argument("--mode", choices=["peer", "client"], default=None,
                        help="zenoh session mode (default: client with -e, else peer)")
    parser.add_argument("--zenoh-config", metavar="F",
                        help="a zenoh json5 config (credentials, TLS), e.g. config/zenoh-client.example.json5")
    parser.add_argument("--prefix", type=functools.partial(checked_prefix, error=argparse.ArgumentTypeError),
                        default=DEFAULT_PREFIX, metavar="P",
                        help="the daemons' [zenoh] prefix: keys <P>/<cell>/... (default: nanodrift)")


def open_client(args: argparse.Namespace, cell: str | None) -> Client:
    """The client of ``cell`` (None: the network's cells) on the session ``-e``/``--mode``/``--zenoh-config``
    say, or a one-sentence :class:`UserError`."""
    try:
        return Client(args.connect or None, cell, zenoh_config=args.zenoh_config, prefix=args.prefix,
                      mode=args.mode, label="--zenoh-config")
    except (OSError, ValueError) as error:  # ConnectionError, a missing file, a file zenoh refuses
        raise UserError(str(error)) from None
