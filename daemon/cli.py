"""``nanodrift``: one command line for the service, the procedures and the model tools.

This module only assembles: each command's module under ``daemon/commands`` owns its options
(``configure(parser)``) and its job (``main(args)``), and is imported only when its command runs (the
string table :data:`HANDLERS`), so ``nanodrift fit`` never loads zenoh and ``nanodrift --help`` loads no
command at all. What this module keeps is what every command shares: the one-line summaries of
``nanodrift --help`` (:data:`SUMMARIES`), the help format, and how a failure is reported.
"""

from __future__ import annotations

import argparse
import contextlib
import gc
import importlib
import sys
from collections.abc import Iterator, Sequence
from typing import Any, NoReturn

import structlog

from nanodrift import blas_threads  # noqa: F401  (first: before anything imports numpy)
from nanodrift.errors import UserError
from nanodrift.logs import json_line

#: command -> the module under daemon/commands whose ``configure(parser)`` declares its options and
#: whose ``main(args)`` runs it
HANDLERS = {
    "run": "nanodrift.commands.run",
    "demo": "nanodrift.commands.demo",
    "target": "nanodrift.commands.target",
    "status": "nanodrift.commands.status",
    "check-config": "nanodrift.commands.check_config",
    "confirm-output": "nanodrift.commands.confirm_output",
    "simulate": "nanodrift.commands.simulate",
    "calibrate": "nanodrift.commands.calibrate",
    "validate": "nanodrift.commands.validate",
    "fit": "nanodrift.commands.fit",
    "predict": "nanodrift.commands.predict",
    "restamp": "nanodrift.commands.restamp",
    "discover": "nanodrift.commands.discover",
    "acl": "nanodrift.commands.acl",
    "ioc": "nanodrift.commands.ioc",
}

#: command -> its line in ``nanodrift --help`` (and, capitalised, its ``--help`` description), in the
#: order they are listed: the service, procedures on the cell, model tools, discovery
SUMMARIES = {
    "run": "the daemon (simulated cell when no --config)",
    "demo": "calibrate, validate (Table I, the paper's five tests) and serve on the simulated cell (~1 min)",
    "target": "send targets to a running daemon and print the commands",
    "status": "every cell on the network (or one): sensors, model, health, actuator, counters",
    "check-config": "validate an operator config",
    "confirm-output": "say where an output is when the daemon cannot prove it (writes its state file)",
    "simulate": "data from the simulated cell",
    "calibrate": "the paper's calibration procedure (Fig. 6, 7)",
    "validate": "ISO 9283 validation, Table I",
    "fit": "identify the model from recorded data",
    "predict": "the command the model gives for each row",
    "restamp": "give a hand-edited model file the id of its new content",
    "discover": "find what the model misses, add it, show the gap shrink",
    "acl": "write the Zenoh access control for a list of cells and client groups",
    "ioc": "serve the cells over EPICS Channel Access (a motor-like set of PVs per axis)",
}


def version() -> str:
    """The installed distribution's version (what ``--version`` prints and model files record)."""
    import importlib.metadata  # here: only --version reads the distribution's METADATA (~5 ms of CPU)

    try:
        return importlib.metadata.version("nanodrift")
    except importlib.metadata.PackageNotFoundError:  # run from a source tree that was never installed
        return "0+unknown"


class _VersionAction(argparse._VersionAction):
    """``--version``: the version is read when the option is given, not each time the parser is built."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace, values: Any,
                 option_string: str | None = None) -> None:
        self.version = f"nanodrift {version()}"
        super().__call__(parser, namespace, values, option_string)


class _HelpFormatter(argparse.RawDescriptionHelpFormatter):
    """Every option's default after its help, except the ones that say nothing (None, off, empty)."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        default = action.default
        if "(default" in text or default in (None, argparse.SUPPRESS, [], "") or isinstance(default, bool):
            return text
        if not action.option_strings and action.nargs not in (argparse.OPTIONAL, argparse.ZERO_OR_MORE):
            return text
        shown = " ".join(map(str, default)) if isinstance(default, list | tuple) else str(default)
        return f"{text} (default: {shown.replace('%', '%%')})"


class _Parser(argparse.ArgumentParser):
    """argparse, except that with ``json_errors`` a usage error is one JSON log line, not usage text."""

    json_errors = False

    def error(self, message: str) -> NoReturn:
        if not self.json_errors:
            super().error(message)
        print(json_line("usage_error", "error", error=message, usage=self.format_usage().strip()), file=sys.stderr)
        self.exit(2)


def build_parser(*, json_errors_for_run: bool = False, only: str | None = None) -> argparse.ArgumentParser:
    """The whole command line; with ``only``, just that command's options are declared (its module is
    the only one imported), the others are listed by name and summary: what a run needs."""
    parser = _Parser(
        prog="nanodrift", description="Thermal-drift compensation for a piezo nanopositioning stage.",
        formatter_class=_HelpFormatter,
    )
    parser.json_errors = json_errors_for_run  # "unrecognized arguments" of run are reported up here
    parser.add_argument("--version", action=_VersionAction,
                        help="print the version and exit")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", parser_class=_Parser)
    for name, summary in SUMMARIES.items():
        p = sub.add_parser(name, help=summary, description=summary[:1].upper() + summary[1:] + ".",
                           formatter_class=_HelpFormatter)
        if name == "run":
            p.json_errors = json_errors_for_run
        if only is None or only == name:
            _module(name).configure(p)
    return parser


def _module(command: str) -> Any:
    return importlib.import_module(HANDLERS[command])


def main(argv: Sequence[str] | None = None) -> int:
    arguments = list(sys.argv[1:] if argv is None else argv)
    # `nanodrift run` with stderr not a terminal (systemd's journal, a pipe): every stderr line is JSON, its usage and
    # start-up errors too, so `journalctl -o cat | jq` never meets plain text. The other commands are for terminals
    # and scripts, and keep their plain `error:` lines
    json_errors = arguments[:1] == ["run"] and not sys.stderr.isatty()
    command = arguments[0] if arguments and arguments[0] in HANDLERS else None
    with _imports_kept(own_process=argv is None):  # the command's imports
        parser = build_parser(json_errors_for_run=json_errors, only=command or "")
    args = parser.parse_args(arguments)
    if not structlog.is_configured():  # `run` configures its own; elsewhere stdout is the command's (--json)
        structlog.configure(logger_factory=_stderr_logger)
    handler = _module(args.command).main
    try:
        return int(handler(args) or 0)
    except UserError as err:
        _say(args.command, json_errors, "error", f"error: {err}", event="run_failed", error=str(err))
        return 2
    except KeyboardInterrupt:
        _say(args.command, json_errors, "warning", "interrupted", event="run_interrupted")
        return 130


@contextlib.contextmanager
def _imports_kept(*, own_process: bool) -> Iterator[None]:
    """In the command's own process (the console script, ``python -m nanodrift.cli``: :func:`main` given no
    ``argv``), its imports run without automatic garbage collection, and what they built is then frozen
    (``gc.freeze``: left out of every later collection). Modules, classes and functions, ~75 000 objects that
    live as long as the process, would otherwise be scanned by ~100 collections that free next to nothing
    (about a thousand objects of import-time garbage, frozen with them) and again by every full pass: ~40 ms
    of CPU at each daemon's start. :func:`main` called inside another program (the tests' ``run_cli``) leaves
    that program's collector alone."""
    if not own_process:
        yield
        return
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        gc.freeze()
        if enabled:
            gc.enable()


def _stderr_logger(*_args: Any) -> structlog.PrintLogger:
    """Log lines (a driver's: pi_gcs' servo switched, serial_line's late answers) on stderr, whichever stream
    ``sys.stderr`` is when the line is written."""
    return structlog.PrintLogger(sys.stderr)


def _say(command: str, json_errors: bool, level: str, text: str, *, event: str, **fields: str) -> None:
    """The last line of a command that failed: plain for a terminal, a JSON log line for ``run``'s journal."""
    if json_errors:
        print(json_line(event, level, **fields), file=sys.stderr)
    else:
        print(f"nanodrift {command}: {text}", file=sys.stderr)


if __name__ == "__main__":
    sys.exit(main())
