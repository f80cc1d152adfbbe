"""``nanodrift demo``, shortened: calibrate, serve over Zenoh, targets from a client, Table I."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

from daemon_harness import REPO

from daemon.model.model import load_model


def test_demo_calibrates_serves_and_prints_table_one(tmp_path: Path) -> None:
    result = subprocess.run(
        [sys.executable, "-m", "daemon.cli", "demo", "--tests", "test2", "--cycles", "2",
         "--calibration-cycles", "6", "--keep", str(tmp_path)],
        capture_output=True, text=True, cwd=REPO, timeout=120,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    out = result.stdout
    assert "TABLE I" in out
    row = re.search(r"^test2\s+(\d+) nm\*\s+(\d+) nm", out, re.MULTILINE)
    assert row, out
    without, with_ = float(row.group(1)), float(row.group(2))
    assert with_ < without  # the model served over Zenoh beats the uncompensated stage
    model = load_model(tmp_path / "model.json")
    assert model.id in out
    log = (tmp_path / "test2.log").read_text()
    assert '"event": "serving"' in log and '"event": "stopped"' in log
    assert log.count('"event": "target_refused"') == 0
