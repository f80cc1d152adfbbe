"""``systemd/nanodrift@.service`` (issue 29): one daemon per cell, the instance naming its config.

Both units pass ``systemd-analyze verify`` (with the program they name pointed at this install's
``nanodrift``: the shipped path ``/opt/nanodrift/bin/nanodrift`` exists only on a lab's host); a
unit with a bad line fails it (the control). The template scores the plain unit's exposure (≤ 1.2)
and differs from it only in the per-instance settings.
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
SYSTEMD = REPO / "systemd"
SHIPPED_PROGRAM = "/opt/nanodrift/bin/nanodrift"
NEEDS_SYSTEMD = pytest.mark.skipif(shutil.which("systemd-analyze") is None,
                                   reason="systemd-analyze is not installed here (no systemd)")


def installed_program() -> str:
    """This environment's ``nanodrift`` console script (beside the running Python)."""
    program = Path(sys.executable).parent / "nanodrift"
    assert program.exists(), f"{program}: install nanodrift (pip install -e .) to run this test"
    return str(program)


def unit_copy(directory: Path, name: str, replace: tuple[str, str] | None = None) -> Path:
    """The shipped unit under its own name, running this install's program (and one edit, for the control)."""
    text = (SYSTEMD / name).read_text().replace(SHIPPED_PROGRAM, installed_program())
    if replace is not None:
        assert replace[0] in text
        text = text.replace(*replace)
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / name
    path.write_text(text)
    return path


def verify(path: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["systemd-analyze", "verify", "--man=no", str(path)], capture_output=True, text=True,
                          timeout=60)


@NEEDS_SYSTEMD
@pytest.mark.parametrize("name", ["nanodrift.service", "nanodrift@.service"])
def test_both_units_pass_systemd_analyze_verify(tmp_path: Path, name: str) -> None:
    result = verify(unit_copy(tmp_path, name))
    assert result.returncode == 0, result.stdout + result.stderr
    assert result.stderr.strip() == "", result.stderr


@NEEDS_SYSTEMD
def test_control_a_unit_with_a_bad_line_fails_verify(tmp_path: Path) -> None:
    bad = unit_copy(tmp_path, "nanodrift@.service", ("Type=notify", "Type=notifyy"))
    result = verify(bad)
    assert "notifyy" in result.stdout + result.stderr


@NEEDS_SYSTEMD
def test_an_instance_of_the_template_is_hardened_to_1_2_or_better(tmp_path: Path) -> None:
    unit_copy(tmp_path, "nanodrift@.service")
    result = subprocess.run(["systemd-analyze", "security", "--offline=yes", str(tmp_path / "nanodrift@cell0.service")],
                            capture_output=True, text=True, timeout=60)
    match = re.search(r"Overall exposure level for nanodrift@cell0\.service: (\d+\.\d+)", result.stdout + result.stderr)
    assert match, result.stdout + result.stderr
    assert float(match.group(1)) <= 1.2, result.stdout


def settings(name: str) -> dict[str, list[str]]:
    found: dict[str, list[str]] = {}
    for line in (SYSTEMD / name).read_text().splitlines():
        if "=" in line and not line.lstrip().startswith(("#", "[")):
            key, value = line.split("=", 1)
            found.setdefault(key.strip(), []).append(value.strip())
    return found


def test_the_template_runs_the_instances_config_in_its_own_state_directory() -> None:
    unit = settings("nanodrift@.service")
    assert unit["ExecStart"] == [f"{SHIPPED_PROGRAM} run --config /etc/nanodrift/%i.toml"]
    assert unit["ExecStartPre"] == [f"{SHIPPED_PROGRAM} check-config /etc/nanodrift/%i.toml"]
    assert unit["StateDirectory"] == ["nanodrift/%i"]  # the durable last-written outputs are per cell
    assert "%i" in unit["Description"][0]


def test_the_template_differs_from_the_plain_unit_only_in_what_is_per_instance() -> None:
    plain, template = settings("nanodrift.service"), settings("nanodrift@.service")
    per_instance = {"Description", "ExecStart", "ExecStartPre", "StateDirectory"}
    assert set(plain) == set(template)
    assert {key for key in plain if plain[key] != template[key]} == per_instance
