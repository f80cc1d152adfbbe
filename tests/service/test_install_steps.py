"""The README's install step, verbatim: ``config/sim.toml`` copied to an "etc" folder still finds the
shipped model, from any working directory (issue 10, reproduction 9: it resolved to /etc/daemon/data/...)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

from helpers.daemon_harness import REPO, TESTS, Client, Daemon, free_port

from nanodrift.config import DEFAULT_MODEL_PATH
from nanodrift.model.model import load_model

INSTALL = re.compile(r"^install -D -m 0644 config/lab\.toml /etc/nanodrift/nanodrift\.toml\s+# or config/sim\.toml",
                     re.MULTILINE)


def test_sim_toml_installed_as_the_readme_says_loads_the_shipped_model_from_anywhere(tmp_path: Path) -> None:
    assert INSTALL.search((REPO / "README.md").read_text()), "the README's install step changed: update this test"
    etc, elsewhere = tmp_path / "etc", tmp_path / "somewhere" / "else"
    elsewhere.mkdir(parents=True)
    installed = etc / "nanodrift" / "nanodrift.toml"
    subprocess.run(["install", "-D", "-m", "0644", "config/sim.toml", str(installed)], cwd=REPO, check=True)
    shipped = load_model(DEFAULT_MODEL_PATH)
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(REPO)])}

    check = subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(installed)], cwd=elsewhere,
                           env=env, capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stderr
    assert f"model: {DEFAULT_MODEL_PATH} ({shipped.id})" in check.stdout

    port = free_port()  # -l replaces the file's tcp/127.0.0.1:7447, so a test never takes the real port
    daemon = Daemon(["--config", str(installed), "-l", f"tcp/127.0.0.1:{port}"], tmp_path / "daemon.log",
                    cwd=elsewhere)
    try:
        start = daemon.wait_log("starting", timeout=30)
        assert (start["model"], start["model_problem"]) == (shipped.id, None), start
        assert start["model_path"] == str(DEFAULT_MODEL_PATH)
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "cell0")
        try:
            status = client.wait_ready(["T1", "T2", "T4"])  # the shipped model's channels (T3 is left out)
            assert status["model"]["id"] == shipped.id and status["model_problem"] is None
            ok, command = client.query({"x_um": 240.0, "id": "installed"})
            assert ok and command["model"] == shipped.id, command
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
