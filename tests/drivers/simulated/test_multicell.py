"""The simulated stacked stage stepped through time (``[simulation] axes``): its config defaults, its physics."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from nanodrift.config import ConfigError, load_config
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.clock import VirtualClock
from nanodrift.drivers.simulated.physics import CellPhysics
from nanodrift.settings import DATA_DIR


def _load(tmp_path: Path, text: str):  # type: ignore[no-untyped-def]
    path = tmp_path / "cell.toml"
    path.write_text(text)
    return load_config(path)


def test_simulation_axes_alone_brings_the_axes_sensors_and_shipped_model(tmp_path: Path) -> None:
    config = _load(tmp_path, '[simulation]\naxes = "xyz"\n')
    assert config.axis_names == ("x", "y", "z")
    assert {a: c.workspace_um for a, c in config.axis_actuators().items()} == dict.fromkeys("xyz", (0.0, 480.0))
    assert {a: c.kind for a, c in config.axis_actuators().items()} == dict.fromkeys("xyz", "simulated")
    assert {a: s.name for a, s in config.position_sensors().items()} == {a: f"interferometer_{a}" for a in "xyz"}
    assert [s.name for s in config.sensors if s.role == "temperature"] == ["T1", "T2", "T3", "T4"]
    assert config.model.path == DATA_DIR / "default_model_xyz.json"


def test_one_axis_simulation_keeps_its_defaults(tmp_path: Path) -> None:
    config = _load(tmp_path, '[simulation]\nscenario = "steady"\n')
    assert not config.multi_axis and config.model.path == DATA_DIR / "default_model.json"
    assert [s.name for s in config.sensors] == ["T1", "T2", "T3", "T4", "interferometer"]


@pytest.mark.parametrize(("text", "expected"), [
    ('[simulation]\naxes = "xy"\n[actuator]\nvolts_per_um = 0.02\n', "actuator: the simulated cell has axes x, y"),
    ('[simulation]\naxes = "yz"\n', "unknown simulated axes 'yz'"),
    ('[simulation]\naxes = "xy"\neffects = ["creep"]\n', "the hidden effects are the one-axis cell's"),
])
def test_a_wrong_simulated_stack_is_refused_saying_why(tmp_path: Path, text: str, expected: str) -> None:
    with pytest.raises(ConfigError, match=expected):
        _load(tmp_path, text)


def test_commanding_one_axis_moves_what_every_beam_reads_as_the_stack_physics_says() -> None:
    physics = CellPhysics.create("steady", seed=2, axes="xy")
    clock = VirtualClock(100.0)
    cell = SimulatedCell(physics, clock)
    cell.epoch = 0.0
    before = cell.true_positions()
    cell.command("y", 400.0)  # only y moves: x sees the crosstalk and the tilt of the upper stage
    after = cell.true_positions()
    static = physics.static({"x": np.array([0.0]), "y": np.array([400.0])})
    drift = physics.drift(np.array([100.0]))
    assert after["y"] == pytest.approx(float(static["y"][0] + drift["y"][0]), abs=0.02)  # within the landing error
    assert after["x"] - before["x"] == pytest.approx(float(static["x"][0]), abs=0.02)
    assert abs(after["x"] - before["x"]) > 0.5  # a stacked stage: ~1.7 µm on x for 400 µm of y
    read = cell.read(["interferometer_x", "interferometer_y", "T1"])
    assert read["interferometer_y"].value == pytest.approx(after["y"], abs=0.2)  # noise + wander
    assert read["interferometer_y"].unit == "um" and read["T1"].unit == "degC"
    assert cell.true_reading("interferometer_x") == pytest.approx(after["x"]) and cell.true_reading("T1") is None
