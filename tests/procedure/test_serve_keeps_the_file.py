"""``calibrate --serve`` edits one line of the operator's config and nothing else about the file (issue 26.9):
a 0640 ``root:nogroup`` config stayed 0640 but became ``root:root``, and its CRLF line endings became LF."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

from nanodrift.cli import main
from nanodrift.config import load_config

REPO = Path(__file__).resolve().parents[2]
SIM_TOML = REPO / "config" / "sim.toml"
NOBODY = 65534  # nobody / nogroup on Debian and Ubuntu


def crlf_config(tmp_path: Path) -> Path:
    config = tmp_path / "nanodrift.toml"
    config.write_bytes(SIM_TOML.read_text().replace("\n", "\r\n").encode())
    os.chmod(config, 0o640)
    return config


def serve(tmp_path: Path, config: Path) -> Path:
    out = tmp_path / "model.json"
    assert main(["calibrate", "--config", str(config), "--out", str(out), "--cycles", "2", "--serve"]) == 0
    assert load_config(config).model.path == out.resolve()  # the edit itself happened
    return out


def test_serve_keeps_crlf_line_endings_and_the_mode(tmp_path: Path) -> None:
    config = crlf_config(tmp_path)
    before = config.read_bytes()
    serve(tmp_path, config)
    after = config.read_bytes()
    assert after.count(b"\n") == after.count(b"\r\n") > before.count(b"\r\n")  # every line CRLF, one more line
    kept = [line for line in after.split(b"\r\n") if b"calibrate --serve" not in line]
    assert kept == before.split(b"\r\n")  # every other line is the operator's, byte for byte
    assert stat.S_IMODE(config.stat().st_mode) == 0o640


@pytest.mark.skipif(os.geteuid() != 0, reason="only root may give a file to another owner and group; the code "
                    "keeps them where permitted, which for another user is nothing to test")
def test_serve_run_by_root_keeps_the_files_owner_and_group(tmp_path: Path) -> None:
    config = crlf_config(tmp_path)
    os.chown(config, 0, NOBODY)  # root:nogroup, readable by the daemon's group only
    serve(tmp_path, config)
    assert (config.stat().st_uid, config.stat().st_gid) == (0, NOBODY)
    assert stat.S_IMODE(config.stat().st_mode) == 0o640
