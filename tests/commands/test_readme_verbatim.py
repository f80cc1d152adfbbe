"""The README's try-out, verbatim: ``nanodrift run`` (no config), then the client commands as written.

Issue 13, reproduction 1: with no config the daemon listened on a random port, so the README's
``nanodrift target 0 240 480 -e tcp/127.0.0.1:7447`` failed. The commands are read from the README
and run through the installed ``nanodrift`` script in a fresh folder. They need the real port 7447:
when something else holds it the test fails and says so (a skip would hide a broken README).
"""

from __future__ import annotations

import re
import shlex
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.daemon_harness import REPO, Daemon

NANODRIFT = Path(sys.executable).with_name("nanodrift")
PORT = 7447


def readme_tryout() -> list[list[str]]:
    """The commands of the README's "Try it without hardware" block, split as a shell would."""
    text = (REPO / "README.md").read_text()
    block = re.search(r"\*\*Try it without hardware\*\*.*?```sh\n(.*?)```", text, re.DOTALL)
    assert block, "the README's 'Try it without hardware' block is gone: update this test"
    return [shlex.split(line) for line in block[1].splitlines() if line.strip()]


class Script(Daemon):
    """:class:`Daemon`'s log parsing and stopping, for the installed ``nanodrift`` script run as written."""

    def __init__(self, argv: list[str], log_path: Path, cwd: Path) -> None:
        self.log_path = log_path
        self._log_file = open(log_path, "wb")
        self.proc = subprocess.Popen(argv, stdout=subprocess.DEVNULL, stderr=self._log_file, cwd=cwd)


def port_taken(port: int) -> bool:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.settimeout(0.5)
        return probe.connect_ex(("127.0.0.1", port)) == 0


def test_the_readme_tryout_works_verbatim(tmp_path: Path) -> None:
    commands = readme_tryout()
    assert commands[0] == ["nanodrift", "run"]
    assert ["nanodrift", "target", "0", "240", "480", "-e", f"tcp/127.0.0.1:{PORT}"] in commands
    if port_taken(PORT):
        pytest.fail(f"port {PORT} on 127.0.0.1 is in use by another program: this test runs the README's "
                    "`nanodrift run` exactly as written, which listens there; stop that program and rerun")
    assert NANODRIFT.exists(), f"{NANODRIFT}: the console script is not installed (pip install -e .)"
    log_path = tmp_path / "run.log"
    runner = Script([str(NANODRIFT), *commands[0][1:]], log_path, cwd=tmp_path)
    try:
        listening = runner.wait_log("listening", timeout=30)
        assert listening["endpoints"] == [f"tcp/127.0.0.1:{PORT}"]
        serving = runner.wait_log("serving", timeout=30)
        assert serving["listen"] == [f"tcp/127.0.0.1:{PORT}"]
        for command in commands[1:]:
            result = subprocess.run([str(NANODRIFT), *command[1:]], capture_output=True, text=True, timeout=60,
                                    cwd=tmp_path)
            assert result.returncode == 0, f"{shlex.join(command)}: {result.stderr}"
            if command[1] == "target":
                lines = result.stdout.splitlines()
                assert len(lines) == 3 and all(re.match(r"x \d+\.\d+ um -> q [-\d.]+ um, [-\d.]+ V", li)
                                               for li in lines), result.stdout
            if command[1] == "status":
                assert result.stdout.splitlines()[1].startswith("cell0 ")

        # a second `nanodrift run` on the taken port: one sentence, exit non-zero, the -l hint, no Rust path
        second = subprocess.run([str(NANODRIFT), "run"], capture_output=True, text=True, timeout=60, cwd=tmp_path)
        assert second.returncode != 0
        last = second.stderr.strip().splitlines()[-1]
        assert last.startswith("nanodrift run: error: tcp/127.0.0.1:7447 is already in use"), second.stderr
        assert "-l tcp/127.0.0.1:PORT" in last and ".rs:" not in second.stderr
    finally:
        assert runner.stop() == 0
