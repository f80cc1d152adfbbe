"""``nanodrift target X...``: a client that sends targets to a running daemon and prints the commands.

A target nobody answers is explained once: the cells that answer ``status`` on the network are asked
for (the query of ``nanodrift status``), so a wrong ``--cell`` is told from a daemon that is not running.

A multi-axis cell's target is one comma-separated point in the cell's axis order (``240,100``), the
axes learnt from the cell's ``status``; a one-axis cell's stays one number, and nothing else is asked.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from nanodrift.client import Refused
from nanodrift.commands._client import add_client_flags, open_client


def configure(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("x", nargs="+", type=_point, metavar="X", help=(
        "target positions (µm); a multi-axis cell: one comma-separated point per target in its axis order, "
        "e.g. 240,100 (put -- before a point that starts with -)"))
    add_client_flags(parser, endpoint_of="the daemon")
    parser.add_argument("--cell", default="cell0",
                        help="cell name (keys <prefix>/<cell>/..., nanodrift/<cell> by default)")
    parser.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for each answer")
    parser.add_argument("--json", action="store_true", help="print JSON lines")


def _point(text: str) -> float | tuple[float, ...]:
    """One number (a one-axis target), or a comma-separated point (a multi-axis cell's)."""
    if "," not in text:
        return float(text)
    return tuple(float(part) for part in text.split(","))


_point.__name__ = "float"  # argparse's message for a bad value stays "invalid float value: 'abc'"


def _shown(target: float | tuple[float, ...]) -> str:
    return ",".join(f"{v:g}" for v in target) if isinstance(target, tuple) else f"{target:g}"


def _format_command(doc: dict[str, Any]) -> str:
    """``x 240.0000 µm -> q 239.6231 µm, 4.79246 V [model m-…; σ 0.0185 µm; T1=21.800 °C, …]``; a cell of several
    axes ``x 240.0000 y 100.0000 µm -> q x … y … µm, x … y … V [model m-…; σ x 0.0185 y 0.0210 µm; …]`` (with
    adaptation, ``correction …`` and ``σ adapted …`` after the model's σ)."""
    several = isinstance(doc["q_um"], dict)
    axes = list(doc["q_um"]) if several else ["x"]

    def values(value: Any, fmt: str, *, every_axis: bool = False) -> str:
        """One axis' number, or ``x … y …`` over the axes the mapping names (or every axis); unknown: no number."""
        def one(v: Any) -> str:
            return format(v, fmt) if isinstance(v, int | float) else "unknown"

        if not several:
            return one(value)
        found = value if isinstance(value, dict) else {}
        return " ".join(f"{a} {one(found.get(a))}" for a in axes if every_axis or a in found)

    def carried(value: Any) -> bool:  # the payload has it (adaptation on)
        return isinstance(value, dict) if several else isinstance(value, int | float)

    sigma = values(doc.get("q_sigma_um"), ".4f", every_axis=True)
    details = [f"model {doc['model']}", "σ unknown" if sigma == "unknown" else f"σ {sigma} µm"]
    if carried(doc.get("correction_um")):
        details.append(f"correction {values(doc['correction_um'], '+.4f')} µm")
    if carried(doc.get("q_sigma_adapted_um")):  # the corrected command's σ: what the bias tracker leaves
        details.append(f"σ adapted {values(doc['q_sigma_adapted_um'], '.4f')} µm")
    temps = ", ".join(f"{k}={v:.3f} °C" for k, v in (doc.get("temperatures_c") or {}).items())
    if temps:
        details.append(temps)
    extra = f" EXTRAPOLATING {','.join(doc['extrapolating'])}" if doc.get("extrapolating") else ""
    target = " ".join(f"{a} {doc[f'{a}_um']:.4f}" for a in axes)
    return (f"{target} µm -> q {values(doc['q_um'], '.4f', every_axis=True)} µm, "
            f"{values(doc['voltage_v'], '.5f', every_axis=True)} V [{'; '.join(details)}]{extra}")


def main(args: argparse.Namespace) -> int:
    """A client: each target through :meth:`nanodrift.Client.move` (the ``compensate`` queryable, not waiting
    for ``done``); non-zero exit if any is refused."""
    cell = open_client(args, args.cell)
    failures = 0
    try:
        axes: tuple[str, ...] | None = None
        if any(isinstance(x, tuple) for x in args.x):
            try:  # the cell's axes from its status (("x",) for a one-axis cell)
                doc = cell.status(timeout_s=args.timeout)
            except TimeoutError:
                print(f"no answer from {cell.keys.status} within {args.timeout:g} s to learn the cell's axes (is the "
                      "daemon running? -e tcp/HOST:PORT)", file=sys.stderr)
                return 1
            axes = tuple(doc["axes"]) if isinstance(doc.get("axes"), dict) else ("x",)
            wrong = [_shown(x) for x in args.x if len(x if isinstance(x, tuple) else (x,)) != len(axes)]
            if wrong:
                print(f"cell {args.cell} has axes {', '.join(axes)}: each target is one point of {len(axes)} "
                      f"comma-separated values in that order (got {', '.join(wrong)})", file=sys.stderr)
                return 2
            args.x = [x if isinstance(x, tuple) else (x,) for x in args.x]
        for index, x in enumerate(args.x):
            target: float | dict[str, float] = x if not isinstance(x, tuple) else dict(
                zip(axes or (), x, strict=True))
            try:
                answer, ok = dict(cell.move(target, wait=False, timeout_s=args.timeout, id=index).payload), True
            except Refused as refused:
                answer, ok = refused.payload, False
            except TimeoutError as unanswered:  # the cell does not answer: why, asked once by the client
                answer, ok = {"id": index, "error": str(unanswered)}, False
            failures += not ok
            if args.json:
                print(json.dumps(answer))
            elif ok:
                print(_format_command(answer))
            else:  # a one-axis target is named by its axis, a point by its values
                print(f"{'' if isinstance(x, tuple) else 'x '}{_shown(x)} µm refused: {answer.get('error')}",
                      file=sys.stderr)
    finally:
        cell.close()
    return 1 if failures else 0
