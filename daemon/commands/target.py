"""``nanodrift target X...``: a client that sends targets to a running daemon and prints the commands.

A target nobody answers is explained once: the cells that answer ``status`` on the network are asked
for (the query of ``nanodrift status``), so a wrong ``--cell`` is told from a daemon that is not running.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

import zenoh

from daemon.bus.protocol import Keys
from daemon.commands._client import add_client_flags, open_client, query_status, status_key

#: seconds to collect the cells' ``status`` replies when the target's cell did not answer
DISCOVERY_TIMEOUT_S = 2.0


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("x", nargs="+", type=float, metavar="X", help="target positions (µm)")
    add_client_flags(parser, endpoint_of="the daemon")
    parser.add_argument("--cell", default="cell0", help="cell name (key prefix nanodrift/<cell>)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for each answer")
    parser.add_argument("--json", action="store_true", help="print JSON lines")


def _format_command(doc: dict[str, Any]) -> str:
    """``x 240.0000 µm -> q 239.6231 µm, 4.79246 V [model m-…; σ 0.0185 µm; T1=21.800 °C, …]``."""
    temps = ", ".join(f"{k}={v:.3f} °C" for k, v in (doc.get("temperatures_c") or {}).items())
    sigma = doc.get("q_sigma_um")
    details = [f"model {doc['model']}", f"σ {sigma:.4f} µm" if isinstance(sigma, int | float) else "σ unknown"]
    correction = doc.get("correction_um")
    if isinstance(correction, int | float):
        details.append(f"correction {correction:+.4f} µm")
    if temps:
        details.append(temps)
    extra = f" EXTRAPOLATING {','.join(doc['extrapolating'])}" if doc.get("extrapolating") else ""
    return (f"x {doc['x_um']:.4f} µm -> q {doc['q_um']:.4f} µm, {doc['voltage_v']:.5f} V "
            f"[{'; '.join(details)}]{extra}")


def no_answer(session: zenoh.Session, cell: str, key: str, timeout_s: float) -> str:
    """Why nothing answered on ``key``: a cell nobody serves (naming those that answer), or no daemon at all."""
    docs = query_status(session, status_key(None), min(timeout_s, DISCOVERY_TIMEOUT_S))
    cells = [str(doc.get("cell")) for doc in docs]
    if cell in cells:
        return (f"cell {cell!r} answers status but gave no command on {key} within {timeout_s:g} s "
                f"(a busy or stalled daemon: nanodrift status --cell {cell})")
    if cells:
        return (f"no daemon serves cell {cell!r} (nothing answers on {key}); the cell(s) answering on this "
                f"network: {', '.join(cells)} (--cell {cells[0]})")
    return (f"no daemon serves cell {cell!r}, and no cell answered on {status_key(None)} either "
            "(is the daemon running? give its endpoint with -e tcp/HOST:PORT)")


def main(args: argparse.Namespace) -> int:
    """A client: each target through the ``compensate`` queryable; non-zero exit if any is refused."""
    keys = Keys(args.cell)
    session = open_client(args)
    failures = 0
    unanswered = ""  # why the cell does not answer, asked once
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
                unanswered = unanswered or no_answer(session, args.cell, keys.compensate, args.timeout)
                answer = {"id": index, "error": unanswered}
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
