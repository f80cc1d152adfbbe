"""Journald priorities on every log line (issue 29): ``journalctl -p warning`` must find the warnings.

journald reads a ``<N>`` at the start of each line of a service's stream as the line's priority and
strips it (``SyslogLevelPrefix=yes``, sd-daemon(3)); a line without one gets the unit's
``SyslogLevel`` (info). Here the daemon runs with stderr in a file and ``JOURNAL_STREAM`` naming that
file's device and inode, exactly what systemd gives a service whose stderr is the journal, and its
lines are read the way journald reads them: warnings at 4, errors at 3, info at 6, debug at 7, and
after the prefix one JSON object. A redirected stream (the variable inherited, the file another)
keeps plain JSON lines.
"""

from __future__ import annotations

import json
import logging
import os
import re
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import (
    REPO,
    TEMPS,
    TESTS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)

from nanodrift.logs import syslog_priority, writes_to_journal

#: journald's default for a line without a prefix (SyslogLevel=info)
JOURNAL_DEFAULT_PRIORITY = 6
PREFIX = re.compile(r"<([0-7])>")


def journal_entries(path: Path) -> list[tuple[int, dict[str, Any]]]:
    """Each line as journald stores it: (priority, message), the message parsed as the JSON object it must be."""
    entries = []
    for line in path.read_text().splitlines():
        match = PREFIX.match(line)
        priority = int(match[1]) if match else JOURNAL_DEFAULT_PRIORITY
        message = json.loads(line[match.end():] if match else line)
        assert isinstance(message, dict), line
        entries.append((priority, message))
    return entries


def journal_stream_of(path: Path) -> str:
    status = os.stat(path)
    return f"{status.st_dev}:{status.st_ino}"


def test_the_daemons_lines_carry_their_priority_when_stderr_is_the_journal(tmp_path: Path) -> None:
    log = tmp_path / "daemon.log"
    log.touch()  # the harness opens it again (truncating): same inode, the one JOURNAL_STREAM names
    port = free_port()
    sensors = SensorFile(tmp_path / "sensors.json", TEMPS)
    model = tmp_path / "model.json"
    write_test_model(model)
    config = tmp_path / "nanodrift.toml"
    good_config = file_sensor_config(tmp_path, cell="journal", port=port, model_path=model, sensor_file=sensors.path)
    config.write_text(good_config)
    daemon = Daemon(["--config", str(config), "--log-level", "debug"], log, [install_file_plugin(tmp_path / "p")],
                    env={"JOURNAL_STREAM": journal_stream_of(log)})
    client = None

    def entry(event: str) -> tuple[int, dict[str, Any]] | None:
        daemon.check_alive()
        return next(((p, m) for p, m in journal_entries(log) if m.get("event") == event), None)

    try:
        wait_until(lambda: entry("serving"), 30, "serving")
        client = Client(port, "journal")
        client.wait_ready(list(TEMPS))
        assert client.query({"x_um": 240.0, "id": "j1"})[0]
        sensors.write(error="hub unplugged")  # a warning: sensor_state fault
        config.write_text(good_config.replace('cell = "journal"', 'cell = "journal"\nbogus_key = 1'))
        daemon.signal(signal.SIGHUP)  # an error: reload_refused
        warning = wait_until(lambda: next(((p, m) for p, m in journal_entries(log) if m.get("event") == "sensor_state"
                                           and m.get("state") == "fault"), None), 10, "sensor_state fault")
        error = wait_until(lambda: entry("reload_refused"), 10, "reload_refused")
        debug = wait_until(lambda: entry("target_answered"), 10, "target_answered")
        assert warning[0] == 4 and warning[1]["level"] == "warning"
        assert error[0] == 3 and error[1]["level"] == "error"
        assert debug[0] == 7 and debug[1]["id"] == "j1"
        serving = entry("serving")
        assert serving is not None and serving[0] == 6
        # every line had its prefix: no line fell back to journald's default by accident
        assert all(PREFIX.match(line) for line in log.read_text().splitlines())
        mismatched = [(p, m) for p, m in journal_entries(log)
                      if p != syslog_priority(logging.getLevelNamesMapping()[m["level"].upper()])]
        assert mismatched == []  # every line's priority is its level's
    finally:
        if client is not None:
            client.close()
        assert daemon.stop() == 0


def test_a_failed_start_is_an_error_line_for_the_journal(tmp_path: Path) -> None:
    """``run_failed`` is written by the command line, before and after the logger: it carries <3> too."""
    log = tmp_path / "stderr.log"
    with open(log, "wb") as stderr:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(REPO)]),
               "JOURNAL_STREAM": journal_stream_of(log)}
        result = subprocess.run([sys.executable, "-m", "nanodrift.cli", "run", "--config", str(tmp_path / "none.toml")],
                                stderr=stderr, stdout=subprocess.DEVNULL, env=env, cwd=REPO, timeout=60)
    assert result.returncode == 2
    [(priority, message)] = [(p, m) for p, m in journal_entries(log) if m["event"] == "run_failed"]
    assert priority == 3 and "none.toml" in message["error"]


def test_a_stream_that_is_not_the_journals_stays_plain_json(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A child's stderr redirected to a file inherits JOURNAL_STREAM: the inode differs, no prefix."""
    journal, elsewhere = tmp_path / "journal", tmp_path / "file.log"
    journal.touch()
    monkeypatch.setenv("JOURNAL_STREAM", journal_stream_of(journal))
    with open(elsewhere, "w") as stream, open(journal, "a") as journal_stream:
        assert writes_to_journal(journal_stream) and not writes_to_journal(stream)
        monkeypatch.setenv("JOURNAL_STREAM", "not:numbers")
        assert not writes_to_journal(journal_stream)
    log = tmp_path / "plain.log"
    with open(log, "wb") as stderr:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(TESTS), str(REPO)]),
               "JOURNAL_STREAM": journal_stream_of(journal)}
        subprocess.run([sys.executable, "-m", "nanodrift.cli", "run", "--config", str(tmp_path / "none.toml")],
                       stderr=stderr, env=env, cwd=REPO, timeout=60)
    lines = log.read_text().splitlines()
    assert lines and all(isinstance(json.loads(line), dict) for line in lines)


def test_priorities_follow_sd_daemon() -> None:
    assert [syslog_priority(level) for level in (logging.CRITICAL, logging.ERROR, logging.WARNING, logging.INFO,
                                                 logging.DEBUG)] == [2, 3, 4, 6, 7]
