"""``nanodrift``: one command line for the service, the procedures and the model tools.

The parser lists every command of the public contract; each handler lives in the module that owns
the job and is imported only when its command runs, so ``nanodrift fit`` never loads zenoh. The
simulated cell's scenario and effect catalogues are imported here (numpy only, no zenoh) so that
``simulate --help`` lists them from the one place they are defined.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.metadata
import sys
import textwrap
from collections.abc import Sequence
from typing import Any, NoReturn

from daemon.errors import UserError
from daemon.logs import json_line
from drivers.simulated.effects import EFFECTS
from drivers.simulated.scenarios import SCENARIOS

#: command -> the module under daemon/commands whose ``main(args)`` runs it
HANDLERS = {
    "run": "daemon.commands.run",
    "demo": "daemon.commands.demo",
    "target": "daemon.commands.target",
    "check-config": "daemon.commands.check_config",
    "simulate": "daemon.commands.simulate",
    "calibrate": "daemon.commands.calibrate",
    "validate": "daemon.commands.validate",
    "fit": "daemon.commands.fit",
    "predict": "daemon.commands.predict",
    "discover": "daemon.commands.discover",
    "restamp": "daemon.commands.restamp",
    "status": "daemon.commands.status",
}


def version() -> str:
    """The installed distribution's version (what ``--version`` prints and model files record)."""
    try:
        return importlib.metadata.version("nanodrift")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "0+unknown"


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option's default after its help, except the ones that say nothing (None, off, empty)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if "(default" in text or default is None or default is argparse.SUPPRESS or isinstance(default, bool):
            return text
        if default in ([], ""):
            return text
        if not action.option_strings and action.nargs not in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return text
        shown = " ".join(map(str, default)) if isinstance(default, list | tuple) else str(default)
        return f"{text} (default: {shown.replace('%', '%%')})"


def _epilog(title: str, items: dict[str, str]) -> str:
    width = max(len(name) for name in items) + 2
    lines = [f"{title}:"]
    for name, text in items.items():
        wrapped = textwrap.wrap(text, 96 - width) or [""]
        lines.append(f"  {name:<{width}}{wrapped[0]}")
        lines.extend(f"  {'':<{width}}{more}" for more in wrapped[1:])
    return "\n".join(lines)


def _scenario_epilog() -> str:
    return _epilog("scenarios", {name: s.description for name, s in SCENARIOS.items()})


def _effects_epilog() -> str:
    items = {
        name: f"{spec.physics} (parameters: "
        + ", ".join(f"{key}={value:g}" for key, value in spec.defaults.items()) + ")"
        for name, spec in EFFECTS.items()
    }
    return _epilog("effects (--effects name[:param=value...],name...)", items)


def _zenoh_flags(p: argparse.ArgumentParser) -> None:
    """The zenoh-python examples' conventions; they override the config file."""
    p.add_argument("-l", "--listen", action="append", default=[], metavar="EP",
                   help="endpoint to listen on, e.g. tcp/127.0.0.1:7447 (repeatable; overrides [zenoh] listen)")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                   help="endpoint to connect to (repeatable; overrides [zenoh] connect)")
    p.add_argument("--mode", choices=["peer", "client", "router"],
                   help="zenoh session mode (overrides [zenoh] mode, whose default is peer)")


def _demo_zenoh_flags(p: argparse.ArgumentParser) -> None:
    """The demo starts its own daemon and client on loopback; these pick the endpoints."""
    p.add_argument("-l", "--listen", action="append", default=[], metavar="EP",
                   help="endpoint the demo's daemon listens on (default: a free port on 127.0.0.1)")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                   help="endpoint the demo's client connects to (default: the --listen endpoint)")
    p.add_argument("--mode", choices=["peer", "client", "router"],
                   help="accepted as for run; the demo's daemon is always a peer and its client a client")


def _simulation_flags(p: argparse.ArgumentParser, default_scenario: str) -> None:
    """For the simulated cell (no --config, or a config with simulated sensors): override [simulation]."""
    p.add_argument("--scenario", metavar="S",
                   help=f"simulated room history, one of {', '.join(SCENARIOS)} (default: {default_scenario} "
                        "with no --config, else the config's [simulation] scenario)")
    p.add_argument("--effects", metavar="a,b",
                   help=f"hidden effects of the simulated cell, from {', '.join(EFFECTS)} "
                        "(default: none, or the config's)")
    p.add_argument("--seed", type=int, metavar="N",
                   help="simulation seed (default: 0, or the config's); the paper's test N runs with seed*100+N, "
                        "as in demo")


def _add(sub: Any, name: str, help_text: str, epilog: str | None = None) -> _Parser:  # sub: parser_class=_Parser
    return sub.add_parser(name, help=help_text, description=help_text[:1].upper() + help_text[1:] + ".",
                          epilog=epilog, formatter_class=_HelpFormatter)


def _output_check_flag(p: argparse.ArgumentParser) -> None:
    """Procedures on hardware with [actuator] kind = "zenoh" refuse to start with nobody applying the steps."""
    p.add_argument("--no-output-check", action="store_true",
                   help="start even when no output node is subscribed to nanodrift/<cell>/command")


class _Parser(argparse.ArgumentParser):
    """argparse, except that with ``json_errors`` a usage error is one JSON log line, not usage text."""

    json_errors = False

    def error(self, message: str) -> NoReturn:
        if not self.json_errors:
            super().error(message)
        print(json_line("usage_error", "error", error=message, usage=self.format_usage().strip()), file=sys.stderr)
        self.exit(2)


def json_errors_wanted(argv: Sequence[str]) -> bool:
    """``nanodrift run`` with stderr not a terminal (systemd's journal, a pipe): every stderr line is
    JSON, its usage and start-up errors too, so ``journalctl -o cat | jq`` never meets plain text.
    The other commands are for terminals and scripts, and keep their plain ``error:`` lines."""
    return list(argv[:1]) == ["run"] and not sys.stderr.isatty()


def build_parser(*, json_errors_for_run: bool = False) -> argparse.ArgumentParser:
    parser = _Parser(
        prog="nanodrift", description="Thermal-drift compensation for a piezo nanopositioning stage.",
        formatter_class=_HelpFormatter,
    )
    parser.json_errors = json_errors_for_run  # "unrecognized arguments" of run are reported up here
    parser.add_argument("--version", action="version", version=f"nanodrift {version()}",
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)

    # --- the service ---
    p = _add(sub, "run", "the daemon (simulated cell when no --config)")
    p.json_errors = json_errors_for_run
    p.add_argument("--config", metavar="F", help="operator config (TOML); none: the built-in simulated cell")
    _zenoh_flags(p)
    p.add_argument("--no-multicast-scouting", action="store_true", help="do not look for peers by UDP multicast")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"],
                   help="the least severe log lines printed")

    p = _add(sub, "demo", "calibrate, validate (Table I, the paper's five tests) and serve on the simulated cell "
             "(~1 min)", epilog=_scenario_epilog())
    _demo_zenoh_flags(p)
    p.add_argument("--tests", nargs="+", default=["test1", "test2", "test3", "test4", "test5"], metavar="T",
                   help="the paper's tests to run: test1 (without compensation), test2-test4 (inside the "
                        "training range), test5 (outside it)")
    p.add_argument("--cycles", type=int, default=30, metavar="N",
                   help="ISO 9283 validation sweeps per test (the paper: 30)")
    p.add_argument("--calibration-cycles", type=int, default=24, metavar="N",
                   help="calibration sweeps of the 'train' room before the tests (the paper: 24)")
    p.add_argument("--speed", type=float, default=50.0,
                   help="simulated seconds per wall second of the served cell (the serving step)")
    p.add_argument("--seed", type=int, default=0, metavar="N",
                   help="simulation seed: the same seed gives the same Table I as validate --seed N")
    p.add_argument("--keep", metavar="DIR", help="keep the model, data, Table I (JSON), config and daemon log in DIR")

    p = _add(sub, "target", "send targets to a running daemon and print the commands")
    p.add_argument("x", nargs="+", type=float, metavar="X", help="target positions (µm)")
    p.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                   help="endpoint of the daemon, e.g. tcp/127.0.0.1:7447 (repeatable; default: scouting)")
    p.add_argument("--mode", choices=["peer", "client"], default=None,
                   help="zenoh session mode (default: client with -e, else peer)")
    p.add_argument("--cell", default="cell0", help="cell name (key prefix nanodrift/<cell>)")
    p.add_argument("--timeout", type=float, default=5.0, help="seconds to wait for each answer")
    p.add_argument("--json", action="store_true", help="print JSON lines")
    p.add_argument("--zenoh-config", metavar="F",
                   help="a zenoh json5 config (credentials, TLS), e.g. config/zenoh-client.example.json5")

    p = _add(sub, "status", "every cell on the network (or one): sensors, model, health, actuator, counters",
             epilog=textwrap.fill(
                 "columns: CELL, STATE (ok | degraded: a sensor not ok | extrapolating | no-model | stalled: "
                 "a sensor poller stopped), SENSORS ok/total, MODEL id and MODEL AGE (since it was made), "
                    "HEALTH (state and residual RMS, when the daemon measures it), ACTUATOR (kind and state), "
                    "TARGETS/MIN and REFUSED/MIN (averaged since the daemon started; with --watch, over the "
                    "last interval). Exit 1 when no cell answers.", 96))
    p.add_argument("-e", "--connect", action="append", default=[], metavar="EP",
                   help="endpoint of a daemon or router, e.g. tcp/127.0.0.1:7447 (repeatable; default: scouting)")
    p.add_argument("--mode", choices=["peer", "client"], default=None,
                   help="zenoh session mode (default: client with -e, else peer)")
    p.add_argument("--cell", default=None, metavar="C",
                   help="only this cell (key nanodrift/C/status; default: every cell, nanodrift/*/status)")
    p.add_argument("--json", action="store_true", help="print the status documents as a JSON list")
    p.add_argument("--watch", type=float, default=None, metavar="S",
                   help="refresh every S seconds until Ctrl-C: in place on a terminal, a block per refresh "
                        "otherwise")
    p.add_argument("--count", type=int, default=0, metavar="N",
                   help="with --watch: stop after N refreshes (default: until Ctrl-C)")
    p.add_argument("--timeout", type=float, default=2.0, metavar="S",
                   help="seconds to collect the cells' replies")
    p.add_argument("--zenoh-config", metavar="F",
                   help="a zenoh json5 config (credentials, TLS), e.g. config/zenoh-client.example.json5")

    p = _add(sub, "check-config", "validate an operator config")
    p.add_argument("file", metavar="F", help="the operator config (TOML) to check")
    p.add_argument("--strict", action="store_true",
                   help="warnings (a channel the model needs is missing, unused sensors) are errors too")

    # --- procedures on the cell ---
    p = _add(sub, "simulate", "data from the simulated cell", epilog=_scenario_epilog() + "\n\n" + _effects_epilog())
    p.add_argument("--scenario", required=True, metavar="S",
                   help=f"room history and trajectory, one of {', '.join(SCENARIOS)} (see below)")
    p.add_argument("--effects", default="", metavar="a,b",
                   help="hidden effects to switch on, with optional parameters, e.g. "
                        "thermal_lag:tau_s=1800,creep (see below; default: none)")
    p.add_argument("--cycles", type=int, metavar="N",
                   help="sweeps to record (default: the scenario's: 24 calibration or 30 validation sweeps)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="noise and room seed: same seed, same data")
    p.add_argument("--out", required=True, metavar="F.csv", help="the CSV to write (data contract columns)")

    p = _add(sub, "calibrate", "the paper's calibration procedure (Fig. 6, 7)", epilog=_scenario_epilog())
    p.add_argument("--config", metavar="F", help="operator config (TOML); none: the built-in simulated cell")
    p.add_argument("--out", required=True, metavar="M.json", help="the model file to write")
    p.add_argument("--data", metavar="D.csv", help="where the recorded steps go (default: beside --out)")
    p.add_argument("--cycles", type=int, metavar="N",
                   help="calibration sweeps (default: the config's [procedure] cycles, 24 as in the paper)")
    p.add_argument("--resume", action="store_true", help="continue an interrupted run from --data")
    _simulation_flags(p, "train")
    _output_check_flag(p)

    p = _add(sub, "validate", "ISO 9283 validation, Table I", epilog=_scenario_epilog())
    p.add_argument("--config", metavar="F", help="operator config (TOML); none: the built-in simulated cell")
    p.add_argument("--model", required=True, metavar="M.json", help="the model to validate")
    p.add_argument("--cycles", type=int, default=30, metavar="N", help="validation sweeps (ISO 9283: 30)")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of Table I")
    p.add_argument("--report", metavar="DIR",
                   help="also write Table I, JSON, raw steps and figures (PNG + SVG) into DIR")
    p.add_argument("--no-compensation", action="store_true", help="command the targets as they are (test 1)")
    p.add_argument("--adapt", action="store_true",
                   help="correct the commands with the daemon's bias tracker ([adapt] mode = \"bias\"), fed by "
                        "each step's residual")
    p.add_argument("--adapt-tau-s", type=float, default=600.0, metavar="S",
                   help="the tracker's time constant (default 600 s, as [adapt] tau_s)")
    p.add_argument("--adapt-max-um", type=float, default=1.0, metavar="UM",
                   help="clamp on the correction (default 1 µm, as [adapt] max_um)")
    _simulation_flags(p, "test2")
    _output_check_flag(p)

    # --- model tools (offline) ---
    p = _add(sub, "fit", "identify the model from recorded data")
    p.add_argument("data", metavar="D.csv", nargs="+",
                   help="recorded data (CSV: t_s, x_um, q_um, one column per channel); several files (a "
                        "calibration plus recorded operation) are fitted together, each a run of its own")
    p.add_argument("--out", required=True, metavar="M.json", help="the model file to write")
    p.add_argument("--order", default="auto", help="geometric order n1, or auto (held-out cycles)")
    p.add_argument("--exclude", action="append", default=[], metavar="CH",
                   help="leave a channel out (repeatable)")
    p.add_argument("--penter", type=float, default=0.05, metavar="P",
                   help="stepwise: a term enters when its p-value is below P")
    p.add_argument("--premove", type=float, default=0.10, metavar="P",
                   help="stepwise: a term leaves when its p-value is above P (>= --penter)")
    p.add_argument("--json", action="store_true",
                   help="print the summary as JSON (residuals in nm, keys ending _nm)")

    p = _add(sub, "predict", "the command the model gives for each row")
    p.add_argument("--model", required=True, metavar="M.json", help="the model to apply")
    p.add_argument("data", metavar="D.csv", help="data with t_s, x_um and the model's channels")
    p.add_argument("--out", required=True, metavar="P.csv", help="D plus columns q_pred_um and q_sigma_um (µm)")

    p = _add(sub, "restamp", "give a hand-edited model file the id of its new content")
    p.add_argument("model", metavar="M.json", help="the edited model file")
    p.add_argument("--out", metavar="M2.json", help="write here instead of over M.json")

    # --- discovery (offline) ---
    p = _add(sub, "discover", "find what the model misses, add it, show the gap shrink")
    p.add_argument("data", metavar="D.csv", nargs="+",
                   help="recorded data (CSV) the model is tested against; several files are runs of their own")
    p.add_argument("--model", required=True, metavar="M.json", help="the model to extend")
    p.add_argument("--out", required=True, metavar="M2.json", help="the extended model file to write")
    p.add_argument("--report", metavar="DIR", help="also write report.md and figures into DIR")
    p.add_argument("--json", action="store_true", help="print the result as JSON")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    json_errors = json_errors_wanted(arguments)
    args = build_parser(json_errors_for_run=json_errors).parse_args(arguments)
    handler = importlib.import_module(HANDLERS[args.command]).main
    try:
        return int(handler(args) or 0)
    except UserError as err:
        _say(args.command, json_errors, "error", f"error: {err}", event="run_failed", error=str(err))
        return 2
    except KeyboardInterrupt:
        _say(args.command, json_errors, "warning", "interrupted", event="run_interrupted")
        return 130


def _say(command: str, json_errors: bool, level: str, text: str, *, event: str, **fields: str) -> None:
    """The last line of a command that failed: plain for a terminal, a JSON log line for ``run``'s journal."""
    if json_errors:
        print(json_line(event, level, **fields), file=sys.stderr)
    else:
        print(f"nanodrift {command}: {text}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
