"""The durable record of what each output was last written (issue 26.5): what a restart believes, and nothing else.

A state file is input from the disk (an earlier run, ``nanodrift confirm-output``, a full disk, an editor): any
content is either a record of finite voltages for this very device, or a :class:`RecordError` naming the file.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nanodrift.output_record import RECORD_FORMAT, OutputRecords, RecordError, state_directory


def test_a_record_round_trips_and_names_only_its_own_device(tmp_path: Path) -> None:
    records = OutputRecords(tmp_path, "cell0")
    records.save("x", "module A register 10", 7.98, 8.0)
    assert records.read("x", "module A register 10")[0] == (7.98, 8.0)
    assert records.read("x", "module B register 10")[0] == ()  # another device's record says nothing of this one
    assert records.read("y", "module A register 10")[0] == ()  # nothing kept for y
    doc = json.loads((tmp_path / "output-cell0-x.json").read_text())
    assert doc["format"] == RECORD_FORMAT and doc["cell"] == "cell0" and doc["axis"] == "x"


def test_a_record_says_whether_an_operator_confirmed_it_or_the_daemon_wrote_it(tmp_path: Path) -> None:
    records = OutputRecords(tmp_path, "cell0")
    records.save("x", "dac", 8.0, 8.0, by="operator")  # nanodrift confirm-output
    assert records.read("x", "dac") == ((8.0, 8.0), "operator")
    records.save("x", "dac", 8.0, 8.4)  # the daemon's next write: its own record from now on
    assert records.read("x", "dac") == ((8.0, 8.4), "daemon")


def test_a_procedures_writes_keep_the_previous_value_as_the_confirmed_one(tmp_path: Path) -> None:
    records = OutputRecords(tmp_path, "c")
    records.note_written("x", "dac", 1.0)
    assert records.read("x", "dac")[0] == (1.0,)  # nothing confirmed before the first write
    records.note_written("x", "dac", 1.5)
    assert records.read("x", "dac")[0] == (1.0, 1.5)  # a kill mid-write leaves the device at one of the two


def test_a_number_that_is_no_voltage_is_refused_naming_the_file(tmp_path: Path) -> None:
    path = tmp_path / "output-c-x.json"
    path.write_text(json.dumps({"format": RECORD_FORMAT, "device": "dac", "confirmed_v": None, "written_v": True}))
    with pytest.raises(RecordError, match=r"output-c-x\.json: confirmed_v and written_v must be numbers or null"):
        OutputRecords(tmp_path, "c").read("x", "dac")[0]


def test_no_state_directory_keeps_nothing_and_systemd_s_wins(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    OutputRecords(None, "c").save("x", "dac", 1.0, 1.0)  # nowhere to keep it: nothing happens
    assert OutputRecords(None, "c").read("x", "dac")[0] == ()
    monkeypatch.delenv("STATE_DIRECTORY", raising=False)
    assert state_directory(tmp_path / "configured") == tmp_path / "configured"
    monkeypatch.setenv("STATE_DIRECTORY", f"{tmp_path / 'unit'}:{tmp_path / 'other'}")
    assert state_directory(tmp_path / "configured") == tmp_path / "unit"


@settings(suppress_health_check=[HealthCheck.function_scoped_fixture], max_examples=60)
@given(content=st.one_of(
    st.binary(max_size=200),
    st.recursive(st.none() | st.booleans() | st.floats() | st.text(max_size=8),
                 lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=12), inner, max_size=4),
                 max_leaves=8).map(lambda doc: json.dumps(doc).encode()),
    st.fixed_dictionaries({"format": st.just(RECORD_FORMAT), "device": st.just("dac"),
                           "confirmed_v": st.one_of(st.none(), st.floats(), st.text(max_size=3)),
                           "written_v": st.one_of(st.none(), st.floats(), st.booleans())}
                          ).map(lambda doc: json.dumps(doc).encode())))
def test_any_file_content_is_a_record_of_finite_voltages_or_an_error_naming_the_file(
        tmp_path: Path, content: bytes) -> None:
    path = tmp_path / "output-c-x.json"
    path.write_bytes(content)
    try:
        voltages = OutputRecords(tmp_path, "c").read("x", "dac")[0]
    except RecordError as error:
        assert str(path) in str(error)
        return
    assert all(isinstance(v, float) and math.isfinite(v) for v in voltages)
