"""``nanodrift target X...``: a client that sends targets to a running daemon and prints the commands."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import zenoh

from daemon.bus.protocol import Keys
from daemon.commands._client import add_client_flags, open_client


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("x", nargs="+", type=float, metavar="X", help="target positions (µm)")
    add_client_flags(parser, endpoint_of="the daemon")
    parser.add_argument("--cell", default="cell0", help="cell name (key prefix nanodrift/<cell>)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for each answer")
    parser.add_argument("--json", action="store_true", help="print JSON lines")


def _format_command(doc: dict[str, Any]) -> str:
    temps = " ".join(f"{k}={v:.3f}" for k, v in (doc.get("temperatures_c") or {}).items())
    extra = f" EXTRAPOLATING {','.join(doc['extrapolating'])}" if doc.get("extrapolating") else ""
    return (f"x {doc['x_um']:.4f} µm -> q {doc['q_um']:.4f} µm, {doc['voltage_v']:.5f} V "
            f"[model {doc['model']}; {temps}]{extra}")


def main(args: argparse.Namespace) -> int:
    """A client: each target through the ``compensate`` queryable; non-zero exit if any is refused."""
    keys = Keys(args.cell)
    session = open_client(args)
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
