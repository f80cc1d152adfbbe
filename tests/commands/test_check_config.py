"""``nanodrift check-config``: exit 2 for what the daemon would refuse on reload, warnings at exit 0,
``--strict`` turning the warnings into errors; every message names the file and the field (issue 10).
Issue 16: a safe ramp longer than a stop may take is a warning; a model path that is a FIFO or a
device is refused at once."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
from pathlib import Path

import pytest
import structlog
from helpers.daemon_harness import REPO, write_test_model

from nanodrift.cli import main
from nanodrift.config import SAFE_RAMP_BUDGET_S, STOP_TIMEOUT_S
from nanodrift.service.actuation import Actuation


def check(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(["check-config", *args])
    out = capsys.readouterr()
    return code, out.out, out.err


def config(tmp_path: Path, model: str, sensors: tuple[str, ...] = ("T1", "T2"), extra: str = "") -> Path:
    path = tmp_path / "nanodrift.toml"
    body = "".join(f'[[sensors]]\nname = "{name}"\nkind = "simulated"\n' for name in sensors)
    path.write_text(f'[model]\npath = "{model}"\n{extra}{body}')
    return path


def test_a_good_config_and_model_exit_zero_even_with_strict(tmp_path: Path, capsys) -> None:
    model = write_test_model(tmp_path / "model.json")
    path = config(tmp_path, "model.json")  # relative to the config file
    for flags in ((), ("--strict",)):
        code, out, err = check(capsys, str(path), *flags)
        assert (code, err) == (0, ""), err
        assert f"{path}: ok" in out and model.id in out


@pytest.mark.parametrize(
    ("content", "why"),
    [
        (None, "no such model file"),
        ('{"format": "nanodrift-model/1", "terms": [', "not valid JSON"),  # an editor's half-saved file
        ('{"format": "nanodrift-model/1", "terms": [{"term": "x^2.5", "coef": 1}]}', "terms[0]"),
        ("[" * 100_000 + "]" * 100_000, ""),  # hostile nesting: a message, never a traceback
    ],
    ids=["missing", "truncated", "bad-term", "nested"],
)
def test_a_model_the_daemon_would_refuse_on_reload_exits_2_naming_file_and_field(
        tmp_path: Path, capsys, content: str | None, why: str) -> None:
    model = tmp_path / "model.json"
    if content is not None:
        model.write_text(content)
    path = config(tmp_path, str(model))
    code, out, err = check(capsys, str(path))
    assert code == 2 and out == ""
    assert f"{path}:2: model.path: {model}" in err and why in err  # [model] path = ... is line 2
    assert "Traceback" not in err and "RecursionError" not in err


def test_warnings_exit_zero_and_strict_makes_them_errors(tmp_path: Path, capsys) -> None:
    write_test_model(tmp_path / "model.json")  # needs T1 and T2
    path = config(tmp_path, "model.json", sensors=("T1", "T3"))
    code, out, err = check(capsys, str(path))
    assert code == 0 and f"{path}: ok" in out
    assert f"{path}: warning: sensors: model" in err and "T2" in err  # missing channel: no one line holds it
    # unused sensor: in the errors' form, the file's line of its name, the 0-based index and the name
    assert f"{path}:7: warning: sensors[1] (T3).name: sensor 'T3' is not used" in err, err
    assert path.read_text().splitlines()[6] == 'name = "T3"'

    code, out, err = check(capsys, str(path), "--strict")
    assert code == 2 and out == ""
    lines = err.splitlines()
    assert any(f"{path}: sensors: model" in line and "T2" in line and "--strict" in line for line in lines), err
    assert any(f"{path}:7: sensors[1] (T3).name: sensor 'T3'" in line for line in lines), err
    assert ": warning:" not in err


def test_a_zenoh_config_file_zenoh_cannot_read_exits_2(tmp_path: Path, capsys) -> None:
    write_test_model(tmp_path / "model.json")
    missing = config(tmp_path, "model.json", extra='[zenoh]\nconfig_file = "absent.json5"\n')
    code, _, err = check(capsys, str(missing))
    assert code == 2 and f"{missing}:4: zenoh.config_file: {tmp_path / 'absent.json5'}" in err  # its key's line

    (tmp_path / "broken.json5").write_text("{ mode: 'peer', transport: { auth: ")
    broken = config(tmp_path, "model.json", extra='[zenoh]\nconfig_file = "broken.json5"\n')
    code, _, err = check(capsys, str(broken))
    assert code == 2 and "zenoh.config_file" in err


def test_the_shipped_secure_zenoh_config_is_accepted(tmp_path: Path, capsys) -> None:
    write_test_model(tmp_path / "model.json")
    secure = REPO / "config" / "zenoh-secure.json5"
    path = config(tmp_path, "model.json", extra=f'[zenoh]\nconfig_file = "{secure}"\n')
    code, _, err = check(capsys, str(path), "--strict")
    assert code == 0, err


@pytest.mark.parametrize(
    ("listen", "exposed"),
    [("tcp/0.0.0.0:7447", True), ("tcp/192.168.1.10:7447", True), ("tls/[fe80::1]:7447", True),
     ("tcp/127.0.0.1:7447", False), ("tcp/localhost:7447", False), ("tcp/[::1]:7447", False)],
)
def test_a_listener_other_computers_reach_without_the_secure_zenoh_config_is_a_warning(
        tmp_path: Path, capsys, listen: str, exposed: bool) -> None:
    write_test_model(tmp_path / "model.json")
    path = config(tmp_path, "model.json", extra=f'[zenoh]\nlisten = ["{listen}"]\n')
    code, _, err = check(capsys, str(path))
    assert code == 0
    # line 4: [model], path, [zenoh], then the listen key
    assert (f"{path}:4: warning: zenoh.listen: {listen} can be reached from other computers" in err) is exposed, err
    code, _, err = check(capsys, str(path), "--strict")
    assert code == (2 if exposed else 0), err
    secured = config(tmp_path, "model.json", extra=f'[zenoh]\nlisten = ["{listen}"]\nconfig_file = '
                                                 f'"{REPO / "config" / "zenoh-secure.json5"}"\n')
    code, _, err = check(capsys, str(secured), "--strict")
    assert code == 0 and "zenoh.listen" not in err, err


# --- issue 16: what check-config accepts must work at runtime --------------------------------------

def run_cli(*args: str, timeout_s: float = 60) -> subprocess.CompletedProcess[str]:
    """``python -m nanodrift.cli ...`` in its own process, its memory capped at 1 GiB and its time at
    ``timeout_s``: a regression that blocks on a FIFO or reads /dev/zero fails the test instead of
    hanging the suite or eating the machine's memory."""
    def cap_memory() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (2**30, 2**30))

    return subprocess.run([sys.executable, "-m", "nanodrift.cli", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=timeout_s, preexec_fn=cap_memory)


def ramp_config(tmp_path: Path, slew_um_per_s: float) -> Path:
    """A simulated cell left at 0 V on stop: from v_max = 12 V that is 600 um at 0.02 V/um."""
    write_test_model(tmp_path / "model.json")
    return config(tmp_path, "model.json", extra=f"[actuator]\nsafe_voltage_v = 0.0\nmax_slew_um_per_s = "
                                                f"{slew_um_per_s}\n")


def test_a_safe_stop_that_cannot_finish_in_the_stop_budget_is_refused_naming_the_slew(tmp_path: Path) -> None:
    """Issue 26.9: a stop that outlasts its budget leaves the stage energised between two voltages."""
    path = ramp_config(tmp_path, 1.0)  # 600 s, the unit allows 20 s of its 30 s stop for it
    result = run_cli("check-config", str(path))
    assert result.returncode == 2 and result.stdout == "", result.stderr
    # line 5: [model], path, [actuator], safe_voltage_v, then the slew key; 600 s at >= 90 % of the rate: 666.7 s
    assert (f"{path}:5: actuator.max_slew_um_per_s: the ramp to safe_voltage_v = 0 V at a stop can take "
            f"666.7 s (from 12 V: 600 um at 1 um/s, at 90% of it on a slow device), more than the "
            f"{SAFE_RAMP_BUDGET_S:g} s of the {STOP_TIMEOUT_S:g} s stop timeout it may use") in result.stderr, \
        result.stderr
    assert "allow at least 33.33 um/s" in result.stderr, result.stderr  # 600 um in 20 s at 90 % of the rate


@pytest.mark.parametrize(("slew_um_per_s", "said"), [
    (60.0, "safe stop: axis x to 0 V in at most 11.1 s (from 12 V: 600 um at 60 um/s"),  # 10 s at >= 90 %
    (0.0, None),  # no ramp at all
])
def test_a_safe_stop_that_fits_the_stop_is_stated_and_no_warning(
        tmp_path: Path, capsys, slew_um_per_s: float, said: str | None) -> None:
    code, out, err = check(capsys, str(ramp_config(tmp_path, slew_um_per_s)), "--strict")
    assert (code, err) == (0, ""), err
    assert (said in out) if said else "safe stop" not in out, out


def test_the_ramp_budget_leaves_room_in_the_stop_timeout() -> None:
    """The safe ramp gives up within its budget, and the budget is inside the unit's stop timeout."""
    assert Actuation(structlog.get_logger()).safe_budget_s == SAFE_RAMP_BUDGET_S < STOP_TIMEOUT_S


@pytest.mark.parametrize("kind", ["fifo", "dev-zero", "directory"])
def test_a_model_path_that_is_no_regular_file_is_refused_at_once(tmp_path: Path, kind: str) -> None:
    """A FIFO blocked the daemon's loop (8 s of stale refusals), /dev/zero was read until memory ran out."""
    if kind == "fifo":
        model = tmp_path / "model.fifo"
        os.mkfifo(model)
        what = "a FIFO (named pipe)"
    elif kind == "dev-zero":
        model, what = Path("/dev/zero"), "a character device"
    else:
        model, what = tmp_path, "a directory"
    path = config(tmp_path, str(model))
    started = time.monotonic()
    result = run_cli("check-config", str(path), timeout_s=30)
    assert result.returncode == 2 and result.stdout == "", result.stderr
    assert (f"{path}:2: model.path: {model}: {what}, not a model file: expected a regular file "
            "(nanodrift-model/1 JSON)") in result.stderr, result.stderr
    assert "Traceback" not in result.stderr and time.monotonic() - started < 30


@pytest.mark.parametrize(
    ("listen", "exposed"),
    [("0.0.0.0:9464", True), ("[::]:9464", True), ("192.168.1.10:9464", True), ("prometheus.lab:9464", True),
     ("127.0.0.1:9464", False), ("127.0.0.2:9464", False), ("localhost:9464", False), ("[::1]:9464", False)],
)
def test_a_metrics_page_other_computers_reach_is_a_warning(tmp_path: Path, capsys, listen: str, exposed: bool) -> None:
    """Issue 16: the page has no authentication; on loopback only unless the operator means it."""
    write_test_model(tmp_path / "model.json")
    path = config(tmp_path, "model.json", extra=f'[metrics]\nlisten = "{listen}"\n')
    code, out, err = check(capsys, str(path))
    assert code == 0 and f"{path}: ok" in out
    # line 4: [model], path, [metrics], then the listen key
    warning = f"{path}:4: warning: metrics.listen: {listen}: the metrics page is open to the network"
    assert (warning in err) is exposed, err
    code, _, err = check(capsys, str(path), "--strict")
    assert code == (2 if exposed else 0), err


def test_a_metrics_host_that_is_no_host_name_exits_2_naming_metrics_listen(tmp_path: Path, capsys) -> None:
    """It used to pass here and fail at start with a traceback from the resolver (a label over 63 characters)."""
    write_test_model(tmp_path / "model.json")
    path = config(tmp_path, "model.json", extra=f'[metrics]\nlisten = "{"a" * 64}.lab:9464"\n')
    code, out, err = check(capsys, str(path))
    assert code == 2 and out == ""
    assert f"{path}:4: metrics.listen: " in err and "is not an IP address" in err, err
    assert "Traceback" not in err


def serial_config(tmp_path: Path, command: str, limits: str = "", query: str = 'query = "POS? 1\\n"\n') -> Path:
    """A real-hardware cell: thermocouples on a Modbus hub, the stage's controller on one serial port."""
    write_test_model(tmp_path / "model.json")
    sensors = "".join(f'[[sensors]]\nname = "{name}"\nkind = "modbus"\nhub = "adam"\naddress = {i}\n'
                      'input_type = "input"\n' for i, name in enumerate(("T1", "T2")))
    path = tmp_path / "nanodrift.toml"
    path.write_text('[model]\npath = "model.json"\n[[hubs]]\nname = "adam"\nhost = "127.0.0.1"\n' + sensors +
                    '[[sensors]]\nname = "stage"\nrole = "position"\nkind = "serial_line"\nport = "/dev/ttyUSB0"\n'
                    f'baudrate = 115200\n{query}'
                    f'[actuator]\nkind = "serial_line"\nport = "/dev/ttyUSB0"\nreadback = "SVA? 1\\n"\n{limits}'
                    f"command = {command!r}\n")
    return path


def line_of(path: Path, key: str) -> int:
    """The line of ``key`` in [actuator] (the file's last table)."""
    lines = path.read_text().splitlines()
    return max(n for n, line in enumerate(lines, 1) if line.startswith(f"{key} ="))


def test_a_serial_command_template_coarser_than_10_nm_of_travel_is_a_warning(tmp_path: Path, capsys) -> None:
    path = serial_config(tmp_path, "SVA 1 {voltage_v:.2f}\\n")  # 10 mV at 0.02 V/um: 500 nm steps
    code, out, err = check(capsys, str(path))
    assert code == 0 and f"{path}: ok" in out, err
    assert (f"{path}:{line_of(path, 'command')}: warning: actuator.command: {{voltage_v:.2f}} writes voltage_v in "
            "steps of 0.01 V, 500 nm of stage travel at volts_per_um = 0.02, coarser than 10 nm") in err, err
    code, _, err = check(capsys, str(path), "--strict")
    assert code == 2 and "actuator.command: {voltage_v:.2f} writes voltage_v in steps" in err
    fine = serial_config(tmp_path, "SVA 1 {voltage_v:.4f}\\n")  # 0.1 mV: 5 nm
    code, _, err = check(capsys, str(fine))
    assert code == 0 and "actuator.command" not in err, err


def test_a_serial_command_template_that_cannot_write_the_limits_is_an_error(tmp_path: Path, capsys) -> None:
    path = serial_config(tmp_path, "SVA 1 {voltage_v:.0f}\\n", limits="v_min = -0.5\nv_max = 0.4\n")
    code, out, err = check(capsys, str(path))
    assert code == 2 and out == ""
    assert (f"{path}:{line_of(path, 'command')}: actuator.command: {{voltage_v:.0f}} cannot write the voltages "
            "within [v_min, v_max] = [-0.5, 0.4] V: it writes every one of them as '-0'") in err, err


def test_a_streaming_sensor_on_the_controllers_port_is_an_error(tmp_path: Path, capsys) -> None:
    path = serial_config(tmp_path, "SVA 1 {voltage_v:.4f}\\n", query="")
    code, _, err = check(capsys, str(path))
    assert code == 2
    assert (f"{path}:{line_of(path, 'port')}: actuator.port: sensors[2] (stage) streams lines on '/dev/ttyUSB0': "
            "its lines cannot be told from the answers") in err, err


def proof_config(tmp_path: Path, tolerance_um: float, *, position: bool) -> Path:
    """A simulated cell stating ``position_proof_tolerance_um``, with or without a position sensor."""
    write_test_model(tmp_path / "model.json")
    sensors = ("T1", "T2", "interferometer") if position else ("T1", "T2")
    path = config(tmp_path, "model.json", sensors=sensors,
                  extra=f"[actuator]\nposition_proof_tolerance_um = {tolerance_um}\n")
    if position:
        path.write_text(path.read_text().replace('name = "interferometer"\n',
                                                 'name = "interferometer"\nrole = "position"\n'))
    return path


def test_a_position_proof_states_the_largest_jump_it_may_allow_and_warns_without_a_sensor_or_when_too_wide(
        tmp_path: Path, capsys) -> None:
    code, out, err = check(capsys, str(proof_config(tmp_path, 5.0, position=True)), "--strict")
    assert (code, err) == (0, ""), err
    assert ("position proof: axis x by interferometer: a read-back nothing on record confirms is believed within "
            "5 um (0.1 V) of its reading: the most a first move may jump") in out, out
    path = proof_config(tmp_path, 5.0, position=False)
    code, out, err = check(capsys, str(path))
    assert code == 0 and "position proof" not in out, out
    assert (f"{path}:4: warning: actuator.position_proof_tolerance_um: no position sensor measures axis x (role = "
            '"position", axis = "x"): a read-back nothing on record confirms stays refused') in err, err
    wide = proof_config(tmp_path, 300.0, position=True)
    code, _, err = check(capsys, str(wide), "--strict")
    assert code == 2 and ("actuator.position_proof_tolerance_um: 300 um is half the axis' workspace (500 um) or more: "
                          "a position sensor would prove almost any read-back") in err, err
