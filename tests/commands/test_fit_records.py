"""``nanodrift fit cal.csv records/*.csv`` and ``discover`` on several files (issue 12, recorded operation):
a calibration extended with recorded operation widens the model's training ranges; a bad file is named."""

from __future__ import annotations

import datetime as dt
import json
from pathlib import Path

import numpy as np
import pytest

from nanodrift.atomic import file_sha256
from nanodrift.calibration.dataset import read_csv, write_csv
from nanodrift.calibration.residuals import Settled
from nanodrift.cli import main
from nanodrift.model.model import load_model
from nanodrift.service.recorder import DayRecorder

MORNING = dt.datetime(2026, 11, 23, 8, tzinfo=dt.UTC).timestamp()


def simulate(tmp_path: Path, name: str, *args: str) -> Path:
    out = tmp_path / name
    assert main(["simulate", *args, "--out", str(out)]) == 0
    return out


def record_operation(run_csv: Path, folder: Path) -> list[Path]:
    """The rows of a simulated run, recorded as the daemon records settled targets (the same recorder)."""
    run = read_csv(run_csv)
    rec = DayRecorder(folder)
    for i in range(len(run)):
        temps = {c: float(v[i]) for c, v in run.channels.items()}
        settled = Settled(t=float(run.t[i]), x_um=float(run.q[i]), q_um=float(run.q[i]), position_um=float(run.x[i]),
                          samples=10, temperatures=temps)
        assert rec.record({"x": settled}, MORNING + float(run.t[i]))
    rec.close()
    return sorted(folder.glob("*.csv"))


@pytest.fixture(scope="module")
def cell_files(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path]]:
    tmp = tmp_path_factory.mktemp("records")
    cal = simulate(tmp, "cal.csv", "--scenario", "train", "--cycles", "8", "--seed", "1")
    test5 = simulate(tmp, "test5.csv", "--scenario", "test5", "--seed", "2")  # the room above the training range
    return cal, record_operation(test5, tmp / "records")


def fit_json(capsys: pytest.CaptureFixture[str], *args: str) -> dict:
    capsys.readouterr()
    assert main(["fit", *args, "--order", "3", "--json"]) == 0
    return json.loads(capsys.readouterr().out)


def test_fit_on_calibration_plus_records_widens_the_training_ranges(tmp_path, capsys, cell_files) -> None:
    cal, records = cell_files
    assert [p.name for p in records] == ["records-2026-11-23.csv"]
    # T1 kept in both: the selection may pick different channels from the two data sets, the ranges compared
    # are those of a channel both models hold
    alone = fit_json(capsys, str(cal), "--keep", "T1", "--out", str(tmp_path / "cal.json"))
    both = fit_json(capsys, str(cal), *map(str, records), "--keep", "T1", "--out", str(tmp_path / "both.json"))

    common = set(alone["training"]["channels"]) & set(both["training"]["channels"])
    assert common, (alone["training"], both["training"])
    for channel in common:
        low, high = alone["training"]["channels"][channel]
        low2, high2 = both["training"]["channels"][channel]
        assert low2 <= low and high2 > high + 0.5, channel  # test 5's room is about 1 °C warmer
    assert both["rows"] == alone["rows"] + len(read_csv(records[0]))

    model = load_model(tmp_path / "both.json")
    files = model.provenance["data_files"]
    assert [f["path"] for f in files] == [str(cal), str(records[0])]
    assert [f["sha256"] for f in files] == [file_sha256(cal), file_sha256(records[0])]
    assert both["data_files"] == files
    assert model.training.t_span_s == pytest.approx(
        sum(float(np.ptp(read_csv(p).t)) for p in (cal, records[0])))  # the runs' own spans, not the gap

    capsys.readouterr()
    assert main(["fit", str(cal), str(records[0]), "--out", str(tmp_path / "human.json")]) == 0
    assert "from 2 runs" in capsys.readouterr().out


def test_a_bad_file_among_several_is_named_and_nothing_is_written(tmp_path, capsys, cell_files) -> None:
    cal, records = cell_files
    out = tmp_path / "m.json"
    bad = tmp_path / "records-2026-11-24.csv"
    bad.write_text("t_s,x_um,q_um,target_um,residual_um,T1,T2,T3,T4\n"
                   "1.0,0,0,0,0,22,22,22,22\n2.0,30,30,30,0,22,oops,22,22\n")
    assert main(["fit", str(cal), str(records[0]), str(bad), "--out", str(out)]) == 2
    assert f"{bad}, row 3, column T2" in capsys.readouterr().err
    assert not out.exists()

    no_q = tmp_path / "targets.csv"
    no_q.write_text("t_s,x_um,T1,T2,T3,T4\n0,0,22,22,22,22\n1,30,22,22,22,22\n")
    assert main(["fit", str(cal), str(no_q), "--out", str(out)]) == 2
    assert f"{no_q}: no q_um column" in capsys.readouterr().err

    fewer = tmp_path / "records-three.csv"
    data = read_csv(records[0])
    data.channels.pop("T4")
    write_csv(data, fewer)
    assert main(["fit", str(cal), str(fewer), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert f"{fewer}: lacks channel(s) T4" in err and "--exclude T4" in err
    assert not out.exists()
    assert main(["fit", str(cal), str(fewer), "--exclude", "T4", "--out", str(out)]) == 0  # as the message says
    assert "T4" not in load_model(out).channels


def test_discover_on_several_runs_names_the_effect_and_records_every_file(tmp_path, capsys) -> None:
    runs = [simulate(tmp_path, f"run{seed}.csv", "--scenario", "train", "--effects", "creep", "--cycles", "12",
                     "--seed", str(seed)) for seed in (1, 2)]
    model, extended = tmp_path / "m.json", tmp_path / "m2.json"
    assert main(["fit", str(runs[0]), "--out", str(model)]) == 0
    capsys.readouterr()
    assert main(["discover", *map(str, runs), "--model", str(model), "--out", str(extended), "--json"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert [s["effect"] for s in doc["steps"]] == ["creep"], doc["final"]["summary"]
    assert doc["baseline"]["rows"] == sum(len(read_csv(p)) for p in runs)
    files = load_model(extended).provenance["data_files"]
    assert [f["sha256"] for f in files] == [file_sha256(p) for p in runs]

    lacking = tmp_path / "lacking.csv"
    data = read_csv(runs[1])
    needed = load_model(model).channels[0]
    data.channels.pop(needed)
    write_csv(data, lacking)
    args = ["discover", str(runs[0]), str(lacking), "--model", str(model), "--out", str(tmp_path / "m3.json")]
    assert main(args) == 2
    assert f"{lacking} lacks channel(s) {needed}" in capsys.readouterr().err
    assert not (tmp_path / "m3.json").exists()
