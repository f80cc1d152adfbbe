"""``nanodrift status``: every cell on the network (or one), from their ``status`` queryables.

One wildcard query on ``<prefix>/*/status`` (or ``<prefix>/<cell>/status``), :meth:`nanodrift.Client.statuses`,
collects every daemon's reply until the timeout, printed as a compact table or a JSON list. ``--watch S``
repeats it: a log file or a pipe gets a block per refresh, every sample. Health and actuator state are shown
when the status document carries them (older daemons do not).
"""

from __future__ import annotations

import argparse
import json
import sys
import textwrap
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any, TextIO

from nanodrift.cell_view import cell_state
from nanodrift.client import Client, status_key
from nanodrift.commands._client import add_client_flags, open_client

#: ANSI: cursor home, clear the screen (what ``watch`` does)
CLEAR = "\x1b[H\x1b[2J"
COLUMNS = ("CELL", "STATE", "SENSORS", "MODEL", "MODEL AGE", "HEALTH", "CORRECTION", "ACTUATOR", "TARGETS/MIN",
           "REFUSED/MIN")
NO_CELL_HINT = ("no cell answered on {key} within {timeout:g} s (is a daemon running? "
                "give its endpoint with -e tcp/HOST:PORT, or --zenoh-config F)")


def configure(parser: argparse.ArgumentParser) -> None:
    parser.epilog = textwrap.fill(
        "columns: CELL, STATE (ok | degraded: a sensor not ok | extrapolating | no-model | stalled: "
        "a sensor poller stopped), SENSORS ok/total, MODEL id and MODEL AGE (since it was made), "
        "HEALTH (state and residual RMS, when the daemon measures it), CORRECTION (the bias the adaptation "
        "adds to every command, [adapt] mode = \"bias\"; - when it is off), ACTUATOR (kind and state), "
        "TARGETS/MIN and REFUSED/MIN (averaged since the daemon started; with --watch, over the "
        "last interval). Exit 1 when no cell answers.", 96)
    add_client_flags(parser, endpoint_of="a daemon or router")
    parser.add_argument("--cell", default=None, metavar="C",
                        help="only this cell (key <prefix>/C/status; default: every cell, <prefix>/*/status)")
    parser.add_argument("--json", action="store_true", help="print the status documents as a JSON list")
    parser.add_argument("--watch", type=float, default=None, metavar="S",
                        help="refresh every S seconds until Ctrl-C: in place on a terminal, a block per refresh "
                             "otherwise")
    parser.add_argument("--count", type=int, default=0, metavar="N",
                        help="with --watch: stop after N refreshes (default: until Ctrl-C)")
    parser.add_argument("--timeout", type=float, default=2.0, metavar="S",
                        help="seconds to collect the cells' replies")


@dataclass
class Rates:
    """Targets and refusals per minute of one cell; ``since`` says over what."""

    targets_per_min: float | None
    refused_per_min: float | None
    since: str  # "start" (counters / uptime) or "last" (two samples)


def _counts(doc: dict[str, Any]) -> tuple[float, float] | None:
    counters = doc.get("counters")
    if not isinstance(counters, dict):
        return None
    targets = counters.get("targets")
    refused = counters.get("errors_total")
    if refused is None and isinstance(counters.get("errors"), dict):
        refused = sum(counters["errors"].values())
    if not isinstance(targets, int | float) or not isinstance(refused, int | float):
        return None
    return float(targets), float(refused)


def rates(doc: dict[str, Any], previous: dict[str, Any] | None = None) -> Rates:
    """From two samples of one cell (the same daemon run: uptime grew), else from counters and uptime."""
    now = _counts(doc)
    if now is None:
        return Rates(None, None, "start")
    if previous is not None and (before := _counts(previous)) is not None:
        dt = _number(doc.get("uptime_s")) - _number(previous.get("uptime_s"))
        if dt > 0 and now[0] >= before[0] and now[1] >= before[1]:
            return Rates(60.0 * (now[0] - before[0]) / dt, 60.0 * (now[1] - before[1]) / dt, "last")
    uptime = _number(doc.get("uptime_s"))
    if uptime <= 0:
        return Rates(None, None, "start")
    return Rates(60.0 * now[0] / uptime, 60.0 * now[1] / uptime, "start")


def _number(value: Any) -> float:
    return float(value) if isinstance(value, int | float) else 0.0


def _age(iso: Any, now: datetime) -> str:
    if not isinstance(iso, str):
        return "-"
    try:
        created = datetime.fromisoformat(iso)
    except ValueError:
        return "-"
    if created.tzinfo is None:
        created = created.replace(tzinfo=UTC)
    seconds = max((now - created).total_seconds(), 0.0)
    if seconds < 3600:
        return f"{seconds / 60:.0f} min"
    if seconds < 2 * 86400:
        return f"{seconds / 3600:.1f} h"
    return f"{seconds / 86400:.0f} d"


def _health(health: Any) -> str:
    if not isinstance(health, dict):
        return "-"
    text = str(health.get("state") or "-")
    rms = health.get("residual_rms_nm")
    text = f"{text} {rms:.0f} nm" if isinstance(rms, int | float) else text
    unrecorded = health.get("holds_unrecorded")  # held targets the position poll could not fill: said, not hidden
    return f"{text} ({unrecorded} unrecorded)" if isinstance(unrecorded, int) and unrecorded > 0 else text


def _actuator(doc: dict[str, Any], *, proof: bool = True) -> str:
    """``kind state``, and how the daemon proved where the output was at its start (``proof``)."""
    axes = doc.get("axes")
    if isinstance(axes, dict) and axes:  # a multi-axis cell: each axis' output (its proof on its axis line)
        return " ".join(f"{axis}:{_actuator({'actuator': each.get('actuator')}, proof=False)}".replace(" ", ":", 1)
                        for axis, each in axes.items() if isinstance(each, dict))
    actuator = doc.get("actuator")
    if not isinstance(actuator, dict):
        return "-"
    kind = str(actuator.get("kind") or "-")
    state = actuator.get("state")
    proved_by = actuator.get("proved_by")
    shown = f"{kind} {state}" if state else kind
    return shown + (f" (proved: {proved_by})" if proof and isinstance(proved_by, str) else "")


def axis_lines(doc: dict[str, Any]) -> list[str]:
    """A multi-axis cell's axes under the table: workspace, output and its last voltage, position sensor."""
    axes = doc.get("axes")
    if not isinstance(axes, dict):
        return []
    out = []
    for axis, each in axes.items():
        if not isinstance(each, dict):
            continue
        actuator = each.get("actuator")
        actuator = actuator if isinstance(actuator, dict) else {}
        volts = actuator.get("last_voltage_v")
        position = each.get("position")
        sensor = ""
        if isinstance(position, dict):
            value = position.get("value")
            sensor = (f", position {each.get('position_sensor')} {position.get('state')}"
                      + (f" {value:.3f} µm" if isinstance(value, int | float) else ""))
        health = doc.get("health")
        axis_health = health.get("axes", {}).get(axis) if isinstance(health, dict) else None
        shown = f", health {_health(axis_health)}" if isinstance(axis_health, dict) else ""
        proved_by = actuator.get("proved_by")
        out.append(f"  {doc.get('cell', '?')} axis {axis}: [{_number(each.get('min_um')):g}, "
                   f"{_number(each.get('max_um')):g}] µm, {_actuator({'actuator': actuator}, proof=False)}"
                   + (f" at {volts:.5f} V" if isinstance(volts, int | float) else "")
                   + (f" (proved: {proved_by})" if isinstance(proved_by, str) else "") + sensor + shown)
    return out


def _rate(value: float | None) -> str:
    return "-" if value is None else f"{value:.1f}"


def row(doc: dict[str, Any], previous: dict[str, Any] | None, now: datetime) -> list[str]:
    sensors = doc.get("sensors") or {}
    ok = sum(isinstance(s, dict) and s.get("state") == "ok" for s in sensors.values())
    model = doc.get("model") if isinstance(doc.get("model"), dict) else None
    r = rates(doc, previous)
    health = doc.get("health")
    correction = health.get("correction_um") if isinstance(health, dict) else None  # the adaptation's, µm
    return [
        str(doc.get("cell", "?")),
        cell_state(doc),
        f"{ok}/{len(sensors)}",
        str(model.get("id")) if model else "none",
        _age(model.get("created"), now) if model else "-",
        _health(health),
        f"{correction * 1000.0:+.0f} nm" if isinstance(correction, int | float) else "-",  # -: off, or not said
        _actuator(doc),
        _rate(r.targets_per_min),
        _rate(r.refused_per_min),
    ]


def table(docs: Sequence[dict[str, Any]], previous: dict[str, dict[str, Any]] | None = None,
          now: datetime | None = None) -> str:
    """The compact table; ``previous`` (cell -> last document) turns the rates into the last interval's."""
    now = now or datetime.now(UTC)
    rows = [list(COLUMNS)] + [row(d, (previous or {}).get(str(d.get("cell"))), now) for d in docs]
    widths = [max(len(r[i]) for r in rows) for i in range(len(COLUMNS))]
    lines = ["  ".join(cell.ljust(widths[i]) for i, cell in enumerate(r)).rstrip() for r in rows]
    for doc in docs:
        lines += axis_lines(doc)
    since = "over the last interval" if previous else "averaged since each daemon started"
    return "\n".join([*lines, f"({len(docs)} cell{'s' if len(docs) != 1 else ''}; rates {since})"])


def render(docs: Sequence[dict[str, Any]], args: argparse.Namespace, previous: dict[str, dict[str, Any]]) -> str:
    if args.json:
        return json.dumps(list(docs))
    if not docs:
        return NO_CELL_HINT.format(key=status_key(args.cell, args.prefix), timeout=args.timeout)
    return table(docs, previous)


def watch(client: Client, args: argparse.Namespace, out: TextIO,
          sleep: Callable[[float], None] = time.sleep) -> int:
    """Refresh every ``args.watch`` seconds, ``args.count`` times (0: until Ctrl-C); exit 0."""
    terminal = out.isatty() and not args.json
    previous: dict[str, dict[str, Any]] = {}
    done = 0
    try:
        while True:
            started = time.monotonic()
            docs = client.statuses(args.cell, timeout_s=args.timeout)
            text = render(docs, args, previous)
            stamp = datetime.now().astimezone().strftime("%Y-%m-%d %H:%M:%S")
            if terminal:
                out.write(f"{CLEAR}nanodrift status  {stamp}  every {args.watch:g} s (Ctrl-C stops)\n{text}\n")
            elif args.json:
                out.write(text + "\n")
            else:
                out.write(f"--- {stamp}\n{text}\n\n")
            out.flush()
            previous = {str(d.get("cell")): d for d in docs}
            done += 1
            if args.count and done >= args.count:
                return 0
            sleep(max(args.watch - (time.monotonic() - started), 0.0))
    except KeyboardInterrupt:
        return 0


def main(args: argparse.Namespace) -> int:
    """One query (or ``--watch``); non-zero exit when no cell answers a single query."""
    client = open_client(args, None)
    try:
        if args.watch:
            return watch(client, args, sys.stdout)
        docs = client.statuses(args.cell, timeout_s=args.timeout)
    finally:
        client.close()
    if not docs:
        if args.json:
            print("[]")
        hint = NO_CELL_HINT.format(key=status_key(args.cell, args.prefix), timeout=args.timeout)
        print(f"nanodrift status: {hint}", file=sys.stderr)
        return 1
    print(render(docs, args, {}))
    return 0
