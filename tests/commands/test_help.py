"""``--help`` describes every option of every command, with defaults; ``--version`` (issue 13, item 4)."""

import argparse
import importlib.metadata
import re
import subprocess
import sys

import pytest

from daemon.cli import HANDLERS, build_parser, main
from drivers.simulated.effects import EFFECTS
from drivers.simulated.scenarios import SCENARIOS


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
    assert set(subparsers()) == set(HANDLERS)


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


def test_the_offline_tools_never_import_zenoh():
    run = subprocess.run([sys.executable, "-X", "importtime", "-m", "daemon.cli", "fit", "--help"],
                         capture_output=True, text=True, check=True)
    assert "import time:" in run.stderr and "zenoh" not in run.stderr


@pytest.mark.parametrize("command", ["validate", "target", "fit", "predict", "demo", "calibrate", "status"])
def test_units_for_people_are_micrometres_never_um(capsys, command):
    text = " ".join(help_of(capsys, command).split())
    assert not re.findall(r"(?<![\w-])um\b", text), f"{command} --help writes 'um' for µm"
    if command == "validate":
        assert "(default 1 µm, as [adapt] max_um)" in text
