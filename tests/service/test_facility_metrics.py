"""What a facility's monitoring reads (issue 29): the process metrics on ``/metrics``, and the shipped
Grafana dashboard and Prometheus alert rules, which may name only metrics a real daemon exports.

One simulated cell (``config/sim.toml`` with metrics on, a short health settle and the bias
adaptation, so that every family the dashboard draws has a value) is scraped over HTTP on 127.0.0.1
after it has held enough targets for its health statistics. ``promtool check rules`` runs on the
shipped rules where Prometheus' promtool is installed (Debian: the ``prometheus`` package).
"""

from __future__ import annotations

import json
import os
import re
import resource
import shutil
import subprocess
import urllib.request
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import REPO, Daemon, free_port, wait_until
from prometheus_client.parser import text_string_to_metric_families

from nanodrift import Client

CONFIG = REPO / "config"
DASHBOARD = CONFIG / "grafana-dashboard.json"
RULES = CONFIG / "prometheus-rules.yml"
#: series Prometheus makes itself for every scrape target (not exported by the daemon)
PROMETHEUS_OWN = {"up"}
#: a metric name in a PromQL expression (label names and functions never start with these)
METRIC_NAME = re.compile(r"\b(?:nanodrift|process)_[a-z_]+\b")


def sim_config(root: Path, port: int, metrics_port: int) -> Path:
    text = (CONFIG / "sim.toml").read_text()
    for old, new in (('listen = ["tcp/127.0.0.1:7447"]', f'listen = ["tcp/127.0.0.1:{port}"]'),
                     ('listen = ""', f'listen = "127.0.0.1:{metrics_port}"'),
                     ("settle_s = 3.0", "settle_s = 0.2"), ("window_s = 2.0", "window_s = 0.3"),
                     ('mode = "off"', 'mode = "bias"')):
        assert text.count(old) == 1, f"config/sim.toml changed: {old!r}"
        text = text.replace(old, new)
    path = root / "sim.toml"
    path.write_text(text)
    return path


class Scraped:
    def __init__(self, root: Path) -> None:
        self.port, metrics_port = free_port(), free_port()
        self.daemon = Daemon(["--config", str(sim_config(root, self.port, metrics_port))], root / "daemon.log")
        try:
            self.url = self.daemon.wait_log("metrics_listening", timeout=30)["url"]
            self.daemon.wait_log("serving", timeout=30)
            with Client(f"tcp/127.0.0.1:{self.port}", cell="cell0") as cell:
                wait_until(lambda: cell.status()["sensors"]["T1"]["state"] == "ok", 15, "T1 ok")
                for index, x_um in enumerate((100.0, 200.0, 300.0, 200.0, 100.0, 150.0)):
                    cell.move(x_um)
                    wait_until(lambda n=index + 1: (cell.status()["health"].get("n") or 0) >= n, 15,
                               f"{index + 1} settled residuals", interval=0.05)
        except BaseException:
            self.daemon.stop()
            raise

    def text(self) -> str:
        with urllib.request.urlopen(self.url, timeout=10) as response:
            assert response.status == 200
            return response.read().decode()

    def sample_names(self) -> set[str]:
        return {s.name for family in text_string_to_metric_families(self.text()) for s in family.samples}


@pytest.fixture(scope="module")
def scraped(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Scraped]:
    daemon = Scraped(tmp_path_factory.mktemp("facility"))
    yield daemon
    assert daemon.daemon.stop() == 0


def process_samples(text: str) -> dict[str, float]:
    return {s.name: s.value for family in text_string_to_metric_families(text) for s in family.samples
            if s.name.startswith("process_")}


def test_metrics_include_the_daemons_process_metrics(scraped: Scraped) -> None:
    samples = process_samples(scraped.text())
    pid = scraped.daemon.proc.pid
    open_now = len(os.listdir(f"/proc/{pid}/fd"))
    # the daemon's own descriptors (its sockets and threads come and go: a margin, not equality)
    assert samples["process_open_fds"] == pytest.approx(open_now, abs=10)
    assert samples["process_max_fds"] == resource.getrlimit(resource.RLIMIT_NOFILE)[0]  # inherited from here
    started = os.stat(f"/proc/{pid}").st_mtime
    assert samples["process_start_time_seconds"] == pytest.approx(started, abs=5)
    assert samples["process_resident_memory_bytes"] > 10e6 and samples["process_cpu_seconds_total"] > 0


def expressions(node: Any) -> Iterator[str]:
    """Every ``expr`` string in a dashboard (panels' targets) or a rules file, however deeply nested."""
    if isinstance(node, dict):
        for key, value in node.items():
            if key == "expr" and isinstance(value, str):
                yield value
            else:
                yield from expressions(value)
    elif isinstance(node, list):
        for item in node:
            yield from expressions(item)


def rule_expressions() -> list[str]:
    """The rules file's ``expr:`` lines (one line each in the shipped file; no YAML parser needed)."""
    return [line.split("expr:", 1)[1].strip() for line in RULES.read_text().splitlines()
            if line.strip().startswith("expr:")]


def names_in(exprs: list[str]) -> set[str]:
    return {name for expr in exprs for name in METRIC_NAME.findall(expr)}


def test_the_dashboard_draws_only_metrics_the_daemon_exports(scraped: Scraped) -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    exprs = list(expressions(dashboard["panels"]))
    named = names_in(exprs)
    exported = scraped.sample_names()
    assert named - exported == set(), f"the dashboard names metrics no scrape has: {sorted(named - exported)}"
    # what the issue asks a cell's row to show
    for wanted in ("nanodrift_targets_total", "nanodrift_errors_total", "nanodrift_health_residual_rms_meters",
                   "nanodrift_health_correction_meters", "nanodrift_temperature_celsius", "nanodrift_actuator_ok",
                   "nanodrift_answer_latency_seconds_bucket", "process_open_fds"):
        assert wanted in named, wanted


def test_the_alert_rules_name_only_metrics_the_daemon_exports(scraped: Scraped) -> None:
    exprs = rule_expressions()
    assert len(exprs) == RULES.read_text().count("- alert:") >= 10
    named = names_in(exprs)
    exported = scraped.sample_names()
    assert named - exported == set(), f"the rules name metrics no scrape has: {sorted(named - exported)}"
    others = {word for expr in exprs for word in re.findall(r"\b([a-z_]+)\{", expr)} - named
    assert others <= PROMETHEUS_OWN, others
    # the README's former prose alerts, and the descriptor alert of issue 16
    for wanted in ("nanodrift_sensor_state", "nanodrift_health_state", "nanodrift_actuator_ok",
                   "nanodrift_errors_total", "nanodrift_answer_latency_seconds_bucket", "process_open_fds"):
        assert wanted in named, wanted


def test_a_metric_name_the_daemon_does_not_export_is_caught(scraped: Scraped) -> None:
    """The control: the comparison above sees a misspelt name."""
    assert names_in(["rate(nanodrift_target_total[5m]) > 0"]) - scraped.sample_names() == {"nanodrift_target_total"}


@pytest.mark.skipif(shutil.which("promtool") is None,
                    reason="promtool is not installed here (Debian: apt-get install prometheus)")
def test_promtool_accepts_the_rules(tmp_path: Path) -> None:
    result = subprocess.run(["promtool", "check", "rules", str(RULES)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr
    assert f"SUCCESS: {len(rule_expressions())} rules found" in result.stdout
    broken = tmp_path / "broken.yml"
    broken.write_text(RULES.read_text().replace("> 0.005", "> > 0.005", 1))
    assert subprocess.run(["promtool", "check", "rules", str(broken)], capture_output=True, timeout=60).returncode != 0


def test_the_dashboard_has_a_row_per_cell() -> None:
    dashboard = json.loads(DASHBOARD.read_text())
    assert len([p for p in dashboard["panels"] if p["type"] == "row" and p.get("repeat") == "cell"]) == 1
    cell_variable = next(v for v in dashboard["templating"]["list"] if v["name"] == "cell")
    assert "nanodrift_build_info" in cell_variable["definition"] and cell_variable["multi"]
    ids = [p["id"] for p in dashboard["panels"]]
    assert len(ids) == len(set(ids))
    cell_exprs = [e for e in expressions(dashboard["panels"]) if "nanodrift_" in e]
    assert cell_exprs and all('cell="$cell"' in e for e in cell_exprs)  # each row shows its own cell only
