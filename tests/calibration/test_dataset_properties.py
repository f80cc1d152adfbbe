"""Property-based: a malformed data file is refused with a DataError naming the file, and the row
and column of the defect; nothing else ever escapes ``read_csv`` (issue 10: no traceback ever).

Files start from a valid table (contract columns and 1-3 channels) and get one defect at a place the
test knows, so the message must name exactly that place; then random damage anywhere, where only
the kind of exception and a plausible place are checked.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from helpers.budget import examples
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from nanodrift.calibration.dataset import DataError, Dataset, read_csv

SETTINGS = settings(max_examples=examples(150), deadline=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
ROW = re.compile(r", row (\d+)")


@st.composite
def tables(draw: st.DrawFn) -> tuple[list[str], list[list[str]]]:
    """A valid header and rows (as the cells' text): increasing t_s, the contract columns, channels."""
    channels = draw(st.lists(st.sampled_from(["T1", "T2", "T3", "air", "stage"]), min_size=1, max_size=3, unique=True))
    header = ["t_s", "x_um", *draw(st.sampled_from([["q_um"], []])), *channels]
    n = draw(st.integers(1, 8))
    steps = draw(st.lists(st.floats(0.001, 100.0), min_size=n, max_size=n))
    rows, t = [], 0.0
    for step in steps:
        t += step
        values = [t] + [draw(st.floats(-1e3, 1e3, allow_nan=False)) for _ in header[1:]]
        rows.append([repr(v) for v in values])
    return header, rows


def text_of(header: list[str], rows: list[list[str]], newline: str = "\n") -> str:
    return newline.join([",".join(header), *(",".join(r) for r in rows)]) + newline


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return tmp_path_factory.mktemp("csv_props")


def refused(path: Path) -> str:
    """read_csv's DataError message; the test fails on a Dataset or on any other exception."""
    with pytest.raises(DataError) as caught:
        read_csv(path)
    message = str(caught.value)
    assert message.startswith(str(path)), message
    return message


@SETTINGS
@given(tables())
def test_valid_tables_are_read(folder: Path, table: tuple[list[str], list[list[str]]]) -> None:
    header, rows = table
    path = folder / "valid.csv"
    path.write_text(text_of(header, rows))
    data = read_csv(path)
    assert isinstance(data, Dataset) and len(data) == len(rows)
    assert list(data.channel_names) == [h for h in header if h not in ("t_s", "x_um", "q_um")]


BAD_CELLS = st.one_of(
    st.sampled_from(["", " ", "abc", "1,2".replace(",", ";"), "nan", "NaN", "inf", "-inf", "1e999", "0x10", "--1",
                     "1.2.3", "one", "™", "1 2", "TRUE"]),
    st.text(alphabet=st.characters(codec="utf-8", exclude_characters=',"\r\n\x00', exclude_categories=["Cs"]),
            min_size=1, max_size=8).filter(lambda c: not _is_finite_number(c)),
)


def _is_finite_number(cell: str) -> bool:
    try:
        value = float(cell)
    except ValueError:
        return False
    return value - value == 0  # finite


@SETTINGS
@given(tables(), BAD_CELLS, st.data())
def test_one_bad_cell_is_named_by_file_row_and_column(folder: Path, table, cell: str, data: st.DataObject) -> None:
    header, rows = table
    r = data.draw(st.integers(0, len(rows) - 1), label="row")
    c = data.draw(st.integers(0, len(header) - 1), label="column")
    rows[r][c] = cell
    path = folder / "bad_cell.csv"
    path.write_text(text_of(header, rows))
    message = refused(path)
    assert f"{path}, row {r + 2}, column {header[c]}:" in message, message


@SETTINGS
@given(tables(), st.data())
def test_a_row_with_a_cell_too_many_or_too_few_is_named_by_row(folder: Path, table, data: st.DataObject) -> None:
    header, rows = table
    r = data.draw(st.integers(0, len(rows) - 1), label="row")
    if data.draw(st.booleans(), label="drop") and len(rows[r]) > 1:
        rows[r] = rows[r][:-1]
    else:
        rows[r] = [*rows[r], "1.0"]
    path = folder / "bad_length.csv"
    path.write_text(text_of(header, rows))
    message = refused(path)
    assert f"{path}, row {r + 2}:" in message and "cells" in message, message


@SETTINGS
@given(tables(), st.data())
def test_time_that_does_not_increase_is_named_by_row_and_column(folder: Path, table, data: st.DataObject) -> None:
    header, rows = table
    if len(rows) < 2:
        rows.append([repr(float(rows[0][0]) + 1.0), *rows[0][1:]])
    r = data.draw(st.integers(1, len(rows) - 1), label="row")
    rows[r][0] = rows[r - 1][0] if data.draw(st.booleans(), label="equal") else repr(float(rows[r - 1][0]) - 0.5)
    for later in range(r + 1, len(rows)):  # only this row goes back in time
        rows[later][0] = repr(float(rows[later - 1][0]) + 1.0)
    path = folder / "bad_time.csv"
    path.write_text(text_of(header, rows))
    message = refused(path)
    assert f"{path}, row {r + 1 + 1}, column t_s:" in message, message


@SETTINGS
@given(tables(), st.sampled_from(["drop t_s", "drop x_um", "duplicate", "bad name", "empty name", "forbidden name"]))
def test_a_bad_header_is_named_by_row_1(folder: Path, table, defect: str) -> None:
    header, rows = table
    if defect.startswith("drop"):
        i = header.index(defect.split()[1])
        header, rows = header[:i] + header[i + 1:], [row[:i] + row[i + 1:] for row in rows]
    elif defect == "duplicate":
        header[-1] = header[1]
    else:
        header[-1] = {"bad name": "1st", "empty name": "", "forbidden name": "dir"}[defect]
    path = folder / "bad_header.csv"
    path.write_text(text_of(header, rows))
    message = refused(path)
    assert f"{path}, row 1" in message, message


GARBAGE = st.lists(st.sampled_from([*"0123456789.,-+eE \t\"'\r\nxT_s", "\x00", "\ufeff", "é", "nan", "inf"]),
                   max_size=40).map("".join)


@SETTINGS
@given(tables(), GARBAGE, st.integers(0, 10_000), st.sampled_from(["\n", "\r\n", "\r"]))
@example(table=(["t_s", "x_um", "T1"], [["1.0", "2.0", "3.0"], ["2.0", "2.0", "3.0"]]), garbage="\r", where=18,
         newline="\n")  # a lone CR inside the second row's cells
def test_random_damage_never_escapes_as_anything_but_a_data_error(folder: Path, table, garbage: str, where: int,
                                                                  newline: str) -> None:
    header, rows = table
    text = text_of(header, rows, newline)
    at = where % (len(text) + 1)
    path = folder / "damaged.csv"
    path.write_text(text[:at] + garbage + text[at:], encoding="utf-8", newline="")
    try:
        data = read_csv(path)
    except DataError as error:
        message = str(error)
        assert message.startswith(str(path)), message
        found = ROW.search(message)
        with open(path, encoding="utf-8", newline="") as handle:
            lines = handle.read().replace("\r\n", "\n").replace("\r", "\n").count("\n")
        assert found is None or 1 <= int(found.group(1)) <= lines + 1, (message, lines)
    else:
        assert isinstance(data, Dataset)


@SETTINGS
@given(st.binary(max_size=64))
@example(raw=b"\r\x00")  # what the csv module says about a lone CR or a NUL must become a DataError too
@example(raw=b"1,2\x00,3\n")
@example(raw=b"1,2,3\r4,5,6\n")
@example(raw=b"\xff\xfe1,2,3\n")
def test_bytes_that_are_not_text_name_the_file(folder: Path, raw: bytes) -> None:
    path = folder / "binary.csv"
    path.write_bytes(b"t_s,x_um,T1\n" + raw)
    try:
        read_csv(path)
    except DataError as error:
        assert str(error).startswith(str(path)), str(error)
