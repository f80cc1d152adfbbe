"""The three output paths of a procedure on (emulated) hardware, and the checks before it starts:
a serving daemon's ``alive`` token refuses the run; with ``kind = "zenoh"`` an output node must be
subscribed (unless ``--no-output-check``) and then applies the steps; ``kind = "serial_line"`` and
``kind = "pi_gcs"`` drive a PI controller over GCS through calibration and validation."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh
from helpers.daemon_harness import free_port, wait_until
from helpers.emulated_cell import EmulatedCell, write_config

from nanodrift.calibration.dataset import read_csv
from nanodrift.cli import main
from nanodrift.config import ZenohSettings
from nanodrift.procedure import preflight

ONE_CYCLE = "cycles = 1\nrise_s = 0.05\nhold_s = 0.12\naverage_s = 0.06\n"
TWO_CYCLES = ONE_CYCLE.replace("cycles = 1", "cycles = 2")


def peer(listen: int) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{listen}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def calibrate(config: Path, tmp_path: Path, *extra: str) -> int:
    return main(["calibrate", "--config", str(config), "--out", str(tmp_path / "m.json"), "--data",
                 str(tmp_path / "cal.csv"), *extra])


def test_a_serving_daemon_refuses_the_procedure_before_anything_moves(tmp_path: Path,
                                                                        capsys: pytest.CaptureFixture) -> None:
    zenoh_port = free_port()
    daemon = peer(zenoh_port)  # where the cell's daemon listens, with its token
    token = daemon.liveliness().declare_token("nanodrift/hil/alive")
    try:
        with EmulatedCell(tmp_path) as emulated:
            config = write_config(tmp_path / "hil.toml", emulated.config_text(zenoh_port=zenoh_port,
                                                                               procedure=ONE_CYCLE))
            assert calibrate(config, tmp_path) == 2
            err = capsys.readouterr().err
            assert ("a daemon is commanding cell 'hil' (its liveliness token nanodrift/hil/alive is present): stop it "
                    "first (systemctl stop nanodrift)") in err
            assert emulated.device.reads == [] and emulated.device.writes == []  # nothing was opened
            token.undeclare()
            assert calibrate(config, tmp_path) == 0  # the daemon stopped: the run goes ahead
            model = tmp_path / "m.json"
            assert model.exists()
            capsys.readouterr()

            token = daemon.liveliness().declare_token("nanodrift/hil/alive")  # a daemon serves the cell again
            reads, writes, lines = len(emulated.device.reads), len(emulated.device.writes), len(emulated.voltages)
            assert main(["validate", "--config", str(config), "--model", str(model)]) == 2  # a real model: it loads
            err = capsys.readouterr().err
            assert ("a daemon is commanding cell 'hil' (its liveliness token nanodrift/hil/alive is present): stop it "
                    "first (systemctl stop nanodrift)") in err
            assert (len(emulated.device.reads), len(emulated.device.writes), len(emulated.voltages)) == (
                reads, writes, lines), "the refused validation touched the cell"
            token.undeclare()
    finally:
        daemon.close()


def test_kind_zenoh_needs_an_output_node_and_the_node_applies_the_steps(
        tmp_path: Path, capsys: pytest.CaptureFixture, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(preflight, "OUTPUT_WAIT_S", 0.5)
    with EmulatedCell(tmp_path) as emulated:
        alone = write_config(tmp_path / "alone.toml", emulated.config_text(actuator="zenoh", procedure=ONE_CYCLE))
        assert calibrate(alone, tmp_path) == 2
        err = capsys.readouterr().err
        assert "no output node is subscribed to nanodrift/hil/command after 0.5 s" in err
        assert "--no-output-check" in err and emulated.voltages == []
        assert not (tmp_path / "cal.csv").exists()  # refused before the first step: no file to trip over

        # told to go ahead without a node: the steps go out, nothing moves, the follow check stops it
        assert calibrate(alone, tmp_path, "--no-output-check") == 2
        assert "the stage did not follow: commanded +30 µm" in capsys.readouterr().err
        (tmp_path / "cal.csv").unlink()

        emulated.start_output_node()  # the lab's node: applies voltage_v of every command
        with_node = write_config(tmp_path / "node.toml", emulated.config_text(actuator="zenoh", procedure=ONE_CYCLE))
        assert calibrate(with_node, tmp_path) == 0
        err = capsys.readouterr().err
        assert "stage commands published on nanodrift/hil/command" in err
        assert len(read_csv(tmp_path / "cal.csv")) == 17
        # 480 um x 0.02 V/um, put on the amplifier by the node (its samples arrive asynchronously)
        wait_until(lambda: emulated.voltages and abs(emulated.voltages[-1] - 9.6) < 1e-9, 5.0, "the node applied 9.6 V")


def assert_compensated_through_the_controller(test: dict) -> None:
    """The model's commands reached the stage: uncompensated, this validation errs ~400 nm (``without_comp_nm``,
    from the truth); compensated, ≤ 65 nm per point idle and 121 nm once beside a loaded suite. The emulated physics
    runs at 1000x wall time, so a poll a loaded machine makes 50 ms late is 50 simulated seconds late: the bound
    is half the uncompensated error, and the model must remove most of it."""
    assert test["points"] and all(abs(p["accuracy_nm"]) < 200.0 for p in test["points"]), test["points"]
    assert test["without_is_computed"] and test["improvement_ratio"] > 3.0, test


def test_kind_serial_line_calibrates_and_validates_through_a_gcs_controller(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with EmulatedCell(tmp_path) as emulated:
        config = write_config(tmp_path / "pi.toml", emulated.config_text(actuator="serial_line",
                                                                          procedure=TWO_CYCLES))
        assert calibrate(config, tmp_path) == 0
        assert "stage driven by the controller on " in capsys.readouterr().err
        lines = emulated.controller.lines
        # where the stage is is asked first (the first ramp starts there), then each command is checked
        assert lines[:4] == ["SVA? 1", "SVA 1 0.0000", "SVA? 1", "ERR?"] and "SVA 1 9.6000" in lines
        assert len(read_csv(tmp_path / "cal.csv")) == 34
        assert main(["validate", "--config", str(config), "--model", str(tmp_path / "m.json"), "--cycles", "1",
                     "--json"]) == 0
        result = json.loads(capsys.readouterr().out)
        assert result["backend"].startswith("hardware; stage driven by the controller")
        (test,) = result["tests"]
        assert_compensated_through_the_controller(test)


def test_kind_pi_gcs_switches_the_servo_off_then_calibrates_and_validates_through_the_controller(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with EmulatedCell(tmp_path) as emulated:
        config = write_config(tmp_path / "pi.toml", emulated.config_text(actuator="pi_gcs", procedure=TWO_CYCLES))
        assert calibrate(config, tmp_path) == 0
        printed = capsys.readouterr()  # the plugin's log lines on stderr, never in a command's output
        [switched] = [line for line in printed.err.splitlines() if "pi_gcs_servo_switched" in line]
        assert "servo=off" in switched and "pi_gcs_servo_switched" not in printed.out
        lines = emulated.pi_gcs.received()
        first_sva = next(i for i, line in enumerate(lines) if line.startswith("SVA "))
        assert lines.index("SVO 1 0") < first_sva  # the servo, on at power-up, is off before the stage moves
        assert "SVA 1 9.600000" in lines and all(-1.0 <= v <= 11.0 for _, v in emulated.pi_gcs.applied_sva)
        assert len(read_csv(tmp_path / "cal.csv")) == 34
        assert main(["validate", "--config", str(config), "--model", str(tmp_path / "m.json"), "--cycles", "1",
                     "--json"]) == 0
        result = json.loads(capsys.readouterr().out)
        assert result["backend"].startswith("hardware; stage driven by the PI controller")
        (test,) = result["tests"]
        assert_compensated_through_the_controller(test)


def test_the_probe_listens_nowhere_and_connects_where_the_daemon_listens() -> None:
    settings = ZenohSettings(listen=["tcp/0.0.0.0:7447", "tcp/[::]:7448", "udp/10.0.0.5:7449", "tcp/0.0.0.0:0"],
                             connect=["tcp/10.0.0.2:7447"], multicast_scouting=False)
    conf = preflight.probe_config(settings)
    assert json.loads(conf.get_json("listen/endpoints")) == []
    assert json.loads(conf.get_json("connect/endpoints")) == [
        "tcp/10.0.0.2:7447", "tcp/127.0.0.1:7447", "tcp/[::1]:7448", "udp/10.0.0.5:7449"]
    router = preflight.probe_config(ZenohSettings(mode="router"))
    assert json.loads(router.get_json("mode")) == "peer"  # a probe never serves as anyone's router
    assert json.loads(router.get_json("connect/endpoints")) == ["tcp/[::1]:7447"]  # the router default tcp/[::]:7447
