"""``nanodrift target X...``: a client that sends targets to a running daemon and prints the commands."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import zenoh

from daemon.bus.session import Keys, describe_zenoh_error, session_config
from daemon.config import ZenohSettings
from daemon.errors import UserError


def _format_command(doc: dict[str, Any]) -> str:
    temps = " ".join(f"{k}={v:.3f}" for k, v in (doc.get("temperatures_c") or {}).items())
    extra = f" EXTRAPOLATING {','.join(doc['extrapolating'])}" if doc.get("extrapolating") else ""
    return (f"x {doc['x_um']:.4f} µm -> q {doc['q_um']:.4f} µm, {doc['voltage_v']:.5f} V "
            f"[model {doc['model']}; {temps}]{extra}")


def client_config(args: argparse.Namespace) -> zenoh.Config:
    """The client's session config: ``--zenoh-config F`` (credentials, TLS) as the base, then ``-e``/``--mode``.

    Without a file: client mode towards ``-e`` endpoints, else a peer that scouts. With a file, its
    mode, endpoints and scouting stand unless ``-e``/``--mode`` are given (the zenoh examples' rule).
    """
    file = getattr(args, "zenoh_config", None)
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


def open_client_session(args: argparse.Namespace, conf: zenoh.Config) -> zenoh.Session:
    """The client's session, or a one-sentence :class:`UserError` (``target`` and ``status`` share it)."""
    try:
        return zenoh.open(conf)
    except zenoh.ZError as error:
        where = ", ".join(args.connect) or getattr(args, "zenoh_config", None) or "scouting"
        raise UserError(f"cannot open a zenoh session ({where}): "
                        f"{describe_zenoh_error(error, connect=args.connect)}") from None


def main(args: argparse.Namespace) -> int:
    """A client: each target through the ``compensate`` queryable; non-zero exit if any is refused."""
    keys = Keys(args.cell)
    conf = client_config(args)
    session = open_client_session(args, conf)
    failures = 0
    try:
        for index, x in enumerate(args.x):
            request = json.dumps({"x_um": x, "id": index})
            answer: dict[str, Any] | None = None
            ok = False
            for reply in session.get(keys.compensate, payload=request, timeout=args.timeout):
                result = reply.result  # a Sample, or a ReplyError
                raw = result.payload.to_bytes()
                ok = isinstance(result, zenoh.Sample)
                try:
                    answer = json.loads(raw)
                except ValueError:
                    answer = {"id": index, "error": raw.decode("utf-8", "replace")}
                break
            if answer is None:
                failures += 1
                answer = {"id": index, "error": f"no answer from {keys.compensate} within {args.timeout:g} s "
                                               "(is the daemon running? -e tcp/HOST:PORT)"}
            elif not ok:
                failures += 1
            if args.json:
                print(json.dumps(answer))
            elif ok:
                print(_format_command(answer))
            else:
                print(f"x {x:g} µm refused: {answer.get('error')}", file=sys.stderr)
    finally:
        session.close()
    return 1 if failures else 0
