"""Reload integrity over the running daemon: a model file's content decides what is served.

Reproduction 2 of issue 10: a model edited to keep its ``"id"`` was "reloaded" but not applied (the
daemon kept the old evaluator because the ids matched). Now the edit is refused on SIGHUP
(``reload_refused``, the old model keeps serving) until ``nanodrift restamp``; then the reload
applies it and the command changes. Reproduction 5: a deeply nested model file on SIGHUP is a
``reload_refused``, and at start the daemon serves without a model, every log line still JSON.
"""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
from helpers.daemon_harness import MODEL_TERMS, TEMPS, Daemon, Served, expected_q

from nanodrift.cli import main

NESTED = "[" * 100_000 + "]" * 100_000


def test_an_edit_keeping_the_id_is_refused_until_restamped_then_applied(tmp_path: Path) -> None:
    s = Served(tmp_path, "restamp").start()
    try:
        ok, before = s.client.query({"x_um": 240.0, "id": 1})
        assert ok and before["model"] == s.model.id
        assert before["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)

        doc = json.loads(s.model_path.read_text())
        [x_term] = [t for t in doc["terms"] if t["term"] == "x"]
        x_term["coef"] = 2.0  # "id" left as it was
        s.model_path.write_text(json.dumps(doc, indent=2))
        s.daemon.signal(signal.SIGHUP)
        line = s.daemon.wait_log("reload_refused")
        assert any("does not match its content" in p and "nanodrift restamp" in p for p in line["problems"]), line
        ok, still = s.client.query({"x_um": 240.0, "id": 2})
        assert ok and still["model"] == s.model.id and still["q_um"] == pytest.approx(before["q_um"], abs=1e-12)

        assert main(["restamp", str(s.model_path)]) == 0
        new_id = json.loads(s.model_path.read_text())["id"]
        assert new_id != s.model.id
        s.daemon.signal(signal.SIGHUP)
        applied = s.daemon.wait_log("reload_applied")
        assert applied["model"] == new_id
        ok, after = s.client.query({"x_um": 240.0, "id": 3})
        assert ok and after["model"] == new_id
        assert after["q_um"] == pytest.approx(expected_q(240.0, TEMPS, {**MODEL_TERMS, "x": 2.0}), abs=1e-9)
        assert s.client.status()["counters"]["reload_failures"] == 1
    finally:
        assert s.close() == 0


def test_a_nested_model_file_is_refused_on_reload_and_at_start_the_daemon_serves_without_it(tmp_path: Path) -> None:
    s = Served(tmp_path, "nested").start()
    try:
        s.model_path.write_text(NESTED)
        s.daemon.signal(signal.SIGHUP)
        line = s.daemon.wait_log("reload_refused")
        assert any(f"{s.model_path}: not a model file" in p for p in line["problems"]), line
        ok, still = s.client.query({"x_um": 100.0, "id": 1})
        assert ok and still["model"] == s.model.id
    finally:
        assert s.close() == 0

    restarted = Daemon(["--config", str(s.config_path)], tmp_path / "restart.log", [s.plugin_dir])
    try:
        restarted.wait_log("serving", timeout=30)
        [starting] = restarted.log_events("starting")
        assert starting["model"] is None and f"{s.model_path}: not a model file" in starting["model_problem"]
    finally:
        assert restarted.stop() == 0
    for log in (tmp_path / "daemon.log", tmp_path / "restart.log"):
        text = log.read_text()
        assert "RecursionError" not in text and "Task exception was never retrieved" not in text
        assert all(isinstance(json.loads(line), dict) for line in text.splitlines())
