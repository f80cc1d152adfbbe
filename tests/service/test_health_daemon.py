"""Issue 12 in the daemon: health, adaptation and per-command uncertainty, end to end.

Each daemon is ``nanodrift run`` in its own process, reached by a real Zenoh client over 127.0.0.1.
The simulated cell (its room sped up 5x, its interferometer the ``role = "position"`` sensor) serves
the shipped model, right or with its bias moved by +0.3 um; the stale/faulted interferometer is the
harness's ``file`` plugin, whose readings the test controls exactly. The health unit's own rules
(repeated, old or missing readings, reloads) are checked in process on the same classes.
"""

from __future__ import annotations

import dataclasses
import math
import signal
import urllib.request
from pathlib import Path
from typing import Any

import pytest
from helpers.cell_helpers import write_cell_model
from helpers.daemon_harness import (
    TEMPS,
    HealthCell,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)
from prometheus_client.parser import text_string_to_metric_families

from nanodrift.compensation import Command, Target
from nanodrift.config import DEFAULT_MODEL_PATH, Config, parse_config
from nanodrift.drivers.base import MonotonicClock, Reading, SensorConfig
from nanodrift.model.model import Model, load_model, save_model
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.state import CellState, serving_state
from nanodrift.service.status import status_line
from nanodrift.service.table import SensorTable

SPEED = 5.0
FAST_HEALTH = "settle_s = 0.5\nwindow_s = 0.5\n"  # simulated seconds: 0.2 s of wall time per held target
X_CYCLE = (0.0, 80.0, 160.0, 240.0, 320.0, 400.0, 480.0)


def shifted_model(path: Path, bias_um: float) -> Model:
    """The shipped model with its bias term ("1") moved by ``bias_um``, under its own content id."""
    base = load_model(DEFAULT_MODEL_PATH)
    terms = [dataclasses.replace(ft, coef=ft.coef + bias_um) if ft.term.name == "1" else ft for ft in base.terms]
    model = Model(terms=terms, training=base.training, fit=base.fit, selection=base.selection,
                  provenance=base.provenance, covariance=base.covariance)  # no id given: the content id
    save_model(model, path)
    return model


def model_q(model: Model, command: dict[str, Any]) -> float:
    """What ``model`` alone commands for this command's target and temperatures (its terms are static)."""
    evaluator = model.evaluator()
    evaluator.observe(0.0, command["temperatures_c"])
    return evaluator.value(command["x_um"], 0.0)


def scrape(url: str) -> dict[tuple[str, tuple[tuple[str, str], ...]], float]:
    with urllib.request.urlopen(url, timeout=10) as response:
        text = response.read().decode()
    return {(s.name, tuple(sorted(s.labels.items()))): s.value
            for family in text_string_to_metric_families(text) for s in family.samples}


def sim_config(cell: str, port: int, model_path: Path, *, position: bool = True, scenario: str = "room",
               adapt: str = "", seed: int = 4) -> str:
    # max ages of 30 s of wall time (the clock runs at SPEED): a loaded machine may stall a poller for seconds, and
    # a stale interferometer voids the window (tested with the file sensors below), so no residual would come
    sensors = "".join(f'[[sensors]]\nname = "{n}"\nkind = "simulated"\ninterval_s = 1.0\nmax_age_s = {30 * SPEED}\n'
                      for n in ("T1", "T2", "T3", "T4"))
    if position:
        sensors += ('[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "simulated"\n'
                    f"interval_s = 0.1\nmax_age_s = {30 * SPEED}\n")
    return (f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
            f'[model]\npath = "{model_path}"\n[health]\n{FAST_HEALTH}[adapt]\n{adapt}\n'
            f'[simulation]\nscenario = "{scenario}"\nspeed = {SPEED}\nseed = {seed}\n{sensors}')


# --- over Zenoh, on the simulated cell -------------------------------------------------------------


def test_a_model_with_its_bias_moved_goes_degraded_and_every_command_states_its_uncertainty(tmp_path: Path) -> None:
    model = shifted_model(tmp_path / "shifted.json", +0.3)
    config = sim_config("hbias", 0, tmp_path / "shifted.json").replace("127.0.0.1:0", "127.0.0.1:@PORT@")
    cell = HealthCell(tmp_path, "hbias", config + f'[metrics]\nlisten = "127.0.0.1:{free_port()}"\n')
    try:
        assert cell.client is not None
        cell.client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
        commands = []
        for i in range(30):  # "within a few dozen targets"
            commands.append(cell.settle(X_CYCLE[i % len(X_CYCLE)], i))
            if cell.health()["state"] == "degraded":
                break
        health = cell.health()
        assert health["state"] == "degraded", health
        assert len(commands) <= 8  # degraded as soon as there are enough residuals (5)
        # +0.3 um in q puts the stage 0.3 um beyond the target: residual = position - target = +300 nm
        assert health["residual_mean_nm"] == pytest.approx(300.0, abs=80.0)
        assert health["residual_rms_nm"] > 100.0 and health["n"] == len(commands)
        assert "recalibrate" in health["advice"] and health["correction_um"] is None  # adaptation is off
        assert all(c["model"] == model.id and "correction_um" not in c for c in commands)
        assert all(c["q_um"] == pytest.approx(model_q(model, c), abs=1e-9) for c in commands)
        # published on nanodrift/<cell>/health when the state changed, and logged once per transition
        wait_until(lambda: any(s["state"] == "degraded" for s in cell.samples()), 10, "a degraded health sample")
        for i in range(3):
            cell.settle(240.0, f"more-{i}")
        degraded = cell.daemon.log_events("health_degraded")
        assert len(degraded) == 1 and degraded[0]["level"] == "warning", degraded
        assert degraded[0]["residual_mean_nm"] == pytest.approx(300.0, abs=80.0)
        # Prometheus reads the same document, in base units
        samples = scrape(cell.daemon.wait_log("metrics_listening")["url"])
        health = cell.health()
        assert samples[("nanodrift_health_state", (("cell", "hbias"), ("state", "degraded")))] == 1.0
        assert samples[("nanodrift_health_state", (("cell", "hbias"), ("state", "ok")))] == 0.0
        assert samples[("nanodrift_health_residual_mean_meters", (("cell", "hbias"),))] == pytest.approx(
            health["residual_mean_nm"] * 1e-9, rel=0.2)
        assert samples[("nanodrift_health_residuals", (("cell", "hbias"),))] == health["n"]
        assert ("nanodrift_health_correction_meters", (("cell", "hbias"),)) not in samples  # adaptation off

        # every command states its uncertainty; a target outside the training range x gets a larger one
        assert all(c["q_sigma_um"] > 0.0 for c in commands)
        ok, inside = cell.client.query({"x_um": 480.0, "id": "edge"})
        ok2, outside = cell.client.query({"x_um": 500.0, "id": "beyond"})
        assert ok and ok2
        assert inside["extrapolating"] == [] and outside["extrapolating"] == ["x"]
        assert outside["q_sigma_um"] > inside["q_sigma_um"] > 0.0
        assert list(outside)[-2:] == ["extrapolating", "q_sigma_um"]  # the wire order: new keys at the end
    finally:
        assert cell.close() == 0


def test_the_right_model_stays_ok_and_adaptation_cancels_a_bias_after_a_reload(tmp_path: Path) -> None:
    adapt = 'mode = "bias"\ntau_s = 5.0\nmax_um = 1.0\n'
    config = sim_config("hadapt", 0, DEFAULT_MODEL_PATH, adapt=adapt, seed=6).replace("127.0.0.1:0",
                                                                                       "127.0.0.1:@PORT@")
    cell = HealthCell(tmp_path, "hadapt", config)
    try:
        assert cell.client is not None
        cell.client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
        right = [cell.settle(X_CYCLE[i % len(X_CYCLE)], i) for i in range(8)]
        health = cell.health()
        assert health["state"] == "ok", health  # the model fits the cell: no alarm
        assert abs(health["residual_mean_nm"]) < 80.0 and health["residual_rms_nm"] < 100.0
        assert right[0]["correction_um"] == 0.0  # adaptation on: every command shows its correction ...
        assert right[0]["q_sigma_adapted_um"] == right[0]["q_sigma_um"]  # ... and its σ (nothing learnt yet)
        assert all(abs(c["correction_um"]) < 0.1 for c in right)
        assert not cell.daemon.log_events("health_degraded")

        # a reload with another model starts the monitor and the tracker afresh
        shifted = shifted_model(tmp_path / "shifted.json", +0.3)
        cell.config_path.write_text(cell.config_path.read_text().replace(str(DEFAULT_MODEL_PATH),
                                                                         str(tmp_path / "shifted.json")))
        cell.daemon.signal(signal.SIGHUP)
        cell.daemon.wait_log("reload_applied")
        health = cell.health()
        assert (health["state"], health["n"], health["correction_um"]) == ("unknown", 0, 0.0)

        first = cell.settle(240.0, "after-reload")
        assert first["model"] == shifted.id and first["correction_um"] == 0.0
        assert first["q_sigma_adapted_um"] == first["q_sigma_um"]  # a fresh tracker: the new model's own σ
        # its residual (+0.3 um) moved the correction towards -0.3 um; q = model + correction
        later = [cell.settle(X_CYCLE[i % len(X_CYCLE)], f"later-{i}") for i in range(4)]
        # the +0.3 um the first residual showed counts in the corrected commands' σ (issue 19)
        assert later[0]["q_sigma_adapted_um"] > 0.2 > later[0]["q_sigma_um"]
        for command in later:
            assert command["correction_um"] == pytest.approx(-0.3, abs=0.08)
            assert command["q_um"] == pytest.approx(model_q(shifted, command) + command["correction_um"], abs=1e-9)
            assert command["voltage_v"] == pytest.approx(0.02 * command["q_um"])
        health = cell.health()
        assert health["correction_um"] == pytest.approx(-0.3, abs=0.08)
        assert abs(health["residual_mean_nm"] - 300.0 / health["n"]) < 60.0  # only the first one was off
    finally:
        assert cell.close() == 0


def test_without_a_position_sensor_health_is_unknown_and_extrapolation_raises_the_uncertainty(
        tmp_path: Path) -> None:
    """Test 5's room (beyond the training range from the start), no interferometer."""
    config = sim_config("hnone", 0, DEFAULT_MODEL_PATH, position=False, scenario="test5").replace(
        "127.0.0.1:0", "127.0.0.1:@PORT@")
    cell = HealthCell(tmp_path, "hnone", config)
    try:
        assert cell.client is not None
        cell.client.wait_ready(["T1", "T2", "T3", "T4"])
        answers = [cell.client.query({"x_um": x, "id": i}) for i, x in enumerate(X_CYCLE)]
        assert all(ok for ok, _ in answers), answers
        status = cell.client.status()
        health = status["health"]
        assert health["state"] == "unknown" and health["n"] == 0 and health["residual_rms_nm"] is None
        assert "no position sensor" in health["advice"]
        # no change of state to announce: the health document is still published every few seconds
        sample = wait_until(lambda: next(iter(cell.samples()), None), 12, "a periodic health sample")
        assert sample["state"] == "unknown" and set(sample) == {"state", "residual_rms_nm", "residual_mean_nm", "n",
                                                               "correction_um", "extrapolating", "advice",
                                                               "holds_unrecorded", "residuals_rejected"}
        assert sample["extrapolating"]  # test 5's room, named in the document too
        # the uncertainty grows outside the training range: the model's own sigma in its range is ~0.09 um
        model = load_model(DEFAULT_MODEL_PATH)
        evaluator = model.evaluator()
        evaluator.observe(0.0, {c: (lo + hi) / 2 for c, (lo, hi) in model.training.channel_ranges.items()})
        in_range = max(evaluator.sigma(x, 0.0) for x in X_CYCLE)
        for _, command in answers:
            assert command["extrapolating"], command  # test 5: the room is above the training range
            assert command["q_sigma_um"] > 1.5 * in_range
    finally:
        assert cell.close() == 0


def test_a_faulted_or_stale_interferometer_never_feeds_the_monitor_or_the_tracker(tmp_path: Path) -> None:
    """The position sensor is the ``file`` plugin (wall clock): the test says what it reads and when."""
    plugins = install_file_plugin(tmp_path / "plugins")
    model = tmp_path / "model.json"
    write_test_model(model)
    sensors = SensorFile(tmp_path / "sensors.json", {**TEMPS, "interferometer": 0.0})
    settle_s, window_s = 0.1, 0.2
    extra = (f"[health]\nsettle_s = {settle_s}\nwindow_s = {window_s}\n[adapt]\nmode = \"bias\"\ntau_s = 1.0\n"
             f'[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "file"\npath = "{sensors.path}"\n'
             "interval_s = 0.05\nmax_age_s = 1.0\n")
    config = file_sensor_config(tmp_path, cell="hstale", port=0, model_path=model, sensor_file=sensors.path,
                                extra=extra).replace("127.0.0.1:0", "127.0.0.1:@PORT@")
    cell = HealthCell(tmp_path, "hstale", config, plugins)
    try:
        client = cell.client
        assert client is not None
        client.wait_ready(["T1", "T2", "interferometer"])

        def read_after(command: dict[str, Any]) -> None:
            """Until the daemon has a position reading stamped after the command's window (a witness: had
            the readings inside the window counted, the window would now be closed and counted)."""
            end = command["t"] + settle_s + window_s + 0.1
            wait_until(lambda: (p := client.telemetry.get("position")) is not None and p["t"] > end,
                       10, "a position reading stamped after the window")

        sensors.set(interferometer=100.3)  # the stage 0.3 um beyond the target
        cell.settle(100.0, "good")
        health = cell.health()
        assert health["n"] == 1 and health["residual_mean_nm"] == pytest.approx(300.0, abs=1e-6)
        correction = health["correction_um"]
        assert correction == pytest.approx(-0.3, abs=0.01)  # the tracker took the residual

        sensors.write(fault={"interferometer": "beam lost"})
        ok, faulted = client.query({"x_um": 200.0, "id": "faulted"})
        assert ok and faulted["correction_um"] == correction
        read_after(faulted)
        assert client.telemetry["position"]["state"] == "fault"
        assert (cell.health()["n"], cell.health()["correction_um"]) == (1, correction)

        sensors.write(fault={}, age={"interferometer": 1.5})  # readings 1.5 s old, max_age_s 1: stale
        sensors.set(interferometer=300.5)
        ok, stale = client.query({"x_um": 300.0, "id": "stale"})
        assert ok
        read_after(stale)
        assert (cell.health()["n"], cell.health()["correction_um"]) == (1, correction)

        sensors.write(age={})  # fresh again: the next held target counts
        sensors.set(interferometer=400.0)
        cell.settle(400.0, "fresh")
        health = cell.health()
        assert health["n"] == 2 and health["residual_mean_nm"] == pytest.approx(150.0, abs=1e-6)
    finally:
        assert cell.close() == 0


# --- in process: the health unit's rules ---------------------------------------------------------


#: a one-axis cell and an XY cell (each axis with its own interferometer): the same health unit, the same tests
CELLS = pytest.mark.parametrize("axes", [("x",), ("x", "y")], ids=["one-axis", "xy"])
#: each axis' position sensor
POSITION = {"x": "interferometer", "y": "ifm_y"}


def unit_config(axes: tuple[str, ...] = ("x",), *, position: bool = True, adapt: dict[str, Any] | None = None,
                **health: Any) -> Config:
    cell = [{"name": a, "actuator": {"kind": "zenoh"}} for a in axes] if len(axes) > 1 else None
    config = parse_config({"health": {"settle_s": 3.0, "window_s": 2.0, **health}, "adapt": adapt or {},
                           "sensors": [], **({"axes": cell} if cell else {})}, source="unit.toml")
    sensors = [SensorConfig(name="T1", kind="x", max_age_s=5.0), SensorConfig(name="T2", kind="x", max_age_s=5.0)]
    if position:
        sensors += [SensorConfig(name=POSITION[a], kind="x", role="position", max_age_s=1.0) for a in axes]
    config = config.model_copy(update={"sensors": sensors})
    config._sensor_axes = {POSITION[a]: a for a in axes if a != "x"}  # what [[sensors]] axis = "y" says
    return config


class Unit:
    """A health unit serving through a compensator on the harness's test model (XY: a hand-made cell model)."""

    def __init__(self, tmp_path: Path, config: Config) -> None:
        self.axes = config.axis_names
        path = tmp_path / "m.json"
        self.model = write_test_model(path) if self.axes == ("x",) else write_cell_model(path, self.axes)
        self.config = config
        self.table = SensorTable(config.sensors)
        self.log = _NullLog()
        self.health = HealthUnit(config, None, self.log)
        self.compensator = serving_state(config, self.model, self.health, table=self.table)
        self.x = self.health.watches["x"]

    def command(self, t: float, x: float, target_id: object = None) -> Command:
        """Every axis to ``x``."""
        for name, value in TEMPS.items():
            self.table.update(name, Reading(value, t=t))
        self.compensator.observe(t, TEMPS)
        return self.compensator.compensate(Target(target_id, dict.fromkeys(self.axes, x)), t, 1.7e9 + t)

    def position(self, now: float, t: float, value_um: float, ok: bool) -> None:
        """The same reading from every axis' position sensor."""
        for axis in self.axes:
            self.health.on_position(now, t, value_um, ok, channel=POSITION[axis])

    def hold(self, t: float, x: float, position_um: float) -> None:
        """A command at ``t`` and readings every 0.5 s through its window and past it."""
        self.command(t, x)
        for k in range(1, 13):
            self.position(t + 0.5 * k, t + 0.5 * k, position_um, True)

    def counts(self) -> set[int]:
        """The residuals each axis' rolling statistics hold (one value: every axis the same)."""
        return {w.monitor.n for w in self.health.watches.values()}

    def axis_doc(self) -> dict[str, Any]:
        """The x axis' health document (a one-axis cell's whole document)."""
        doc = self.health.document()
        return doc if self.axes == ("x",) else doc["axes"]["x"]

    def held(self, handed: list[tuple[Any, float]]) -> list[Any]:
        """The x axis' :class:`Settled` of every recorded row (a row holds every axis of the cell)."""
        rows = [row for row, _ in handed]
        assert all(set(row) == set(self.axes) for row in rows)
        return [row["x"] for row in rows]


class _NullLog:
    def __init__(self) -> None:
        self.lines: list[tuple[str, dict[str, Any]]] = []

    def info(self, event: str, **fields: Any) -> None:
        self.lines.append((event, fields))

    warning = info

    def bind(self, **fields: Any) -> _NullLog:
        return self


@CELLS
def test_the_unit_counts_only_fresh_new_ok_readings(tmp_path: Path, axes: tuple[str, ...]) -> None:
    unit = Unit(tmp_path, unit_config(axes))
    health = unit.health
    handed: list[tuple[Any, float]] = []
    health.settled_listeners.append(lambda settled, unix_s, polled: handed.append((settled, unix_s)))
    unit.hold(0.0, 100.0, 100.2)
    assert unit.counts() == {1} and unit.axis_doc()["residual_mean_nm"] == pytest.approx(200.0)
    health.flush()  # the recorder's hook: each settled target once, outside the lock, with its unix time
    assert [(s.x_um, s.samples, s.t) for s in unit.held(handed)] == [(100.0, 5, 5.0)] and handed[0][1] > 1.7e9
    first = unit.held(handed)[0]
    assert first.residual_um == pytest.approx(0.2) and set(first.temperatures) == set(unit.compensator.channels)

    unit.command(10.0, 200.0)  # a reading inside the window that is not ok (faulted or too old) voids it
    unit.position(13.5, 13.5, 200.2, True)
    unit.position(14.0, 12.0, 200.2, False)
    unit.position(15.5, 15.5, 200.2, True)
    assert unit.counts() == {1}

    unit.command(20.0, 300.0)  # silent through the window for longer than max_age_s (1 s): stale meanwhile
    unit.position(23.2, 23.2, 300.2, True)
    unit.position(24.8, 24.8, 300.2, True)
    unit.position(25.5, 25.5, 300.2, True)
    assert unit.counts() == {1}

    unit.command(30.0, 400.0)  # the same sample again is not news: one sample, not three
    for _ in range(3):
        unit.position(33.5, 33.5, 400.9, True)
    unit.position(34.5, 34.5, 400.0, True)
    unit.position(35.5, 35.5, 400.0, True)
    assert unit.counts() == {2}  # 200 nm, then (400.9 + 400.0) / 2 - 400 = 450 nm
    assert unit.axis_doc()["residual_mean_nm"] == pytest.approx(325.0)
    health.flush()
    assert [s.x_um for s in unit.held(handed)] == [100.0, 400.0]

    for k, x in enumerate((10.0, 20.0, 30.0)):  # a burst between two readings: the last target is the one held
        unit.command(40.0 + 0.01 * k, x)
    for k in range(1, 13):
        unit.position(40.02 + 0.5 * k, 40.02 + 0.5 * k, 30.1, True)
    health.flush()
    assert [s.x_um for s in unit.held(handed)][2:] == [30.0] and unit.counts() == {3}
    assert not any(w.served for w in health.watches.values())


@CELLS
def test_a_new_model_or_new_settings_on_reload_start_afresh_and_the_same_model_carries_on(
        tmp_path: Path, axes: tuple[str, ...]) -> None:
    config = unit_config(axes, adapt={"mode": "bias", "tau_s": 60.0})
    unit = Unit(tmp_path, config)
    for k in range(6):
        unit.hold(20.0 * k, 100.0, 100.5)
    health = unit.health
    correction = health.correction_um()
    assert health.state == "degraded" and correction is not None and set(correction) == set(axes)
    assert all(c < -0.1 for c in correction.values())
    health.flush()
    assert [e for e, _ in unit.log.lines] == ["health_degraded"] * len(axes)  # each axis says it

    # a reload that only touched the actuator: the monitor and the correction carry on into the new compensator
    same = serving_state(config, unit.model, health, running=unit.compensator, table=unit.table)
    assert unit.counts() == {6} and health.correction_um() == correction
    assert same.compensate(Target(1, dict.fromkeys(axes, 100.0)), 101.0, 0.0).correction_um == correction
    assert health.watches["x"].served[-1][2].correction_um == correction  # ... and it queues its commands here
    recording = config.model_copy(update={"health": config.health.model_copy(update={"record_dir": "/tmp/r"})})
    serving_state(recording, unit.model, health, running=same, table=unit.table)  # recording is not the monitor's
    assert unit.counts() == {6}

    if axes == ("x",):
        other: Any = write_test_model(tmp_path / "other.json", {"x^3": 0.0, "x^2": 0.0, "x": 1.0, "T1": 0.0,
                                                                "T2": 0.0, "1": 0.0})
    else:
        other = write_cell_model(tmp_path / "other.json", axes, max_um=400.0)
    fresh = serving_state(config, other, health, running=same, table=unit.table)
    assert (health.state, unit.counts(), health.correction_um()) == ("unknown", {0}, dict.fromkeys(axes, 0.0))
    health.flush()
    assert [e for e, _ in unit.log.lines] == ["health_degraded"] * len(axes) + ["health_recovered"] * len(axes)

    off = config.model_copy(update={"adapt": config.adapt.model_copy(update={"mode": "off"})})
    unit.compensator = serving_state(off, other, health, running=fresh, table=unit.table)
    assert health.correction_um() is None and all(w.tracker is None for w in health.watches.values())
    assert unit.command(200.0, 100.0).correction_um is None


@CELLS
def test_without_a_position_sensor_nothing_is_queued_and_the_state_is_unknown(tmp_path: Path,
                                                                               axes: tuple[str, ...]) -> None:
    unit = Unit(tmp_path, unit_config(axes, position=False))
    assert all(w.position_channel is None for w in unit.health.watches.values())
    command = unit.command(0.0, 100.0)
    assert command.q_sigma_um is not None and all(map(math.isnan, command.q_sigma_um.values()))  # no statistics
    assert unit.health.document()["state"] == "unknown" and not any(w.served for w in unit.health.watches.values())


def test_the_status_line_carries_the_health_state(tmp_path: Path) -> None:
    unit = Unit(tmp_path, unit_config())
    state = CellState(unit.config, unit.compensator, MonotonicClock())
    assert status_line(state, unit.health).endswith(", health unknown")
    for k in range(5):
        unit.hold(20.0 * k, 100.0, 100.0 + 0.01 * (-1) ** k)
    assert status_line(state, unit.health).endswith(", health ok")
    assert unit.health.document()["residual_rms_nm"] == pytest.approx(10.0)
