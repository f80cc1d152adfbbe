"""The calibration procedure on the simulated cell: end to end, faults mid-run, interrupt and resume."""

from __future__ import annotations

import asyncio
import hashlib
import importlib.metadata
import json

import numpy as np
import pytest
from helpers.sim_helpers import Capture

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration.dataset import read_csv
from nanodrift.calibration.plans import StepResult, calibration_plan
from nanodrift.cli import main
from nanodrift.drivers.simulated.plugin import shared_cell
from nanodrift.model.model import load_model
from nanodrift.procedure.recording import record_calibration


def test_calibrate_command_end_to_end(tmp_path, capsys):
    out, data = tmp_path / "m.json", tmp_path / "cal.csv"
    assert main(["calibrate", "--out", str(out), "--data", str(data), "--cycles", "8", "--seed", "3"]) == 0
    ds = read_csv(data)
    assert len(ds) == 8 * 17 and list(ds.channels) == ["T1", "T2", "T3", "T4"]
    assert np.array_equal(ds.extra["cycle"], np.repeat(np.arange(8), 17)) and ds.extra["valid"].all()
    assert np.allclose(ds.q, np.tile(np.arange(0, 481, 30.0), 8))
    assert np.all(np.diff(ds.t) == pytest.approx(29.0))  # 4 s ramp + 25 s hold per step
    model = load_model(out)
    assert model.fit["residual_rms_nm"] < 35.0  # the noise: 20 nm white + 25 nm slow interferometer wander
    assert "x" in model.term_names() and set(model.channels) <= {"T1", "T2", "T3", "T4"} and model.channels
    assert model.provenance["software"] == f"nanodrift {importlib.metadata.version('nanodrift')}"
    # the data file is stamped as fit and discover stamp theirs: its path, SHA-256 and rows
    digest = hashlib.sha256(data.read_bytes()).hexdigest()
    assert model.provenance["data_file"] == str(data) and model.provenance["data_sha256"] == digest
    assert model.provenance["data_files"] == [{"path": str(data), "sha256": digest, "rows": 8 * 17}]
    out = capsys.readouterr().out  # the result is on stdout (issue 19); progress stays on stderr
    assert "fit residual" in out and "model ->" in out and "·x³" in out and "+ -" not in out


def test_progress_is_a_line_per_cycle_when_not_a_tty(tmp_path):
    stream = Capture()
    backend = simulated_drivers("train", seed=1)
    asyncio.run(record_calibration(backend, tmp_path / "d.csv", cycles=3, progress_stream=stream))
    lines = stream.getvalue().splitlines()
    # the simulated stage says where it is (read back): no "unknown start" note before the plan
    assert not any("before the first move is unknown" in line for line in lines)
    # at the start, the plan's 51 x (4 s + 25 s) of cell time; then a line per cycle at the measured pace
    assert lines[0] == "calibration: 0/51 steps, 0:24:39 left (planned), 0 invalid"
    assert len(lines) == 4 and lines[-1].startswith("calibration: 51/51 steps, 0:00:00 left")
    assert "17/51" in lines[1] and "0:16:26 left" not in lines[1]  # wall-clock time, not the cell's 34 x 29 s


def _run(backend, path, cycles=1, **kw) -> list[StepResult]:
    results: list[StepResult] = []
    asyncio.run(record_calibration(backend, path, cycles=cycles, on_step=results.append,
                                   progress_stream=Capture(), **kw))
    return results


def test_a_short_fault_is_retried_a_long_one_marks_the_step_invalid(tmp_path):
    backend = simulated_drivers("train", seed=2)
    cell = shared_cell(backend.context)
    cell.inject_fault("T2", 112.0, 113.0, "fault")  # inside step 3's averaging window (111-116 s)
    cell.inject_fault("interferometer", 200.0, 260.0, "fault")  # longer than a window and its retries
    results = _run(backend, tmp_path / "d.csv")
    assert results[3].valid and results[3].retries == 1
    assert all(r.valid for r in results[:3])
    invalid = [r for r in results if not r.valid]
    assert invalid and all("interferometer" in r.problem for r in invalid)
    assert all(r.retries == 2 for r in invalid)
    ds = read_csv(tmp_path / "d.csv")
    assert len(ds) == 17 and int((ds.extra["valid"] == 0).sum()) == len(invalid)
    # the retried step is clean: its T2 mean was taken from samples after the fault
    assert abs(results[3].temperatures["T2"] - results[2].temperatures["T2"]) < 0.02


def test_a_stale_sensor_is_never_averaged(tmp_path):
    backend = simulated_drivers("train", seed=2)
    shared_cell(backend.context).inject_fault("T3", 50.0, 150.0, "stale")  # T3 max_age_s = 5 s
    results = _run(backend, tmp_path / "d.csv")
    stale = [r for r in results if "stale" in r.problem]
    assert stale and all(not r.valid for r in stale)
    assert all(r.t_s - 5.0 >= 150.0 or r.t_s <= 55.0 or not r.valid for r in results)


def test_interrupt_keeps_every_step_and_resume_continues(tmp_path, capsys):
    data, out = tmp_path / "cal.csv", tmp_path / "m.json"

    def stop(result: StepResult) -> None:
        if result.step.index == 9:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        asyncio.run(record_calibration(simulated_drivers("train", seed=5), data, cycles=2, on_step=stop,
                                       progress_stream=Capture()))
    first = read_csv(data)
    assert len(first) == 10
    # without --resume the recorded file is never overwritten
    assert main(["calibrate", "--out", str(out), "--data", str(data), "--cycles", "2", "--seed", "5"]) == 2
    assert "--resume" in capsys.readouterr().err and len(read_csv(data)) == 10
    assert main(["calibrate", "--out", str(out), "--data", str(data), "--cycles", "2", "--seed", "5",
                 "--resume"]) == 0
    ds = read_csv(data)
    assert len(ds) == 34 and np.all(np.diff(ds.t) > 0)
    assert np.array_equal(ds.t[:10], first.t) and np.array_equal(ds.x[:10], first.x)
    assert np.allclose(ds.q, [s.target_um for s in calibration_plan(2)])
    assert json.loads(out.read_text())["format"] == "nanodrift-model/1"


def test_cli_interrupt_prints_how_to_resume(tmp_path, capsys, monkeypatch):
    from nanodrift.procedure import steps as procedure

    data, out = tmp_path / "cal.csv", tmp_path / "m.json"
    original = procedure.measure_step
    calls = {"n": 0}

    async def flaky(*args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 4:
            raise KeyboardInterrupt
        return await original(*args, **kwargs)

    monkeypatch.setattr(procedure, "measure_step", flaky)
    assert main(["calibrate", "--out", str(out), "--data", str(data), "--cycles", "1"]) == 130
    err = capsys.readouterr().err
    assert "stopped after 3 of 17 steps" in err and f"--data {data} --resume" in err
    assert len(read_csv(data)) == 3 and not out.exists()


def test_a_link_failure_mid_window_is_retried(tmp_path):
    backend = simulated_drivers("train", seed=4)
    shared_cell(backend.context).inject_fault("T4", 140.0, 141.0, "device_error")  # step 4's window: 140-145 s
    results = _run(backend, tmp_path / "d.csv")
    assert results[4].valid and results[4].retries == 1
    assert all(r.valid for r in results)


def test_ctrl_c_on_a_real_process_keeps_the_steps_and_says_how_to_resume(tmp_path):
    import os
    import signal
    import subprocess
    import sys

    data, out = tmp_path / "cal.csv", tmp_path / "m.json"
    proc = subprocess.Popen(
        [sys.executable, "-m", "nanodrift.cli", "calibrate", "--out", str(out), "--data", str(data), "--cycles", "200"],
        stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert proc.stderr is not None
        for line in proc.stderr:  # wait for the first completed cycle
            if line.startswith("calibration: 17/"):
                break
        proc.send_signal(signal.SIGINT)
        rest = proc.stderr.read()
        assert proc.wait(timeout=30) == 130
    finally:
        proc.kill()
    assert "Resume with: nanodrift calibrate" in rest and "--resume" in rest
    ds = read_csv(data)  # every line complete: no half-written row
    assert 17 <= len(ds) < 200 * 17 and ds.extra["valid"].all()
    assert not out.exists()


def test_calibrate_with_an_operator_config_uses_its_sensor_names(tmp_path):
    config = tmp_path / "cell.toml"
    config.write_text(
        'cell = "bench"\n'
        '[simulation]\nscenario = "steady"\nseed = 3\neffects = { thermal_lag = { tau_s = 1800.0 } }\n'
        '[[sensors]]\nname = "stage"\nkind = "simulated"\nchannel = "T1"\n'
        '[[sensors]]\nname = "room"\nkind = "simulated"\nchannel = "T4"\ninterval_s = 1.0\n'
        '[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "simulated"\ninterval_s = 0.2\n'
    )
    out, data = tmp_path / "m.json", tmp_path / "d.csv"
    assert main(["calibrate", "--config", str(config), "--out", str(out), "--data", str(data), "--cycles", "2"]) == 0
    ds = read_csv(data)
    assert list(ds.channels) == ["stage", "room"] and len(ds) == 34
    assert set(load_model(out).channels) <= {"stage", "room"}
    bad = tmp_path / "bad.toml"
    bad.write_text('[simulation]\nscenario = "nope"\n')
    assert main(["calibrate", "--config", str(bad), "--out", str(out), "--cycles", "1"]) == 2


def test_ctrl_c_ends_a_procedure_even_when_the_cancellation_is_lost() -> None:
    """Python 3.11 can lose the cancellation asyncio.run turns SIGINT into (``asyncio.wait_for``): a calibration
    then returned as if complete and its few steps were fitted (a loaded CI run). ``run_procedure`` remembers
    the SIGINT: the procedure ends as KeyboardInterrupt whether or not the cancellation reached it."""
    import asyncio
    import os
    import signal

    from nanodrift.commands._cell import run_procedure

    async def swallows() -> str:
        os.kill(os.getpid(), signal.SIGINT)
        try:
            await asyncio.sleep(5)
        except asyncio.CancelledError:
            return "returned as if complete"  # what a lost cancellation looks like to the caller
        return "slept"

    async def cancelled() -> str:
        os.kill(os.getpid(), signal.SIGINT)
        await asyncio.sleep(5)
        return "slept"

    async def quiet() -> int:
        await asyncio.sleep(0)
        return 7

    for procedure in (swallows, cancelled):
        with pytest.raises(KeyboardInterrupt):
            run_procedure(procedure())
    assert run_procedure(quiet()) == 7
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # nothing of ours is left behind
