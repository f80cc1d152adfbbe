"""``--help`` describes every option of every command, with defaults; ``--version`` (issue 13, item 4)."""

import argparse
import ast
import importlib
import importlib.metadata
import re
import subprocess
import sys
from pathlib import Path

import pytest

from nanodrift.cli import HANDLERS, SUMMARIES, build_parser, main
from nanodrift.drivers.simulated.effects import EFFECTS
from nanodrift.drivers.simulated.scenarios import SCENARIOS


def subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def help_of(capsys, *argv: str) -> str:
    with pytest.raises(SystemExit) as exit_info:
        main([*argv, "--help"])
    assert exit_info.value.code == 0
    return capsys.readouterr().out


def test_every_command_is_in_the_parser():
    assert set(subparsers()) == set(HANDLERS) == set(SUMMARIES)


def args_read(source: str) -> set[str]:
    """Every ``args.NAME`` a module reads, and every ``getattr(args, ...)`` (an option the parser may lack)."""
    read = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id == "args":
            read.add(node.attr)
        if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "getattr"
                and node.args and isinstance(node.args[0], ast.Name) and node.args[0].id == "args"):
            read.add(f"getattr({ast.unparse(node.args[1])})")
    return read


@pytest.mark.parametrize("command", sorted(HANDLERS))
def test_a_command_reads_only_the_options_its_parser_declares(command):
    """Each command module owns its parser (``configure``): every ``args.X`` its ``main`` reads is declared
    there, with its default, so no ``getattr(args, "x", default)`` is needed (nor allowed)."""
    declared = {action.dest for action in subparsers()[command]._actions} | {"command"}
    module = importlib.import_module(HANDLERS[command])
    read = args_read(Path(module.__file__).read_text())
    assert read <= declared, f"{command} reads {sorted(read - declared)}, which its parser does not declare"


def test_the_read_check_sees_getattr():
    assert args_read("def main(args):\n    return args.out, getattr(args, 'keep', None)\n") == {
        "out", "getattr('keep')"}


def test_only_the_command_that_runs_is_imported():
    """``nanodrift --help`` imports no command module, ``nanodrift fit --help`` only fit's; ``nanodrift run`` only
    its --config flag's helper, not the procedures' (``_cell``: preflight, follow checks, catalogues)."""
    code = ("import sys\nfrom nanodrift.cli import main\n"
            "try:\n    main(sys.argv[1:])\nexcept SystemExit:\n    pass\n"
            "print(sorted(m for m in sys.modules if m.startswith('nanodrift.commands.')))")
    for argv, expected in (([], "[]"), (["fit"], "['nanodrift.commands.fit']"),
                           (["run"], "['nanodrift.commands._config_flag', 'nanodrift.commands.run']")):
        run = subprocess.run([sys.executable, "-c", code, *argv, "--help"], capture_output=True, text=True, check=True)
        assert run.stdout.strip().splitlines()[-1] == expected


def test_every_option_of_every_command_has_a_description():
    undescribed = []
    for name, parser in subparsers().items():
        assert parser.description, f"{name} has no description"
        for action in parser._actions:
            if isinstance(action, argparse._HelpAction):
                continue
            if not (action.help or "").strip():
                undescribed.append(f"{name} {'/'.join(action.option_strings) or action.dest}")
    assert not undescribed, "options without help: " + ", ".join(undescribed)


@pytest.mark.parametrize(
    ("command", "shown"),
    [
        ("fit", ["--penter P", "(default: 0.05)", "(default: 0.1)", "(default: auto)", "_nm"]),
        ("demo", ["(default: 24)", "(default: 0)", "(default: 30)", "(default: test1 test2 test3 test4 test5)"]),
        ("run", ["(default: info)"]),
        ("validate", ["(default: 30)", "SVG"]),
        ("calibrate", ["(default: the config's [procedure] cycles, 24", "--no-output-check"]),
        ("target", ["(default: cell0)", "(default: 5.0)"]),
    ],
)
def test_defaults_are_shown(capsys, command, shown):
    text = " ".join(help_of(capsys, command).split())  # argparse wraps lines at the terminal's width
    for fragment in shown:
        assert fragment in text, f"{command} --help lacks {fragment!r}:\n{text}"


def test_simulate_help_lists_every_scenario_and_effect(capsys):
    text = help_of(capsys, "simulate")
    for option in ("--scenario", "--effects", "--cycles", "--seed", "--out"):
        assert option in text
    for name in [*SCENARIOS, *EFFECTS]:
        assert f"\n  {name} " in text, f"{name} is not listed in simulate --help"
    for default_value in ("tau_s=7200", "h_um=0.15"):
        assert default_value in text


def test_version(capsys):
    with pytest.raises(SystemExit) as exit_info:
        main(["--version"])
    assert exit_info.value.code == 0
    assert capsys.readouterr().out.strip() == f"nanodrift {importlib.metadata.version('nanodrift')}"


def test_the_version_is_read_only_when_asked_for(monkeypatch):
    """Reading the distribution's metadata costs every command ~5 ms of CPU: only ``--version`` pays it."""

    def no_version() -> str:
        raise AssertionError("the version was read to build the parser")

    monkeypatch.setattr("nanodrift.cli.version", no_version)
    build_parser()
    build_parser(only="run")


def test_a_command_process_freezes_its_imports_and_an_embedding_program_keeps_its_collector():
    """``gc.freeze`` after the command's imports (~40 ms less CPU at a daemon's start), in the command's own process
    only: ``main(argv)`` called by another program (run_cli) leaves its collector as it was."""
    code = ("import gc, sys\n"
            "from nanodrift.cli import main\n"
            "try:\n"
            "    main(['run', '--help'])\n"  # an embedding program's call
            "except SystemExit:\n"
            "    pass\n"
            "print('GC', gc.get_freeze_count(), gc.isenabled())\n"
            "sys.argv = ['nanodrift', 'run', '--help']\n"
            "try:\n"
            "    main()\n"  # the console script's
            "except SystemExit:\n"
            "    pass\n"
            "print('GC', gc.get_freeze_count(), gc.isenabled())\n")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    embedded, own = [line.split()[1:] for line in done.stdout.splitlines() if line.startswith("GC ")]
    assert embedded == ["0", "True"]
    frozen, enabled = own
    assert int(frozen) > 20_000 and enabled == "True", own  # the daemon's modules: ~75 000 objects


def test_the_offline_tools_never_import_zenoh():
    run = subprocess.run([sys.executable, "-X", "importtime", "-m", "nanodrift.cli", "fit", "--help"],
                         capture_output=True, text=True, check=True)
    assert "import time:" in run.stderr and "zenoh" not in run.stderr


@pytest.mark.parametrize("command", ["validate", "target", "fit", "predict", "demo", "calibrate", "status"])
def test_units_for_people_are_micrometres_never_um(capsys, command):
    text = " ".join(help_of(capsys, command).split())
    assert not re.findall(r"(?<![\w-])um\b", text), f"{command} --help writes 'um' for µm"
    if command == "validate":
        assert "(default 1 µm, as [adapt] max_um)" in text
