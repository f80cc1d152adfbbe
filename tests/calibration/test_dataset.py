"""The CSV contract: what is accepted, and every malformed file refused with file, row and column."""

import os
from pathlib import Path

import numpy as np
import pytest

from nanodrift.calibration.dataset import CsvAppender, DataError, Dataset, read_csv, write_csv


def write(tmp_path: Path, text: str, name: str = "d.csv") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_reads_columns_and_any_channel_names(tmp_path):
    path = write(tmp_path, "t_s,x_um,q_um,air,stage.top,T-3\n0,0,0.1,20.0,20.5,19.9\n1,30,30.2,20.1,20.6,19.8\n")
    ds = read_csv(path)
    assert ds.channel_names == ("air", "stage.top", "T-3")
    np.testing.assert_array_equal(ds.x, [0, 30])
    np.testing.assert_array_equal(ds.q, [0.1, 30.2])
    np.testing.assert_array_equal(ds.channels["stage.top"], [20.5, 20.6])
    assert ds.source == str(path)


def test_request_file_without_q_and_reserved_columns(tmp_path):
    ds = read_csv(write(tmp_path, "t_s,x_um,T1,cycle,valid\n0,0,20,0,1\n5,80,20,1,0\n"))
    assert ds.q is None
    assert set(ds.extra) == {"cycle", "valid"} and ds.channel_names == ("T1",)
    assert len(ds.valid_rows()) == 1


@pytest.mark.parametrize(
    ("text", "fragments"),
    [
        ("", ["empty file"]),
        ("t_s,x_um,T1\n", ["no data rows"]),
        ("t_s,T1\n0,20\n", ["row 1", "missing column 'x_um'"]),
        ("x_um,T1\n0,20\n", ["row 1", "missing column 't_s'"]),
        ("t_s,x_um,T1\n0,0,20\n1,abc,20\n", ["row 3", "column x_um", "'abc' is not a number"]),
        ("t_s,x_um,T1\n0,0,20\n1,0,\n", ["row 3", "column T1", "'' is not a number"]),
        ("t_s,x_um,T1\n0,0,20\n1,0,nan\n", ["row 3", "column T1", "not a finite number"]),
        ("t_s,x_um,T1\n0,0,20\n1,0,inf\n", ["row 3", "column T1", "not a finite number"]),
        ("t_s,x_um,T1\n0,0,20\n1,0\n", ["row 3", "2 cells, expected 3"]),
        ("t_s,x_um,T1\n0,0,20\n2,0,20\n2,0,20\n", ["row 4", "column t_s", "must increase"]),
        ("t_s,x_um,T1\n5,0,20\n2,0,20\n", ["row 3", "column t_s"]),
        ("t_s,x_um,T1,T1\n0,0,20,20\n", ["row 1", "duplicate column 'T1'"]),
        ("t_s,x_um,x\n0,0,20\n", ["row 1", "'x' is not usable"]),
        ("t_s,x_um,T 1\n0,0,20\n", ["row 1", "'T 1' is not usable"]),
        ("t_s,x_um,T1,cycle\n0,0,20,0.5\n", ["row 2", "column cycle", "whole number"]),
        # numpy's parser would take "#" for a comment: the row dropped, or the cell cut to its number
        ("t_s,x_um,T1\n#,0,20\n2,0,20\n", ["row 2", "column t_s", "'#' is not a number"]),
        ("t_s,x_um,T1\n0,0,20\n1,0,20#c\n", ["row 3", "column T1", "'20#c' is not a number"]),
    ],
)
def test_malformed_files_are_refused_with_row_and_column(tmp_path, text, fragments):
    path = write(tmp_path, text)
    with pytest.raises(DataError) as info:
        read_csv(path)
    message = str(info.value)
    assert str(path) in message
    for fragment in fragments:
        assert fragment in message, message


def test_missing_and_binary_files(tmp_path):
    with pytest.raises(DataError, match="no such file"):
        read_csv(tmp_path / "absent.csv")
    path = tmp_path / "bin.csv"
    path.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(DataError, match="not a UTF-8 text file"):
        read_csv(path)


def test_write_read_round_trip_is_exact(tmp_path):
    rng = np.random.default_rng(3)
    ds = Dataset(
        t=np.arange(50.0) * 0.1 + 1e9,
        x=rng.uniform(0, 480, 50),
        q=rng.uniform(0, 480, 50),
        channels={"T1": 20 + rng.normal(0, 1e-3, 50), "air": 19 + rng.normal(0, 1, 50)},
        extra={"cycle": np.repeat(np.arange(5.0), 10)},
    )
    path = tmp_path / "out" / "round.csv"
    write_csv(ds, path, {"q_pred_um": ds.q * 2})
    back = read_csv(path)
    for a, b in [(ds.t, back.t), (ds.x, back.x), (ds.q, back.q), (ds.channels["air"], back.channels["air"])]:
        np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(back.extra["q_pred_um"], ds.q * 2)
    np.testing.assert_array_equal(back.cycles(), np.repeat(np.arange(5), 10))


def test_failed_write_leaves_previous_file_intact(tmp_path):
    path = tmp_path / "keep.csv"
    path.write_text("t_s,x_um\n0,0\n")
    bad = Dataset(t=np.arange(3.0), x=np.zeros(3), channels={"T1": np.zeros(2)})  # ragged: zip fails
    with pytest.raises(ValueError):
        write_csv(bad, path)
    assert path.read_text() == "t_s,x_um\n0,0\n"
    assert [p.name for p in tmp_path.iterdir()] == ["keep.csv"]  # no temp file left behind


def test_cycles_inferred_from_sweeps_when_no_cycle_column():
    x = np.tile(np.arange(0.0, 481.0, 30.0), 3)
    ds = Dataset(t=np.arange(x.size, dtype=float), x=x)
    np.testing.assert_array_equal(ds.cycles(), np.repeat([0, 1, 2], 17))


def test_appender_keeps_completed_rows_and_resumes(tmp_path):
    path = tmp_path / "run.csv"
    with CsvAppender(path, ["t_s", "x_um", "q_um", "cycle", "T1"]) as out:
        out.append({"t_s": 0.0, "x_um": 0.0, "q_um": 0.1, "cycle": 0, "T1": 20.0})
    with CsvAppender(path, ["t_s", "x_um", "q_um", "cycle", "T1"]) as out:  # resume
        out.append({"t_s": 29.0, "x_um": 30.0, "q_um": 30.1, "cycle": 0, "T1": 20.01})
    ds = read_csv(path)
    np.testing.assert_array_equal(ds.x, [0.0, 30.0])
    with pytest.raises(DataError, match="cannot append"):
        CsvAppender(path, ["t_s", "x_um", "T2"])


def test_appender_drops_a_row_cut_by_a_crash(tmp_path):
    path = tmp_path / "run.csv"
    path.write_text("t_s,x_um,T1\n0.0,0.0,20.0\n29.0,30.0,2")  # the crash cut the second row
    with CsvAppender(path, ["t_s", "x_um", "T1"]) as out:
        assert out.dropped_partial_row
        out.append({"t_s": 29.0, "x_um": 30.0, "T1": 20.5})
    np.testing.assert_array_equal(read_csv(path).channels["T1"], [20.0, 20.5])


def test_written_files_get_normal_permissions_not_mkstemps_0600(tmp_path):
    old = os.umask(0o022)
    try:
        path = tmp_path / "new.csv"
        write_csv(Dataset(t=np.arange(2.0), x=np.zeros(2)), path)
        assert path.stat().st_mode & 0o777 == 0o644
        path.chmod(0o640)  # an operator's choice survives a rewrite
        write_csv(Dataset(t=np.arange(3.0), x=np.zeros(3)), path)
        assert path.stat().st_mode & 0o777 == 0o640
    finally:
        os.umask(old)


def test_chunked_writing_loses_no_row_at_chunk_boundaries(tmp_path):
    from nanodrift.calibration.dataset import _csv_chunks

    ds = Dataset(t=np.arange(50.0), x=np.arange(50.0) * 1.5, channels={"T1": 20 + np.arange(50.0) / 7})
    path = tmp_path / "chunked.csv"
    path.write_text("".join(_csv_chunks(ds.columns(), rows_per_chunk=7)))
    back = read_csv(path)
    np.testing.assert_array_equal(back.t, ds.t)
    np.testing.assert_array_equal(back.channels["T1"], ds.channels["T1"])
