"""systemd integration: the unit file's hardening score and contents, and the notify protocol as
the daemon speaks it (READY, WATCHDOG, RELOADING/READY on SIGHUP, STOPPING on SIGTERM)."""

from __future__ import annotations

import os
import re
import shutil
import signal
import socket
import subprocess
import threading
import time
from pathlib import Path

import pytest
from helpers.daemon_harness import Served

from nanodrift.config import SAFE_RAMP_BUDGET_S, STOP_TIMEOUT_S

REPO = Path(__file__).resolve().parents[2]
UNIT = REPO / "systemd" / "nanodrift.service"


@pytest.mark.skipif(shutil.which("systemd-analyze") is None, reason="systemd-analyze is not installed here")
def test_unit_is_hardened_to_an_exposure_of_1_3_or_better() -> None:
    result = subprocess.run(
        ["systemd-analyze", "security", "--offline=yes", str(UNIT)], capture_output=True, text=True, timeout=60
    )
    match = re.search(r"Overall exposure level for nanodrift\.service: (\d+\.\d+)", result.stdout + result.stderr)
    assert match, result.stdout + result.stderr
    assert float(match.group(1)) <= 1.3, result.stdout
    ip_line = next(line for line in result.stdout.splitlines() if "IPAddressDeny=" in line)
    assert "only localhost entries" in ip_line, ip_line


def unit_settings() -> dict[str, list[str]]:
    settings: dict[str, list[str]] = {}
    for line in UNIT.read_text().splitlines():
        if "=" in line and not line.lstrip().startswith(("#", "[")):
            key, value = line.split("=", 1)
            settings.setdefault(key.strip(), []).append(value.strip())
    return settings


def test_unit_runs_the_daemon_as_a_notify_service_with_its_directories_and_serial_access() -> None:
    unit = unit_settings()
    assert unit["Type"] == ["notify"]
    assert unit["WatchdogSec"] and unit["ExecReload"] == ["/bin/kill -HUP $MAINPID"]
    assert any("nanodrift run --config /etc/nanodrift/nanodrift.toml" in v for v in unit["ExecStart"])
    assert any("nanodrift check-config" in v for v in unit["ExecStartPre"])
    assert unit["StateDirectory"] == ["nanodrift"] and unit["ConfigurationDirectory"] == ["nanodrift"]
    assert unit["SupplementaryGroups"] == ["dialout"]
    assert "char-ttyUSB rw" in unit["DeviceAllow"]
    assert "AF_UNIX" in unit["RestrictAddressFamilies"][0]  # NOTIFY_SOCKET needs it


def test_unit_starts_after_the_clock_is_set() -> None:
    """Issue 26.7: a start on a clock months ahead deleted the records; the unit orders after time-sync.target."""
    unit = unit_settings()
    assert "time-sync.target" in unit["After"][0].split() and "time-sync.target" in unit["Wants"][0].split()
    assert "network-online.target" in unit["After"][0].split()


def test_the_units_stop_timeout_is_the_one_the_config_checks_the_safe_ramp_against() -> None:
    """check-config warns when the ramp to safe_voltage_v outlasts its share of TimeoutStopSec: the two
    numbers must be the same, or the warning protects against a timeout the unit does not have."""
    (value,) = unit_settings()["TimeoutStopSec"]
    match = re.fullmatch(r"(\d+(?:\.\d+)?)(s|min)?", value)
    assert match, f"TimeoutStopSec={value}: expected seconds, e.g. 30s"
    seconds = float(match[1]) * (60 if match[2] == "min" else 1)
    assert seconds == STOP_TIMEOUT_S, (value, STOP_TIMEOUT_S)
    assert SAFE_RAMP_BUDGET_S < STOP_TIMEOUT_S


def test_unit_raises_the_file_descriptor_limit_and_says_why() -> None:
    """Issue 16: idle connections took the default 1024 descriptors, and with them sensors and targets."""
    assert unit_settings()["LimitNOFILE"] == ["65536"]
    lines = UNIT.read_text().splitlines()
    above = lines[:next(n for n, line in enumerate(lines) if line.startswith("LimitNOFILE="))]
    comment = []  # the comment lines right above the setting
    while above and above[-1].startswith("#"):
        comment.insert(0, above.pop())
    assert "issue 16" in " ".join(comment) and "1024" in " ".join(comment), comment


def test_unit_reaches_only_localhost_and_says_how_to_widen_it_in_a_drop_in() -> None:
    unit = unit_settings()
    assert unit["IPAddressDeny"] == ["any"]
    assert unit["IPAddressAllow"] == ["localhost"]
    comments = [line.lstrip("# ").strip() for line in UNIT.read_text().splitlines() if line.startswith("#")]
    assert any("systemctl edit nanodrift" in c for c in comments)
    assert "IPAddressAllow=192.168.1.0/24" in comments  # the line an operator puts in the drop-in


class NotifySocket:
    """An abstract unix datagram socket collecting what the daemon tells 'systemd'."""

    def __init__(self) -> None:
        self.name = f"nanodrift-notify-{os.getpid()}-{time.monotonic_ns()}"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind("\0" + self.name)
        self.sock.settimeout(0.2)
        self.messages: list[dict[str, str]] = []
        self._cond = threading.Condition()
        self._stop = False
        self._thread = threading.Thread(target=self._receive, daemon=True)
        self._thread.start()

    @property
    def address(self) -> str:
        return "@" + self.name

    def _receive(self) -> None:
        while not self._stop:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            fields = dict(line.split("=", 1) for line in data.decode().splitlines() if "=" in line)
            with self._cond:
                self.messages.append(fields)
                self._cond.notify_all()

    def wait_for(self, key: str, count: int = 1, timeout: float = 10.0) -> list[dict[str, str]]:
        deadline = time.monotonic() + timeout
        with self._cond:
            while sum(key in m for m in self.messages) < count:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise AssertionError(f"no {key} x{count} within {timeout} s; got {self.messages}")
                self._cond.wait(remaining)
            return list(self.messages)

    def close(self) -> None:
        self._stop = True
        self._thread.join(2)
        self.sock.close()


def test_daemon_speaks_sd_notify_ready_watchdog_reload_and_stopping(tmp_path: Path) -> None:
    notify = NotifySocket()
    env = {"NOTIFY_SOCKET": notify.address, "WATCHDOG_USEC": "400000"}  # ping every 0.2 s
    served = Served(tmp_path, "notify", env=env).start()
    try:
        messages = notify.wait_for("READY")
        assert messages[0].get("READY") == "1" and "cell notify" in messages[0].get("STATUS", "")
        notify.wait_for("WATCHDOG", count=3, timeout=5)

        served.daemon.signal(signal.SIGHUP)
        served.daemon.wait_log("reload_applied")
        messages = notify.wait_for("READY", count=2)
        reloading = [i for i, m in enumerate(messages) if m.get("RELOADING") == "1"]
        assert reloading and "MONOTONIC_USEC" in messages[reloading[0]]
        assert any(m.get("READY") == "1" for m in messages[reloading[0] + 1:])

        served.daemon.signal(signal.SIGTERM)
        assert served.daemon.proc.wait(10) == 0
        messages = notify.wait_for("STOPPING")
        assert messages[-1].get("STOPPING") == "1" or any(m.get("STOPPING") == "1" for m in messages)
    finally:
        served.close()
        notify.close()
