"""Handlers for ``nanodrift run | target | check-config | demo`` (the parser is in daemon/cli.py)."""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

from daemon.config import Config, load_config, missing_model_channels
from daemon.errors import UserError


def zenoh_overrides(args: argparse.Namespace) -> dict[str, Any]:
    """``-l``/``-e``/``--mode``: they replace what the config file says (zenoh examples' rule)."""
    overrides: dict[str, Any] = {
        "mode": getattr(args, "mode", None),
        "listen": list(getattr(args, "listen", None) or []),
        "connect": list(getattr(args, "connect", None) or []),
    }
    if getattr(args, "no_multicast_scouting", False):
        overrides["multicast_scouting"] = False
    return overrides


def run_command(args: argparse.Namespace) -> int:
    from daemon.logs import configure_logging
    from daemon.service import run_service

    configure_logging(getattr(args, "log_level", None) or "info")
    config = load_config(args.config)
    return run_service(config, config_path=args.config, zenoh_overrides=zenoh_overrides(args))


def config_warnings(config: Config) -> list[str]:
    """What an operator should know although the file is valid: model problems, missing channels."""
    from daemon.model.model import ModelFileError, load_model

    try:
        model = load_model(config.model.path)
    except ModelFileError as error:
        return [f"model.path: {error} (the daemon starts but refuses targets until a model is there)"]
    missing = missing_model_channels(config, model.channels)
    warnings = []
    if missing:
        warnings.append(
            f"model {model.id} needs channel(s) {', '.join(missing)} that no temperature sensor provides: "
            "targets will be refused until they are configured"
        )
    unused = [s.name for s in config.sensors if s.role == "temperature" and s.name not in model.channels]
    if unused:
        warnings.append(f"sensor(s) {', '.join(unused)} not used by model {model.id} (monitoring only)")
    return warnings


def check_config_command(args: argparse.Namespace) -> int:
    config = load_config(args.file)
    names = ", ".join(f"{s.name} ({s.kind}, {s.role})" for s in config.sensors)
    print(f"{args.file}: ok: cell {config.cell!r}, {len(config.sensors)} sensor(s): {names}")
    print(f"  model: {config.model.path}")
    for warning in config_warnings(config):
        print(f"{args.file}: warning: {warning}", file=sys.stderr)
    return 0


def _format_command(doc: dict[str, Any]) -> str:
    temps = " ".join(f"{k}={v:.3f}" for k, v in (doc.get("temperatures_c") or {}).items())
    extra = f" EXTRAPOLATING {','.join(doc['extrapolating'])}" if doc.get("extrapolating") else ""
    return (f"x {doc['x_um']:.4f} um -> q {doc['q_um']:.4f} um, {doc['voltage_v']:.5f} V "
            f"[model {doc['model']}; {temps}]{extra}")


def target_command(args: argparse.Namespace) -> int:
    """A client: each target through the ``compensate`` queryable; non-zero exit if any is refused."""
    import zenoh

    from daemon.bus import Keys, session_config

    keys = Keys(args.cell)
    conf = session_config(
        mode=args.mode or ("client" if args.connect else "peer"),
        connect=args.connect,
        multicast_scouting=not args.connect,  # an explicit endpoint needs no scouting
    )
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as error:
        raise UserError(f"cannot open a zenoh session ({', '.join(args.connect) or 'scouting'}): {error}") from None
    failures = 0
    try:
        for index, x in enumerate(args.x):
            request = json.dumps({"x_um": x, "id": index})
            answer: dict[str, Any] | None = None
            ok = False
            for reply in session.get(keys.compensate, payload=request, timeout=args.timeout):
                sample = reply.ok
                raw = sample.payload.to_bytes() if sample is not None else reply.err.payload.to_bytes()
                ok = sample is not None
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
                print(f"x {x:g} um refused: {answer.get('error')}", file=sys.stderr)
    finally:
        session.close()
    return 1 if failures else 0


def demo_command(args: argparse.Namespace) -> int:
    from daemon.demo import run_demo

    return run_demo(args)
