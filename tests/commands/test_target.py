"""``nanodrift target``: a client of the compensate queryable; prints commands, non-zero if refused."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.daemon_harness import REPO, TEMPS, Served, expected_q, run_cli

from nanodrift.commands import target as target_command


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory):
    s = Served(tmp_path_factory.mktemp("cli"), "clicell").start()
    yield s
    s.close()


def target(served: Served, *args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift target ARGS`` towards the served cell, run by the console script's own ``main`` in this process:
    what it prints on stdout (and Python's stderr). A process of its own costs half a second of CPU; the tests
    that judge everything the process writes on stderr (zenoh's lines included) use :func:`target_process`."""
    return run_cli("target", *args, "-e", f"tcp/127.0.0.1:{served.port}", "--cell", served.cell)


def target_process(served: Served, *args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift target ARGS`` in a process of its own: every line it writes on stderr."""
    return subprocess.run(
        [sys.executable, "-m", "nanodrift.cli", "target", *args, "-e", f"tcp/127.0.0.1:{served.port}",
         "--cell", served.cell],
        capture_output=True, text=True, cwd=REPO, timeout=60,
    )


def test_target_prints_commands_as_json_lines(served: Served) -> None:
    result = target(served, "0", "120.5", "480", "--json")
    assert result.returncode == 0, result.stderr
    lines = [json.loads(line) for line in result.stdout.splitlines()]
    assert [line["x_um"] for line in lines] == [0.0, 120.5, 480.0]
    assert [line["id"] for line in lines] == [0, 1, 2]
    for line in lines:
        assert line["q_um"] == pytest.approx(expected_q(line["x_um"], TEMPS), abs=1e-9)


def test_target_readable_output_and_refusals_exit_non_zero(served: Served) -> None:
    result = target_process(served, "100", "750")
    assert result.returncode == 1
    assert "x 100.0000 µm -> q" in result.stdout and " µm, " in result.stdout and served.model.id in result.stdout
    assert "x 750 µm refused: x_um 750 outside the workspace [0, 500] µm" in result.stderr, result.stderr
    assert not re.search(r"\bum\b", result.stdout + result.stderr)  # µm for people; x_um stays a JSON key


def test_target_without_a_daemon_says_so(tmp_path: Path) -> None:
    result = run_cli("target", "1", "--cell", "nobody", "--timeout", "0.5", "-e", f"tcp/127.0.0.1:{1}")
    assert result.returncode != 0
    assert "cannot open a zenoh session" in result.stderr or "no answer" in result.stderr


def test_target_readable_output_shows_sigma_and_degrees(served: Served) -> None:
    result = target(served, "240")
    assert result.returncode == 0, result.stderr
    for channel, value in TEMPS.items():
        assert f"{channel}={value:.3f} °C" in result.stdout, result.stdout
    # the harness' model has no covariance nor fit RMS: its commands' σ is null, and said to be unknown
    assert json.loads(target(served, "240", "--json").stdout)["q_sigma_um"] is None
    assert f"[model {served.model.id}; σ unknown; T1=" in result.stdout, result.stdout


def test_a_commands_sigma_and_correction_are_printed_in_micrometres() -> None:
    doc = {"id": 0, "x_um": 240.0, "q_um": 239.6231, "voltage_v": 4.79246, "temperatures_c": {"T1": 21.8},
           "model": "m-1", "t": 0.0, "extrapolating": ["T1"], "q_sigma_um": 0.01854, "correction_um": -0.0123,
           "q_sigma_adapted_um": 0.03107}
    assert target_command._format_command(doc) == (
        "x 240.0000 µm -> q 239.6231 µm, 4.79246 V [model m-1; σ 0.0185 µm; correction -0.0123 µm; "
        "σ adapted 0.0311 µm; T1=21.800 °C] EXTRAPOLATING T1")
    cell = {"id": 0, "x_um": 1.0, "y_um": 2.0, "q_um": {"x": 1.1, "y": 2.2}, "voltage_v": {"x": 0.1, "y": 0.2},
            "q_sigma_um": {"x": 0.02, "y": None}, "temperatures_c": {}, "model": "m-2", "t": 0.0,
            "extrapolating": [], "correction_um": {"x": -0.3, "y": 0.2}, "q_sigma_adapted_um": {"x": 0.3, "y": None}}
    assert target_command._format_command(cell) == (
        "x 1.0000 y 2.0000 µm -> q x 1.1000 y 2.2000 µm, x 0.10000 y 0.20000 V [model m-2; σ x 0.0200 y unknown µm; "
        "correction x -0.3000 y +0.2000 µm; σ adapted x 0.3000 y unknown µm]")


def test_a_wrong_cell_is_named_with_the_cells_that_answer(served: Served) -> None:
    result = subprocess.run(  # the daemon is up, but for another cell
        [sys.executable, "-m", "nanodrift.cli", "target", "1", "2", "-e", f"tcp/127.0.0.1:{served.port}",
         "--cell", "nosuchcell"],
        capture_output=True, text=True, cwd=REPO, timeout=60,
    )
    assert result.returncode == 1
    lines = result.stderr.splitlines()
    assert len(lines) == 2 and all("no daemon serves cell 'nosuchcell'" in line for line in lines), result.stderr
    assert f"the cell(s) answering on this network: {served.cell} (--cell {served.cell})" in lines[0]
    assert "is the daemon running" not in result.stderr
