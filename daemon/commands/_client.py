"""The client side of ``target`` and ``status``: their shared options, the Zenoh session they open, and
the query that finds the cells on the network.

:func:`add_client_flags` declares ``-e/--connect``, ``--mode`` and ``--zenoh-config``; :func:`open_client`
reads them (and nothing else) into a session, so the rule "a file as the base, then ``-e``/``--mode``"
is written once. :func:`query_status` is ``status``'s query, which ``target`` also asks when its cell
does not answer (to name the cells that do).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import zenoh

from nanodrift.bus.protocol import key_prefix
from nanodrift.bus.session import describe_zenoh_error, session_config
from nanodrift.config import ZenohSettings
from nanodrift.errors import UserError


def add_client_flags(parser: argparse.ArgumentParser, *, endpoint_of: str) -> None:
    """``-e EP`` (``endpoint_of``: whom it reaches, for the help), ``--mode``, ``--zenoh-config F``."""
    parser.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                        help=f"endpoint of {endpoint_of}, e.g. tcp/127.0.0.1:7447 (repeatable; default: scouting)")
    parser.add_argument("--mode", choices=["peer", "client"], default=None,
                        help="zenoh session mode (default: client with -e, else peer)")
    parser.add_argument("--zenoh-config", metavar="F",
                        help="a zenoh json5 config (credentials, TLS), e.g. config/zenoh-client.example.json5")


def client_config(args: argparse.Namespace) -> zenoh.Config:
    """The client's session config: ``--zenoh-config F`` (credentials, TLS) as the base, then ``-e``/``--mode``.

    Without a file: client mode towards ``-e`` endpoints, else a peer that scouts. With a file, its
    mode, endpoints and scouting stand unless ``-e``/``--mode`` are given (the zenoh examples' rule).
    """
    file = args.zenoh_config
    if not file:
        return session_config(
            mode=args.mode or ("client" if args.connect else "peer"),
            connect=args.connect,
            multicast_scouting=not args.connect,  # an explicit endpoint needs no scouting
        )
    if not Path(file).is_file():
        raise UserError(f"--zenoh-config {file}: no such file")
    try:
        return session_config(
            ZenohSettings(config_file=Path(file)),
            mode=args.mode,
            connect=args.connect,
            multicast_scouting=False if args.connect else None,
        )
    except zenoh.ZError as error:
        raise UserError(f"--zenoh-config {file}: zenoh cannot use it: {error}") from None


def open_client(args: argparse.Namespace) -> zenoh.Session:
    """The client's session (:func:`client_config`), or a one-sentence :class:`UserError`."""
    conf = client_config(args)
    try:
        return zenoh.open(conf)
    except zenoh.ZError as error:
        where = ", ".join(args.connect) or args.zenoh_config or "scouting"
        raise UserError(f"cannot open a zenoh session ({where}): "
                        f"{describe_zenoh_error(error, connect=args.connect)}") from None


def status_key(cell: str | None) -> str:
    """One cell's ``status`` key, or every cell's (``None``: the wildcard)."""
    return f"{key_prefix(cell or '*')}/status"


def query_status(session: zenoh.Session, key: str, timeout_s: float) -> list[dict[str, Any]]:
    """Every reply to one query on ``key``, sorted by cell; errors and non-JSON replies are skipped."""
    docs: dict[str, dict[str, Any]] = {}
    for reply in session.get(key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                             timeout=timeout_s):
        sample = reply.ok
        if sample is None:
            continue
        try:
            doc = json.loads(sample.payload.to_bytes())
        except ValueError:
            continue
        if isinstance(doc, dict):
            cell = str(doc.get("cell") or str(sample.key_expr).split("/")[1])
            docs[cell] = doc
    return [docs[cell] for cell in sorted(docs)]
