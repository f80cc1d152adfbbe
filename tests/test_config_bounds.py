"""Every number is finite *and physical* (issue 10): huge values that pass a ``> 0`` check are refused too.

``[simulation] speed = 1e9`` passed check-config and froze the daemon (deaf to SIGTERM);
``interval_s = 1e-300`` spins the poller and ``max_age_s = 1e308`` makes any reading fresh, like
inf; a sensor ``scale = 0`` reads the offset whatever the device says. Issue 16: ``record_keep_days =
1000000`` failed every recorded row, ``max_slew_um_per_s = 1e-300`` never moved the stage. Each bound is refused
naming the field, and the values just inside it are accepted. Also: a hostile, deeply nested TOML
file is a message naming the file (never a traceback), check-config judges a sensor-less file as
the daemon's reload does, and the shipped ``config/sim.toml`` (the paper's four thermocouples) warns only of T3.
"""

from __future__ import annotations

import datetime as dt
import json
import subprocess
import sys
from pathlib import Path

import pytest
from helpers.daemon_harness import REPO, write_test_model
from helpers.daemon_harness import run_cli as harness_run_cli

from nanodrift.calibration.residuals import Settled
from nanodrift.config import MAX_RECORD_KEEP_DAYS, MIN_SLEW_UM_PER_S, ActuatorConfig, ConfigError, load_config
from nanodrift.drivers.base import MAX_AGE_S, MAX_INTERVAL_S, MIN_INTERVAL_S
from nanodrift.drivers.simulated.config import MAX_SPEED
from nanodrift.model.model import FittedTerm, Model, Training, load_model, save_model
from nanodrift.model.terms import parse_term
from nanodrift.motion import RAMP_PERIOD_S, Slew
from nanodrift.service.recorder import DayRecorder, file_name
from nanodrift.settings import DEFAULT_MODEL_PATH

SIM_SENSOR = '[[sensors]]\nname = "T1"\nkind = "simulated"\n'
MODBUS = ('[[hubs]]\nname = "adam"\nhost = "127.0.0.1"\n'
          '[[sensors]]\nname = "T1"\nkind = "modbus"\nhub = "adam"\naddress = 0\n')
SERIAL = ('[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "serial_line"\n'
          'port = "socket://127.0.0.1:4001"\n')


def problems_of(tmp_path: Path, text: str) -> list[str]:
    path = tmp_path / "nanodrift.toml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(path)
    assert info.value.source == str(path)
    return info.value.problems


def accepted(tmp_path: Path, text: str) -> None:
    path = tmp_path / "nanodrift.toml"
    path.write_text(text)
    load_config(path)


@pytest.mark.parametrize(
    ("text", "field", "words"),
    [
        ("[simulation]\nspeed = 1e9\n", "simulation.speed", f"less than or equal to {MAX_SPEED:g}"),
        ("[simulation]\nspeed = 1e308\n", "simulation.speed", f"less than or equal to {MAX_SPEED:g}"),
        (f"[simulation]\nspeed = {MAX_SPEED + 0.5}\n", "simulation.speed", "less than or equal"),
        ("[simulation]\nspeed = 0.0\n", "simulation.speed", "greater than 0"),
        (SIM_SENSOR + "interval_s = 1e-300\n", "sensors[0] (T1).interval_s", "greater than or equal to 0.001"),
        (SIM_SENSOR + "interval_s = 0.0009\n", "sensors[0] (T1).interval_s", "greater than or equal to 0.001"),
        (SIM_SENSOR + "interval_s = 3601.0\nmax_age_s = 7200.0\n", "sensors[0] (T1).interval_s",
         "less than or equal to 3600"),
        (SIM_SENSOR + "max_age_s = 1e308\n", "sensors[0] (T1).max_age_s", "less than or equal to 86400"),
        (SIM_SENSOR + "max_age_s = 86401.0\n", "sensors[0] (T1).max_age_s", "less than or equal to 86400"),
        (SIM_SENSOR + "interval_s = 2.0\nmax_age_s = 1.0\n", "sensors[0] (T1).max_age_s",
         "max_age_s = 1 s is below interval_s = 2 s: every reading would go stale before the next poll"),
        (MODBUS + "scale = 0.0\n", "sensors[0] (T1).scale", "must not be 0"),
        (MODBUS + "scale = -0.0\n", "sensors[0] (T1).scale", "must not be 0"),
        (SERIAL + "scale = 0\n", "sensors[0] (interferometer).scale", "must not be 0"),
        (SERIAL + "scale = 1e400\n", "sensors[0] (interferometer).scale", "finite"),
        ("[health]\nrecord_keep_days = 1000000\n", "health.record_keep_days",
         f"less than or equal to {MAX_RECORD_KEEP_DAYS}"),
        (f"[health]\nrecord_keep_days = {MAX_RECORD_KEEP_DAYS + 1}\n", "health.record_keep_days",
         f"less than or equal to {MAX_RECORD_KEEP_DAYS}"),
        ("[actuator]\nmax_slew_um_per_s = 1e-300\n", "actuator.max_slew_um_per_s",
         f"must be 0 (off) or at least {MIN_SLEW_UM_PER_S:g} um/s, got 1e-300"),
        (f"[actuator]\nmax_slew_um_per_s = {MIN_SLEW_UM_PER_S * 0.99}\n", "actuator.max_slew_um_per_s",
         f"must be 0 (off) or at least {MIN_SLEW_UM_PER_S:g} um/s"),
    ],
    ids=["speed=1e9", "speed=1e308", "speed>max", "speed=0", "interval=1e-300", "interval<1ms", "interval>1h",
         "max_age=1e308", "max_age>1day", "max_age<interval", "modbus-scale=0", "modbus-scale=-0",
         "serial-scale=0", "serial-scale=inf", "keep_days=1e6", "keep_days>century", "slew=1e-300",
         "slew<min"],
)
def test_an_out_of_bounds_number_is_refused_naming_the_field(tmp_path: Path, text: str, field: str,
                                                             words: str) -> None:
    problems = problems_of(tmp_path, text)
    assert any(p.startswith(f"{field}: ") and words in p for p in problems), problems


@pytest.mark.parametrize(
    "text",
    [
        f"[simulation]\nspeed = {MAX_SPEED}\n",
        "[simulation]\nspeed = 0.001\n",
        SIM_SENSOR + f"interval_s = {MIN_INTERVAL_S}\nmax_age_s = {MIN_INTERVAL_S}\n",  # equal: accepted
        SIM_SENSOR + f"interval_s = {MAX_INTERVAL_S}\nmax_age_s = {MAX_AGE_S}\n",
        MODBUS + "scale = -0.1\n",
        SERIAL + "scale = 1e-9\n",
        f"[health]\nrecord_keep_days = {MAX_RECORD_KEEP_DAYS}\n",
        "[health]\nrecord_keep_days = 0\n",
        f"[actuator]\nmax_slew_um_per_s = {MIN_SLEW_UM_PER_S}\n",
        "[actuator]\nmax_slew_um_per_s = 0.0\n",
    ],
    ids=["speed=max", "speed=slow", "interval=min", "interval=max", "modbus-scale<0", "serial-scale-tiny",
         "keep_days=century", "keep_days=0", "slew=min", "slew=off"],
)
def test_values_at_the_bounds_are_accepted(tmp_path: Path, text: str) -> None:
    accepted(tmp_path, text)


def test_the_longest_retention_works_at_runtime(tmp_path: Path) -> None:
    """A row recorded with the largest ``record_keep_days`` check-config accepts is written, and the
    expiry spares a file of the day before (1,000,000 days failed every row: "date value out of range")."""
    records = tmp_path / "records"
    records.mkdir()
    yesterday = records / file_name(dt.date(2026, 11, 22), 1)
    yesterday.write_text("t_s,x_um,q_um,target_um,residual_um\n")
    recorder = DayRecorder(records, keep_days=MAX_RECORD_KEEP_DAYS)
    noon = dt.datetime(2026, 11, 23, 12, tzinfo=dt.UTC).timestamp()
    written = recorder.record({"x": Settled(t=1.0, x_um=30.0, q_um=30.5, position_um=30.001, samples=10,
                                            temperatures={"T1": 21.0})}, noon)
    recorder.close()
    assert written and recorder.rows_written == 1 and recorder.rows_lost == 0
    assert yesterday.exists()


def test_the_slowest_slew_still_moves_the_stage() -> None:
    """At the slowest accepted ``max_slew_um_per_s`` every 20 ms sub-command moves the stage (at 1e-300
    the step vanished in floating point and the ramp wrote the same voltage for ever)."""
    limits = ActuatorConfig(max_slew_um_per_s=MIN_SLEW_UM_PER_S)
    slew, now_s, at_v, goal_v = Slew(), 0.0, limits.voltage(500.0), limits.voltage(499.99)
    steps = []
    while at_v != goal_v and len(steps) < 1000:
        at_v = slew.next_voltage(limits, at_v, goal_v, now_s)
        slew.wrote(now_s, at_v == goal_v)
        steps.append(at_v)
        now_s += RAMP_PERIOD_S
    assert len(steps) == round(0.01 / (MIN_SLEW_UM_PER_S * RAMP_PERIOD_S))  # 50 writes over one second
    assert all(later < earlier for earlier, later in zip([limits.voltage(500.0), *steps], steps, strict=False))
    assert steps[-1] == goal_v


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift ARGS`` in this process (the console script's ``main``; a process each costs half a second)."""
    return harness_run_cli(*args, cwd=REPO)


def run_cli_process(*args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift ARGS`` in a process of its own: an input built to exhaust the parser's recursion stays there."""
    return subprocess.run([sys.executable, "-m", "nanodrift.cli", *args], capture_output=True, text=True, cwd=REPO,
                          timeout=60)


# ids: the parameter itself in the test id would reach the CLI subprocess through PYTEST_CURRENT_TEST, an
# environment string over the kernel's 128 KiB limit ("Argument list too long")
@pytest.mark.parametrize("nesting", ["[" * 100_000 + "]" * 100_000, "{a = " * 5000 + "1" + "}" * 5000],
                         ids=["arrays", "tables"])
def test_check_config_on_a_deeply_nested_toml_exits_2_naming_the_file(tmp_path: Path, nesting: str) -> None:
    deep = tmp_path / "deep.toml"
    deep.write_text(f"x = {nesting}\n")
    result = run_cli_process("check-config", str(deep))
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == f"nanodrift check-config: error: {deep}: not valid TOML: nested too deeply " \
                                    "(a nanodrift config nests a few levels of [ and {, not hundreds)", result.stderr
    assert "Traceback" not in result.stderr and result.stdout == ""


def sensorless_config(tmp_path: Path, model: Path) -> Path:
    path = tmp_path / "nanodrift.toml"
    path.write_text(f'cell = "c0"\n[model]\npath = "{model}"\n')
    return path


def test_check_config_refuses_a_sensorless_file_whose_model_needs_channels_as_a_reload_would(tmp_path: Path) -> None:
    """An emptied file on a real install (its model exists): the running daemon refuses it on reload."""
    model = write_test_model(tmp_path / "model.json")  # needs T1 and T2
    path = sensorless_config(tmp_path, tmp_path / "model.json")
    result = run_cli("check-config", str(path))
    assert result.returncode == 2 and result.stdout == "", result
    assert (f"{path}: sensors: the config lists no sensors (an emptied file?) and model {model.id} needs T1, T2: "
            "a running daemon with sensors refuses it on reload") in result.stderr, result.stderr


def test_check_config_warns_about_a_sensorless_file_a_daemon_may_run(tmp_path: Path) -> None:
    """A model of x alone needs no sensor: the daemon starts with the file and serves; a reload from a
    cell with sensors still refuses it, so check-config says so (an error with --strict)."""
    model = Model(terms=[FittedTerm(parse_term("x"), 1.001), FittedTerm(parse_term("1"), 0.2)],
                  training=Training((0.0, 480.0), {}, 50, 600.0))
    save_model(model, tmp_path / "model.json")
    path = sensorless_config(tmp_path, tmp_path / "model.json")
    result = run_cli("check-config", str(path))
    assert result.returncode == 0, result.stderr
    assert f"{path}: ok: cell 'c0', 0 sensor(s)" in result.stdout
    assert (f"{path}: warning: sensors: the config lists no sensors: a running daemon with sensors refuses it on "
            "reload") in result.stderr, result.stderr
    strict = run_cli("check-config", "--strict", str(path))
    assert strict.returncode == 2 and "sensors: the config lists no sensors" in strict.stderr, strict.stderr


def test_the_shipped_sim_toml_lists_the_papers_four_thermocouples_and_strict_names_only_the_unused_ones() -> None:
    """Issue 27: the paper monitors T1..T4; check-config warns once for each one the shipped model leaves out."""
    unused = sorted({"T1", "T2", "T3", "T4"} - set(load_model(DEFAULT_MODEL_PATH).channels))
    assert unused, "the shipped model uses every thermocouple: the test proves nothing"
    result = run_cli("check-config", str(REPO / "config" / "sim.toml"))
    assert result.returncode == 0, result.stderr
    warnings = [line for line in result.stderr.splitlines() if "warning" in line]
    assert len(warnings) == len(unused), result.stderr
    for channel, line in zip(unused, warnings, strict=True):
        assert f"sensor '{channel}' is not used by model" in line, result.stderr
    strict = run_cli("check-config", "--strict", str(REPO / "config" / "sim.toml"))
    assert strict.returncode == 2 and f"sensor '{unused[0]}' is not used by model" in strict.stderr, strict.stderr
    model = json.loads((REPO / "daemon" / "data" / "default_model.json").read_text())
    configured = load_config(REPO / "config" / "sim.toml")
    temperatures = [s.name for s in configured.sensors if s.role == "temperature"]
    assert temperatures == ["T1", "T2", "T3", "T4"]
    assert set(model["channels"]) < set(temperatures), (temperatures, model["channels"])  # none missing
