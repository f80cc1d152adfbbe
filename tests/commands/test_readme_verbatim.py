"""The README's command blocks, verbatim: the try-out and the operator guide's "Calibrate, then enable".

Issue 13, reproduction 1: with no config the daemon listened on a random port, so the README's
``nanodrift target 0 240 480 -e tcp/127.0.0.1:7447`` failed. The commands are read from the README
and run through the installed ``nanodrift`` script in a fresh folder. They need the real port 7447:
when something else holds it the test fails and says so (a skip would hide a broken README).

"Calibrate, then enable" runs as written with two changes, both for want of root: /etc/nanodrift and
/var/lib/nanodrift live under a temporary folder, and ``systemctl enable --now nanodrift`` (the one
line :data:`NOT_RUN`) is replaced by what the unit runs (its ``ExecStart``, read from the unit file).
(The Quick start's ``nanodrift demo`` is run, shortened, by tests/commands/test_demo.py.)
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import socket
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.daemon_harness import REPO, Client, Daemon

from nanodrift.model.model import load_model

NANODRIFT = Path(sys.executable).with_name("nanodrift")
PORT = 7447


#: the system folders of the operator guide, moved under a temporary folder (the test has no root)
SYSTEM_DIRS = ("/etc/nanodrift", "/var/lib/nanodrift")
#: the README lines this test cannot run, and what it runs instead
NOT_RUN = {("systemctl", "enable", "--now", "nanodrift"): "the unit's ExecStart, as systemd would start it"}


def readme_block(title: str) -> list[list[str]]:
    """The commands of the README's ``**title**`` shell block, split as a shell would (comments dropped)."""
    text = (REPO / "README.md").read_text()
    block = re.search(rf"\*\*{re.escape(title)}\*\*.*?```sh\n(.*?)```", text, re.DOTALL)
    assert block, f"the README's {title!r} block is gone: update this test"
    return [words for line in block[1].splitlines() if (words := shlex.split(line, comments=True))]


def readme_tryout() -> list[list[str]]:
    """The commands of the README's "Try it without hardware" block."""
    return readme_block("Try it without hardware")


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
                assert len(lines) == 3 and all(re.match(r"x \d+\.\d+ µm -> q [-\d.]+ µm, [-\d.]+ V", li)
                                               for li in lines), result.stdout
            if command[1] == "status":
                assert result.stdout.splitlines()[1].startswith("cell0 ")

        # a second `nanodrift run` on the taken port: one sentence, the exit code the README gives, the -l hint,
        # no Rust path
        second = subprocess.run([str(NANODRIFT), "run"], capture_output=True, text=True, timeout=60, cwd=tmp_path)
        documented = re.search(r"If the port is taken it says so in one\s+sentence and exits (\d)",
                               (REPO / "README.md").read_text())
        assert documented, "the README no longer says what a taken port exits with: update this test"
        assert second.returncode == int(documented[1]) == 2, second.stderr
        failed = json.loads(second.stderr.strip().splitlines()[-1])  # stderr is a pipe: the daemon's JSON lines
        assert failed["event"] == "run_failed", second.stderr
        last = failed["error"]
        assert last.startswith("tcp/127.0.0.1:7447 is already in use"), second.stderr
        assert "-l tcp/127.0.0.1:PORT" in last and ".rs:" not in second.stderr
    finally:
        assert runner.stop() == 0


def unit_exec_start() -> list[str]:
    """The unit's ``ExecStart=`` command line, split."""
    unit = (REPO / "systemd" / "nanodrift.service").read_text()
    line = re.search(r"^ExecStart=(.+)$", unit, re.MULTILINE)
    assert line, "systemd/nanodrift.service has no ExecStart"
    return shlex.split(line[1])


def test_the_operator_guides_calibrate_then_enable_block_runs_verbatim(tmp_path: Path) -> None:
    readme = (REPO / "README.md").read_text()
    commands = readme_block("Calibrate, then enable:")
    assert [c[:2] for c in commands] == [["nanodrift", "calibrate"], ["nanodrift", "check-config"],
                                         ["systemctl", "enable"], ["nanodrift", "target"]], commands
    root = tmp_path / "root"

    def rooted(arg: str) -> str:
        return str(root) + arg if arg.startswith(SYSTEM_DIRS) else arg

    # the install step ("install ... /etc/nanodrift/nanodrift.toml   # or config/sim.toml to start"), then
    # "Set [model] path = "/var/lib/nanodrift/model.json" in the config", as the README says
    assert re.search(r"install -D -m 0644 config/lab\.toml /etc/nanodrift/nanodrift\.toml\s+# or config/sim\.toml",
                     readme), "the README's install step changed: update this test"
    assert 'Set `[model] path = "/var/lib/nanodrift/model.json"` in the config' in readme
    config = Path(rooted("/etc/nanodrift/nanodrift.toml"))
    config.parent.mkdir(parents=True)
    shutil.copyfile(REPO / "config" / "sim.toml", config)
    text = config.read_text()
    assert text.count("\n[model]") == 1
    config.write_text(text.replace("\n[model]", f'\n[model]\npath = "{rooted("/var/lib/nanodrift/model.json")}"', 1))
    model_path = Path(rooted("/var/lib/nanodrift/model.json"))
    if port_taken(PORT):
        pytest.fail(f"port {PORT} on 127.0.0.1 is in use by another program: the shipped sim.toml listens there")

    daemon: Script | None = None
    try:
        for command in commands:
            if tuple(command) in NOT_RUN:
                start = unit_exec_start()
                assert start[0].endswith("/bin/nanodrift") and start[1] == "run", start
                daemon = Script([str(NANODRIFT), *map(rooted, start[1:])], tmp_path / "daemon.log", cwd=tmp_path)
                serving = daemon.wait_log("serving", timeout=60)
                assert serving["model"] == load_model(model_path).id
                client = Client(PORT, "cell0")
                try:
                    client.wait_ready(load_model(model_path).channels, timeout=30)
                finally:
                    client.close()
                continue
            result = subprocess.run([str(NANODRIFT), *map(rooted, command[1:])], capture_output=True, text=True,
                                    timeout=300, cwd=tmp_path)
            assert result.returncode == 0, f"{shlex.join(command)}: {result.stdout}{result.stderr}"
            if command[1] == "calibrate":
                model = load_model(model_path)  # written where the config's [model] path says
                assert f"model -> {model_path} ({model.id})" in result.stdout + result.stderr
            if command[1] == "check-config":
                assert f"{config}: ok" in result.stdout and f"({model.id})" in result.stdout, result.stdout
            if command[1] == "target":
                lines = result.stdout.splitlines()
                assert len(lines) == 3, result.stdout
                for line, x in zip(lines, ("0", "240", "480"), strict=True):
                    assert re.match(rf"x {x}\.0000 µm -> q [-\d.]+ µm, [-\d.]+ V \[model {model.id};", line), line
        assert daemon is not None, "the block no longer enables the unit: update this test"
    finally:
        if daemon is not None:
            assert daemon.stop() == 0


def test_the_install_block_puts_nanodrift_on_path_and_the_unit_runs_the_same_script(tmp_path: Path) -> None:
    """Issue 19: after the README's /opt install, ``nanodrift`` was not a command. The block's ``ln`` runs
    under a temporary root, against a stand-in for the venv's script."""
    commands = readme_block("Install")
    venv = commands[0][commands[0].index("venv") + 1]
    script = f"{venv}/bin/nanodrift"
    links = [c for c in commands if c[0] == "ln"]
    assert len(links) == 1 and links[0][-2] == script, commands
    link_dir = str(Path(links[0][-1]).parent)
    assert link_dir in ("/usr/local/bin", "/usr/bin"), f"{link_dir} is not on a default PATH"
    root = tmp_path / "root"
    (root / venv.lstrip("/") / "bin").mkdir(parents=True)
    (root / script.lstrip("/")).write_text("#!/bin/sh\necho venv nanodrift\n")
    (root / script.lstrip("/")).chmod(0o755)
    (root / link_dir.lstrip("/")).mkdir(parents=True)
    rooted = [w if not w.startswith("/") else str(root) + w for w in links[0]]
    subprocess.run(rooted, check=True)
    found = shutil.which("nanodrift", path=str(root) + link_dir)
    assert found is not None
    assert subprocess.run([found], capture_output=True, text=True).stdout == "venv nanodrift\n"
    unit = (REPO / "systemd" / "nanodrift.service").read_text()
    for key in ("ExecStartPre", "ExecStart"):
        line = re.search(rf"^{key}=(\S+) ", unit, re.MULTILINE)
        assert line and line[1] == script, f"the unit's {key} does not run {script}"


def test_the_multi_axis_block_runs_verbatim(tmp_path: Path) -> None:
    """Calibrating an XY stage from the command line, as the README's multi-axis section writes it."""
    commands = readme_block("Calibrating an XY stage.")
    assert [c[1] for c in commands] == ["simulate", "fit", "predict", "validate", "discover"]
    outputs = []
    for words in commands:
        done = subprocess.run([str(NANODRIFT), *words[1:]], capture_output=True, text=True, cwd=tmp_path, timeout=120)
        assert done.returncode == 0, f"{shlex.join(words)}: {done.stderr}"
        outputs.append(done.stdout)
    assert "q_x = " in outputs[1] and "·y" in outputs[1] and "x·y" in outputs[1]  # the cross terms were kept
    header = (tmp_path / "xy_pred.csv").read_text().splitlines()[0].split(",")
    assert {"q_pred_x_um", "q_sigma_x_um", "q_pred_y_um", "q_sigma_y_um"} <= set(header)
    assert outputs[3].count("AP 2-D") == 2  # test2 and test5, one call
