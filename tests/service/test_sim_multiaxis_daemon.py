"""``nanodrift run`` on the simulated stacked stage (``[simulation] axes = "xy"`` / ``"xyz"``), over real Zenoh.

No ``[[axes]]`` or ``[[sensors]]``: the simulated cell brings its axes (0..480 µm, a simulated output
each), T1..T4 and one interferometer per axis, and the shipped model of that stage. A target answered
with a command moves the simulated stage: each axis' own interferometer then reads near its target.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from helpers.daemon_harness import Client, Daemon, free_port, wait_until

from nanodrift.model.cell_model import load_any_model
from nanodrift.settings import DATA_DIR


def _served(tmp_path: Path, axes: str) -> tuple[Daemon, Client]:
    port = free_port()
    config = tmp_path / f"sim_{axes}.toml"
    config.write_text(f'cell = "sim{axes}"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
                      f'[simulation]\naxes = "{axes}"\nscenario = "steady"\nspeed = 10.0\nseed = 3\n')
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    daemon.wait_log("serving", timeout=30)
    client = Client(port, f"sim{axes}")
    client.wait_ready(["T1", "T2", "T3", "T4", *(f"interferometer_{a}" for a in axes)])
    return daemon, client


def _wait_positions_near(client: Client, targets: dict[str, float], tolerance_um: float) -> dict[str, float]:
    """Until every axis' interferometer (in status) reads within ``tolerance_um`` of its target."""
    def near() -> dict[str, float] | None:
        sensors = client.status()["sensors"]
        read = {a: sensors[f"interferometer_{a}"]["value"] for a in targets}
        return read if all(v is not None and abs(v - targets[a]) < tolerance_um for a, v in read.items()) else None

    return wait_until(near, 15, f"interferometers near {targets}", interval=0.05)


@pytest.mark.parametrize("axes", ["xy", "xyz"])
def test_a_target_on_the_simulated_stacked_stage_moves_every_axis_to_it(tmp_path: Path, axes: str) -> None:
    daemon, client = _served(tmp_path, axes)
    model = load_any_model(DATA_DIR / f"default_model_{axes}.json")
    try:
        before = {a: client.status()["sensors"][f"interferometer_{a}"]["value"] for a in axes}
        assert all(abs(v) < 1.0 for v in before.values())  # a fresh stage sits at its zero setpoint
        for k, point in enumerate(({"x": 80.0, "y": 400.0, "z": 240.0}, {"x": 400.0, "y": 60.0, "z": 20.0})):
            targets = {a: point[a] for a in axes}
            ok, command = client.query({**{f"{a}_um": v for a, v in targets.items()}, "id": k})
            assert ok, command
            assert command["model"] == model.id and set(command["q_um"]) == set(axes)
            assert command["voltage_v"] == pytest.approx({a: 0.02 * command["q_um"][a] for a in axes})
            # compensated through the stage's cross terms: every beam within half a micrometre of its target
            read = _wait_positions_near(client, targets, 0.5)
            assert all(abs(read[a] - targets[a]) < 0.5 for a in axes)
        status = client.status()
        assert set(status["axes"]) == set(axes)
        assert status["counters"]["commands"] == 2
        # each axis' position telemetry on its own key, so a client tells the axes apart (never sensors/position)
        last = {a: targets[a] for a in axes}
        beams = wait_until(lambda: ({a: client.telemetry[f"position/{a}"] for a in axes}
                                    if all(f"position/{a}" in client.telemetry for a in axes) else None),
                           10, "position telemetry per axis", interval=0.05)
        assert all(abs(beams[a]["value"] - last[a]) < 0.5 and beams[a]["unit"] == "um" for a in axes), beams
        assert "position" not in client.telemetry
    finally:
        client.close()
        assert daemon.stop() == 0


def test_an_xy_target_outside_one_axis_workspace_is_refused_and_moves_nothing(tmp_path: Path) -> None:
    daemon, client = _served(tmp_path, "xy")
    try:
        ok, command = client.query({"x_um": 300.0, "y_um": 200.0, "id": "in"})
        assert ok, command
        _wait_positions_near(client, {"x": 300.0, "y": 200.0}, 0.5)
        ok, error = client.query({"x_um": 100.0, "y_um": 490.0, "id": "out"})  # y's workspace is 0..480
        assert not ok and "y" in error["error"], error
        read = _wait_positions_near(client, {"x": 300.0, "y": 200.0}, 0.5)  # neither axis moved
        assert abs(read["x"] - 300.0) < 0.5
    finally:
        client.close()
        assert daemon.stop() == 0
