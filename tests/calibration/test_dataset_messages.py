"""Messages a user can act on: the file and the user's own row count in ``fit``; a UTF-8 BOM accepted.

Reproduction 9 of issue 10: ``fit`` on a 1-row file said "0 rows are too few..." (no file, the
count of a held-out fold), and a CSV saved with a byte-order mark was refused as "missing column
't_s'" with the BOM invisible. Property-based: any CSV text is a dataset or a DataError naming the
file (and, for a bad cell, its row and column); any small recorded file either fits or says which
file and how many rows it has.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
from helpers.budget import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nanodrift.calibration.dataset import CsvAppender, DataError, read_csv
from nanodrift.cli import main
from nanodrift.model.identify import FitError, fit

BOM = "\ufeff"


def rows_text(n: int, channels: tuple[str, ...] = ("T1",)) -> str:
    lines = [",".join(("t_s", "x_um", "q_um", *channels))]
    for i in range(n):
        temps = [f"{20 + 0.01 * i + 0.1 * k + 0.003 * (i % 3):.4f}" for k in range(len(channels))]
        lines.append(",".join((str(i), str(10.0 * (i % 7)), f"{10.0 * (i % 7) + 0.02 * (i % 5):.4f}", *temps)))
    return "\n".join(lines) + "\n"


@pytest.mark.parametrize(("rows", "needed"), [(1, 4), (2, 4), (3, 4)])
def test_fit_names_the_file_and_the_users_row_count(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                    rows: int, needed: int) -> None:
    path = tmp_path / "short.csv"
    path.write_text(rows_text(rows))
    assert main(["fit", str(path), "--out", str(tmp_path / "m.json")]) == 2
    err = capsys.readouterr().err
    counted = "1 row is" if rows == 1 else f"{rows} rows are"
    assert f"nanodrift fit: error: {path}: {counted} too few to fit 2 candidate terms" in err, err
    assert f"record at least {needed} rows" in err and "0 rows" not in err
    assert not (tmp_path / "m.json").exists()


def test_rows_marked_invalid_are_counted_apart(tmp_path: Path) -> None:
    path = tmp_path / "invalid.csv"
    path.write_text("t_s,x_um,q_um,T1,valid\n0,0,0,20,1\n1,10,10,20.1,0\n2,20,20,20.2,0\n")
    with pytest.raises(FitError, match=re.escape(f"{path}: 1 row (2 more marked valid = 0 left out) is too few")):
        fit(read_csv(path), source=str(path))


def test_too_few_rows_to_choose_the_order_on_held_out_blocks_says_so(tmp_path: Path) -> None:
    path = tmp_path / "five.csv"
    path.write_text(rows_text(5, ("T1", "T2")))
    with pytest.raises(FitError) as info:
        fit(read_csv(path), source=str(path))
    message = str(info.value)
    assert message.startswith(f"{path}: 5 rows are too few to choose the geometric order on held-out blocks")
    assert message.endswith("or give --order N")
    assert fit(read_csv(path), order=1, source=str(path)).orders["x"].order == 1  # the way out it names


def test_a_utf8_bom_is_not_part_of_the_first_column(tmp_path: Path) -> None:
    path = tmp_path / "excel.csv"
    path.write_bytes((BOM + rows_text(30)).encode("utf-8"))
    data = read_csv(path)
    assert len(data) == 30 and data.channel_names == ("T1",) and data.t[0] == 0.0
    assert main(["fit", str(path), "--out", str(tmp_path / "m.json"), "--order", "1"]) == 0
    with CsvAppender(path, ["t_s", "x_um", "q_um", "T1"]) as appender:  # resuming a BOM file works too
        appender.append({"t_s": 30.0, "x_um": 0.0, "q_um": 0.0, "T1": 20.0})
    assert len(read_csv(path)) == 31


@pytest.mark.parametrize("row", [1, 3])
def test_a_field_longer_than_the_csv_modules_limit_is_a_message(tmp_path: Path, row: int) -> None:
    lines = ["t_s,x_um", "0,1", "1,2"]
    lines[row - 1] = ('"' + "a" * 200_000 + '",x_um') if row == 1 else ('2,"' + "9" * 200_000 + '"')
    path = tmp_path / "huge.csv"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(DataError, match=re.escape(f"{path}, row {row}: not a CSV") + ".*field larger than field limit"):
        read_csv(path)


def test_a_body_of_blank_cells_is_no_data(tmp_path: Path) -> None:
    path = tmp_path / "blank.csv"
    path.write_text('t_s,x_um\n""\n,\n')
    with pytest.raises(DataError, match=re.escape(f"{path}: no data rows after the header")):
        read_csv(path)


# --- property-based --------------------------------------------------------------------------

CELLS = st.one_of(
    st.floats(-1e6, 1e6, allow_nan=False).map(repr),
    st.integers(-1000, 1000).map(str),
    st.sampled_from(["", " ", "nan", "inf", "-inf", "1e400", "abc", '"1"', '"a,b"', "0x10", "1,5", "\t2", "١٢",
                     "\x00", '"unterminated', '""']),
)
NAMES = st.sampled_from(["t_s", "x_um", "q_um", "T1", "T2", "air", "stage.top", "x", "1", "t_s", "", "T 1",
                         "cycle", "valid", "q_pred_um", '"T3"'])


@st.composite
def csv_texts(draw: st.DrawFn) -> str:
    header = draw(st.lists(NAMES, min_size=0, max_size=6))
    if draw(st.booleans()):
        header = ["t_s", "x_um", *header]
    width = max(len(header), 1)
    rows = draw(st.lists(st.lists(CELLS, min_size=max(width - 1, 0), max_size=width + 1), max_size=6))
    newline = draw(st.sampled_from(["\n", "\r\n"]))
    text = newline.join([",".join(header)] + [",".join(r) for r in rows]) + draw(st.sampled_from(["", newline]))
    return (BOM if draw(st.booleans()) else "") + text


@settings(max_examples=examples(300), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(text=csv_texts())
def test_any_csv_is_a_dataset_or_a_message_naming_file_row_and_column(tmp_path: Path, text: str) -> None:
    path = tmp_path / "any.csv"
    path.write_bytes(text.encode("utf-8"))
    try:
        data = read_csv(path)
    except DataError as err:
        message = str(err)
        assert message.startswith(str(path)), message
        if "is not a number" in message or "is not a finite number" in message:
            assert re.search(r", row \d+, column \S+: ", message), message
        return
    assert len(data) >= 1 and all(np.isfinite(v).all() for v in data.channels.values())
    assert np.all(np.diff(data.t) > 0)


@settings(max_examples=examples(40), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(rows=st.integers(1, 14), channels=st.integers(0, 3), bom=st.booleans())
def test_fit_on_any_small_file_fits_or_names_the_file_and_its_row_count(tmp_path: Path, rows: int, channels: int,
                                                                        bom: bool) -> None:
    path = tmp_path / "small.csv"
    path.write_bytes(((BOM if bom else "") + rows_text(rows, tuple(f"T{k + 1}" for k in range(channels))))
                     .encode("utf-8"))
    try:
        fit(read_csv(path), source=str(path))
    except FitError as err:
        counted = "1 row is" if rows == 1 else f"{rows} rows are"
        assert str(err).startswith(f"{path}: {counted} too few"), err
