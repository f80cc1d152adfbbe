"""``nanodrift run`` on the simulated cell: the built-in default config with the shipped model, and a
config with no ``[[sensors]]``. Commands reach the simulated stage: the interferometer sees them."""

from __future__ import annotations

import statistics
from pathlib import Path

from helpers.daemon_harness import Client, Daemon, free_port, wait_until

from nanodrift.config import DEFAULT_MODEL_PATH
from nanodrift.model.model import load_model


def test_run_without_config_serves_the_simulated_cell_with_the_shipped_model(tmp_path: Path) -> None:
    port = free_port()
    daemon = Daemon(["-l", f"tcp/127.0.0.1:{port}", "--no-multicast-scouting"], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "cell0")
        try:
            client.wait_alive()
            client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
            ok, command = client.query({"x_um": 240.0, "id": "sim"})
            assert ok, command
            assert command["model"] == load_model(DEFAULT_MODEL_PATH).id
            assert abs(command["q_um"] - 240.0) < 2.0  # a few hundred nm of geometry + thermal correction
            assert command["voltage_v"] == 0.02 * command["q_um"]
            # the default room stays inside the shipped model's training ranges: nothing flagged
            answers = [client.query({"x_um": x, "id": i})[1] for i, x in enumerate((0.0, 160.0, 480.0))]
            assert [a["extrapolating"] for a in [command, *answers]] == [[], [], [], []]
            assert daemon.log_events("starting")[0]["config"] == "<built-in default config>"
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0


def test_commands_move_the_simulated_stage_to_the_target(tmp_path: Path) -> None:
    port = free_port()
    config = tmp_path / "sim.toml"
    config.write_text(
        f'cell = "simcell"\n[zenoh]\nlisten = ["tcp/127.0.0.1:{port}"]\nmulticast_scouting = false\n'
        f'[model]\npath = "{DEFAULT_MODEL_PATH}"\n[simulation]\nscenario = "steady"\nspeed = 10.0\nseed = 3\n'
    )
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "simcell")
        try:
            client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])
            for x in (80.0, 400.0):
                ok, command = client.query({"x_um": x, "id": f"to-{x:g}"})
                assert ok, command

                def near_target(x: float = x) -> bool:
                    value = client.telemetry.get("position", {}).get("value")
                    return value is not None and abs(value - x) < 0.5

                wait_until(near_target, 10, f"the interferometer near {x} um")
                samples: list[float] = []

                def collect(samples: list[float] = samples) -> bool:
                    samples.append(client.telemetry["position"]["value"])
                    return len(samples) >= 20

                wait_until(collect, 10, "20 position samples", interval=0.02)
                assert abs(statistics.fmean(samples) - x) < 0.25  # compensated: well under a micrometre
            status = client.status()
            assert status["sensors"]["interferometer"]["unit"] == "um"
            assert status["counters"]["commands"] == 2
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0


def test_the_shipped_sim_toml_serves_its_first_targets_inside_the_training_range(tmp_path: Path) -> None:
    """Issue 13: config/sim.toml with the default model flagged T1 as extrapolating on the first targets."""
    port = free_port()
    shipped = (Path(__file__).resolve().parents[2] / "config" / "sim.toml").read_text()
    config = tmp_path / "nanodrift.toml"
    config.write_text(shipped.replace("tcp/127.0.0.1:7447", f"tcp/127.0.0.1:{port}"))
    daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
    try:
        daemon.wait_log("serving", timeout=30)
        client = Client(port, "cell0")
        try:
            client.wait_ready(["T1", "T2", "T3", "T4", "interferometer"])  # the paper's four thermocouples
            answers = [client.query({"x_um": x, "id": i}) for i, x in enumerate((0.0, 240.0, 480.0))]
            assert all(ok for ok, _ in answers), answers
            assert [a["extrapolating"] for _, a in answers] == [[], [], []]
            assert answers[0][1]["model"] == load_model(DEFAULT_MODEL_PATH).id
        finally:
            client.close()
    finally:
        assert daemon.stop() == 0
