"""Recorded operation (``[health] record_dir``): daily CSVs of every settled target, in the data contract,
surviving crashes (issue 12: "Recording survives kill -9 (no partial row, resumes the day file)")."""

from __future__ import annotations

import datetime as dt
import errno
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from helpers.budget import examples
from helpers.daemon_harness import TEMPS, wait_until, write_test_model
from helpers.log_capture import captured_logging, json_lines
from hypothesis import given, settings
from hypothesis import strategies as st

import nanodrift.calibration.dataset as dataset_module
from nanodrift.calibration.dataset import CsvAppender, read_csv
from nanodrift.calibration.residuals import Settled
from nanodrift.compensation import Compensator, Target
from nanodrift.config import HealthSettings, parse_config
from nanodrift.drivers.base import Reading, SensorConfig
from nanodrift.logs import get_logger
from nanodrift.service.health_unit import HealthUnit
from nanodrift.service.recorder import (
    AGREED_DAY_FILE,
    CLOCK_RELEASE_DAYS,
    DayRecorder,
    Polled,
    PolledChannels,
    Recorder,
    RetentionClock,
    file_name,
)
from nanodrift.service.table import SensorTable

DAY = dt.date(2026, 11, 23)
NOON = dt.datetime(2026, 11, 23, 12, tzinfo=dt.UTC).timestamp()
HEADER = "t_s,x_um,q_um,target_um,residual_um,valid,T1,T2"


def settled(i: int, temps: dict[str, float] | None = None) -> dict[str, Settled]:
    """A one-axis cell's settled target number ``i`` (axis x)."""
    target = 30.0 * (i % 17)
    return {"x": Settled(t=100.0 + i, x_um=target, q_um=target + 0.5, position_um=target + 0.002 * (i % 5 - 2),
                         samples=10, sequence=i,
                         temperatures=temps if temps is not None else {"T1": 21.0 + 0.01 * i, "T2": 22.0 - 0.01 * i})}


def rows_of(path: Path) -> list[str]:
    return path.read_text().splitlines()[1:]


def test_rows_follow_the_data_contract(tmp_path: Path) -> None:
    rec = DayRecorder(tmp_path / "records")
    for i in range(5):
        assert rec.record(settled(i), NOON + 10.0 * i)
    path = tmp_path / "records" / "records-2026-11-23.csv"
    assert rec.path == path
    assert path.read_text().splitlines()[0] == HEADER
    data = read_csv(path)  # the project's reader: fit and discover read these files as they are
    assert data.channel_names == ("T1", "T2")  # target_um and residual_um are reserved, not channels
    assert set(data.extra) == {"target_um", "residual_um", "valid"}
    np.testing.assert_array_equal(data.extra["valid"], 1)
    np.testing.assert_allclose(data.t, NOON + 10.0 * np.arange(5))
    np.testing.assert_allclose(data.x, [settled(i)["x"].position_um for i in range(5)])  # measured, not the target
    np.testing.assert_allclose(data.q, [settled(i)["x"].q_um for i in range(5)])
    np.testing.assert_allclose(data.extra["target_um"], [settled(i)["x"].x_um for i in range(5)])
    np.testing.assert_allclose(data.extra["residual_um"], data.x - data.extra["target_um"])
    np.testing.assert_allclose(data.channels["T1"], [21.0 + 0.01 * i for i in range(5)])


def test_each_row_is_fsynced_before_record_returns(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    synced: list[int] = []
    real_fsync = os.fsync

    def spy(fd: int) -> None:
        real_fsync(fd)
        synced.append(os.path.getsize(f"/proc/self/fd/{fd}"))

    monkeypatch.setattr(dataset_module.os, "fsync", spy)
    rec = DayRecorder(tmp_path)
    rec.record(settled(0), NOON)  # creates the file: its header was fsynced in the temp file
    synced.clear()
    for i in range(1, 4):
        assert rec.record(settled(i), NOON + i)
        size = (tmp_path / file_name(DAY)).stat().st_size
        assert synced[-1] == size  # the fsync covered the whole row just written
    assert len(synced) == 3


def test_a_new_day_starts_a_new_file_with_its_header_and_no_temp_file_left(tmp_path: Path) -> None:
    rec = DayRecorder(tmp_path)
    midnight = dt.datetime(2026, 11, 24, tzinfo=dt.UTC).timestamp()
    assert rec.record(settled(0), midnight - 1.0)
    assert rec.record(settled(1), midnight + 1.0)  # the row's own (unix) time decides the day
    assert rec.record(settled(2), midnight + 2.0)
    first, second = tmp_path / "records-2026-11-23.csv", tmp_path / "records-2026-11-24.csv"
    assert len(read_csv(first)) == 1 and len(read_csv(second)) == 2
    assert second.read_text().splitlines()[0] == HEADER
    left = sorted(p.name for p in tmp_path.iterdir() if p.name != AGREED_DAY_FILE)
    assert left == [first.name, second.name]  # no .tmp left behind


def test_retention_deletes_day_files_older_than_keep_days_at_rotation(tmp_path: Path) -> None:
    def day_file(days_before: int, part: int = 1) -> Path:
        path = tmp_path / file_name(DAY - dt.timedelta(days=days_before), part)
        path.write_text(HEADER + "\n")
        return path

    old, old_part, kept, edge = day_file(120), day_file(91, 2), day_file(30), day_file(90)
    day_file(1)  # recorded yesterday: the clock agrees with the files (else see RetentionClock)
    other = tmp_path / "notes-2020-01-01.csv"
    other.write_text("not ours\n")
    assert DayRecorder(tmp_path, keep_days=90, clock=lambda: NOON).record(settled(0), NOON)
    assert not old.exists() and not old_part.exists()
    assert kept.exists() and edge.exists() and other.exists()

    keep_all = tmp_path / "all"
    keep_all.mkdir()
    ancient = keep_all / file_name(DAY - dt.timedelta(days=3000))
    ancient.write_text(HEADER + "\n")
    assert DayRecorder(keep_all, keep_days=0, clock=lambda: NOON).record(settled(0), NOON)
    assert ancient.exists()


def test_a_new_channel_set_continues_the_day_in_a_suffixed_file(tmp_path: Path) -> None:
    rec = DayRecorder(tmp_path)
    assert rec.record(settled(0), NOON)
    assert rec.record(settled(1, {"T2": 22.0, "T1": 21.0}), NOON + 1)  # same channels, other order: same file
    assert rec.record(settled(2, {"T1": 21.0, "T2": 22.0, "T3": 23.0}), NOON + 2)  # a reload with another model
    first, second = tmp_path / file_name(DAY), tmp_path / file_name(DAY, 2)
    assert second.name == "records-2026-11-23.2.csv"
    assert read_csv(first).channel_names == ("T1", "T2") and len(read_csv(first)) == 2
    assert read_csv(second).channel_names == ("T1", "T2", "T3") and len(read_csv(second)) == 1

    again = DayRecorder(tmp_path)  # a restart with the first model's channels: the last file does not fit them
    assert again.record(settled(3), NOON + 3)
    assert again.path == tmp_path / file_name(DAY, 3)


def test_a_clock_stepping_back_starts_a_new_file_so_time_increases_in_each(tmp_path: Path) -> None:
    rec = DayRecorder(tmp_path)
    assert rec.record(settled(0), NOON + 60)
    assert rec.record(settled(1), NOON + 30)  # NTP stepped the clock back
    assert len(read_csv(tmp_path / file_name(DAY))) == 1
    assert len(read_csv(tmp_path / file_name(DAY, 2))) == 1


def test_a_restart_resumes_the_day_file_and_drops_a_row_cut_short(tmp_path: Path) -> None:
    rec = DayRecorder(tmp_path)
    for i in range(3):
        assert rec.record(settled(i), NOON + i)
    rec.close()
    path = tmp_path / file_name(DAY)
    with open(path, "a") as handle:
        handle.write("1795435203.0,240.00")  # a crash in the middle of a row
    again = DayRecorder(tmp_path)
    assert again.record(settled(3), NOON + 3)
    assert again.path == path
    data = read_csv(path)
    np.testing.assert_allclose(data.t, NOON + np.arange(4))
    assert sorted(p.name for p in tmp_path.iterdir() if p.name != AGREED_DAY_FILE) == [path.name]


def test_write_errors_are_logged_once_never_raised_and_recording_resumes(tmp_path: Path) -> None:
    blocked = tmp_path / "records"
    blocked.write_text("a file where the folder should be")  # every write fails, as on a full or read-only disk
    with captured_logging() as stream:
        rec = DayRecorder(blocked, log=get_logger("nanodrift.daemon"))
        assert [rec.record(settled(i), NOON + i) for i in range(4)] == [False] * 4
        blocked.unlink()
        assert rec.record(settled(4), NOON + 4)
        events = json_lines(stream)
    failed = [e for e in events if e["event"] == "record_failed"]
    assert len(failed) == 1 and failed[0]["level"] == "error" and str(blocked) in failed[0]["error"]
    resumed = [e for e in events if e["event"] == "record_resumed"]
    assert len(resumed) == 1 and resumed[0]["rows_lost"] == 4
    assert len(read_csv(blocked / file_name(DAY))) == 1


def test_the_listener_never_raises_into_the_caller_and_writes_off_its_thread(tmp_path: Path) -> None:
    blocked = tmp_path / "blocked"
    blocked.write_text("")
    failing = Recorder(lambda: HealthSettings(record_dir=str(blocked)))
    for i in range(3):
        failing.on_settled(settled(i), NOON + i)  # no exception reaches the health unit
    failing.close()
    assert failing.writer is not None and failing.writer.rows_lost == 3

    rec = Recorder(lambda: HealthSettings(record_dir=str(tmp_path / "ok")))
    for i in range(20):
        rec.on_settled(settled(i), NOON + i)
    path = tmp_path / "ok" / file_name(DAY)
    wait_until(lambda: path.exists() and len(rows_of(path)) == 20, 10, "20 rows written by the recorder's thread")
    rec.close()
    assert not rec.running
    assert len(read_csv(path)) == 20


def test_a_reload_sets_moves_and_clears_record_dir_in_order_with_the_rows(tmp_path: Path) -> None:
    config = {"health": HealthSettings()}  # record_dir "" = off
    rec = Recorder(lambda: config["health"])
    rec.on_settled(settled(0), NOON)
    config["health"] = HealthSettings(record_dir=str(tmp_path / "a"))
    for i in range(1, 4):
        rec.on_settled(settled(i), NOON + i)
    config["health"] = HealthSettings(record_dir=str(tmp_path / "b"), record_keep_days=0)
    rec.on_settled(settled(4), NOON + 4)
    config["health"] = HealthSettings()
    rec.on_settled(settled(5), NOON + 5)
    rec.close()
    assert not rec.running
    np.testing.assert_array_equal(read_csv(tmp_path / "a" / file_name(DAY)).t, NOON + np.arange(1, 4))
    np.testing.assert_array_equal(read_csv(tmp_path / "b" / file_name(DAY)).t, [NOON + 4])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a", "b"]


@settings(max_examples=examples(40), deadline=None)
@given(st.lists(st.floats(min_value=-1e6, max_value=1e6, allow_nan=False), min_size=1, max_size=8))
def test_any_finite_values_round_trip_through_the_reader(tmp_path_factory: pytest.TempPathFactory,
                                                         values: list[float]) -> None:
    folder = tmp_path_factory.mktemp("rec")
    rec = DayRecorder(folder)
    for i, v in enumerate(values):
        s = Settled(t=i, x_um=v, q_um=-v, position_um=v / 3.0, samples=1, temperatures={"T1": v, "air": 20.0})
        assert rec.record({"x": s}, NOON + i)
    rec.close()
    data = read_csv(folder / file_name(DAY))
    np.testing.assert_array_equal(data.channels["T1"], values)
    np.testing.assert_array_equal(data.extra["target_um"], values)


def test_non_finite_values_are_refused_and_the_file_stays_readable(tmp_path: Path) -> None:
    rec = DayRecorder(tmp_path)
    assert rec.record(settled(0), NOON)
    assert not rec.record(settled(1, {"T1": float("nan"), "T2": 22.0}), NOON + 1)
    assert rec.record(settled(2), NOON + 2)
    assert len(read_csv(tmp_path / file_name(DAY))) == 2


# --- retention on the daemon's clock (issue 16): a label stepped ahead deletes nothing more -------------------


DAY_S = 86400.0


def test_a_label_stepped_months_ahead_deletes_no_file_the_daemons_clock_keeps(tmp_path: Path) -> None:
    """The wall clock stepped +120 days (the row's label), the daemon's clock did not: retention counts
    from the daemon's day, so the last 31 days stay; a file old by the daemon's clock still goes."""
    recent = [tmp_path / file_name(DAY - dt.timedelta(days=k)) for k in range(31)]
    for path in recent:
        path.write_text(HEADER + "\n")
    edge = tmp_path / file_name(DAY - dt.timedelta(days=90))  # kept today, not tomorrow
    old = tmp_path / file_name(DAY - dt.timedelta(days=91))
    for path in (edge, old):
        path.write_text(HEADER + "\n")
    clock = {"now": NOON}
    with captured_logging() as stream:
        rec = DayRecorder(tmp_path, keep_days=90, log=get_logger("nanodrift.daemon"), clock=lambda: clock["now"])
        for i in range(3):
            assert rec.record(settled(i), NOON + 120 * DAY_S + i)
        events = json_lines(stream)
    assert rec.path == tmp_path / file_name(DAY + dt.timedelta(days=120))
    assert all(p.exists() for p in recent) and edge.exists() and not old.exists()
    assert [e["path"] for e in events if e["event"] == "record_expired"] == [str(old)]

    clock["now"] += DAY_S  # a day later by the daemon's clock: its day moves, retention runs again
    assert rec.record(settled(3), NOON + 121 * DAY_S)
    assert not edge.exists() and all(p.exists() for p in recent)  # DAY - 90 is now 91 days old

    ahead = tmp_path / "ahead"  # the other way: the daemon's clock started ahead, the label is right
    ahead.mkdir()
    kept = ahead / file_name(DAY - dt.timedelta(days=30))
    kept.write_text(HEADER + "\n")
    assert DayRecorder(ahead, keep_days=90, clock=lambda: NOON + 120 * DAY_S).record(settled(0), NOON)
    assert kept.exists()



@pytest.mark.parametrize("how", ["synchronised", "ran two days on"])
def test_a_clock_that_started_months_ahead_of_the_files_deletes_only_once_believed(tmp_path: Path, how: str) -> None:
    """Issue 26.7: the daemon's clock and the labels both 120 days ahead of the newest file (a wrong RTC at
    boot): nothing recorded in the last 90 days of the files' own timeline goes, the hold is said once;
    once the clock is known synchronised (systemd's flag), or has run on for CLOCK_RELEASE_DAYS, retention
    counts from it again."""
    recent = [tmp_path / file_name(DAY - dt.timedelta(days=k)) for k in range(4)]
    stale = tmp_path / file_name(DAY - dt.timedelta(days=100))  # old by the files' own timeline: goes at once
    for path in (*recent, stale):
        path.write_text(HEADER + "\n")
    now = {"s": NOON + 120 * DAY_S}
    synced = {"flag": False}
    with captured_logging() as stream:
        log = get_logger("nanodrift.daemon")
        rec = DayRecorder(tmp_path, keep_days=90, log=log, clock=lambda: now["s"],
                          retention=RetentionClock(log, synchronized=lambda: synced["flag"]))
        for i in range(3):
            assert rec.record(settled(i), now["s"] + i)
        assert all(p.exists() for p in recent) and not stale.exists()
        held = [e for e in json_lines(stream) if e["event"] == "record_retention_held"]
        assert len(held) == 1 and held[0]["newest_file_day"] == DAY.isoformat(), held
        if how == "synchronised":
            synced["flag"] = True
            now["s"] += 60.0
        else:
            now["s"] += (CLOCK_RELEASE_DAYS - 1) * DAY_S
            assert rec.record(settled(3), now["s"])
            assert all(p.exists() for p in recent)  # one day on: still doubted
            now["s"] += DAY_S
        assert rec.record(settled(4), now["s"])
        events = json_lines(stream)
    assert not any(p.exists() for p in recent)  # 120 days old by a clock the daemon now believes
    assert [e["event"] for e in events].count("record_retention_resumed") == 1


def test_a_clock_ahead_that_ntp_steps_back_never_deletes_and_a_short_absence_is_believed(tmp_path: Path) -> None:
    """The clock 120 days ahead, then NTP steps it back (the labels come back; the daemon's own clock does
    not, retention takes the earlier day): nothing of the files' last 90 days is deleted. A daemon off for
    a weekend (the clock within CLOCK_AHEAD_MARGIN_DAYS of the newest file) is believed at once."""
    recent = [tmp_path / file_name(DAY - dt.timedelta(days=k)) for k in range(4)]
    for path in recent:
        path.write_text(HEADER + "\n")
    rec = DayRecorder(tmp_path, keep_days=3, clock=lambda: NOON + 120 * DAY_S,
                      retention=RetentionClock(synchronized=lambda: False))
    assert rec.record(settled(0), NOON + 120 * DAY_S)
    assert rec.record(settled(1), NOON + 3600.0)  # NTP corrected the wall clock: the label is today again
    assert all(p.exists() for p in recent)
    weekend = tmp_path / "weekend"
    weekend.mkdir()
    friday, older = weekend / file_name(DAY - dt.timedelta(days=2)), weekend / file_name(DAY - dt.timedelta(days=6))
    for path in (friday, older):
        path.write_text(HEADER + "\n")
    monday = DayRecorder(weekend, keep_days=3, clock=lambda: NOON, retention=RetentionClock(synchronized=lambda: False))
    assert monday.record(settled(0), NOON)
    assert friday.exists() and not older.exists()

# --- a full disk (issue 16): no partial row, one line per outage ---------------------------------------------


class FullDisk:
    """``os.write`` until :attr:`full`; then each row's first write lands half the row and the next
    (the rest of it) fails with ENOSPC: what a disk filling up mid-row does."""

    def __init__(self) -> None:
        self.full = False
        self._half_written = False
        self.failures = 0

    def __call__(self, fd: int, data: bytes) -> int:
        if not self.full:
            return os.write(fd, data)
        if self._half_written:
            self._half_written = False
            self.failures += 1
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        self._half_written = True
        return os.write(fd, data[: max(1, len(data) // 2)])


def test_a_full_disk_leaves_no_partial_row_and_logs_the_outage_once(tmp_path: Path) -> None:
    disk = FullDisk()
    path = tmp_path / file_name(DAY)
    with captured_logging() as stream:
        rec = DayRecorder(tmp_path, log=get_logger("nanodrift.daemon"), clock=lambda: NOON, write=disk)
        for i in range(3):
            assert rec.record(settled(i), NOON + i)
        disk.full = True
        for i in range(3, 43):
            assert not rec.record(settled(i), NOON + i)
            data = read_csv(path)  # the loader fit uses: the file never ends inside a row, all through the outage
            assert len(data) == 3 and path.read_bytes().endswith(b"\n")
        assert disk.failures == 40  # every row did try, and half of each reached the file before it was cut
        disk.full = False
        assert rec.record(settled(43), NOON + 43)
        assert rec.record(settled(44), NOON + 44)
        events = json_lines(stream)
    failed = [e for e in events if e["event"] == "record_failed"]
    resumed = [e for e in events if e["event"] == "record_resumed"]
    assert len(failed) == 1 and "No space left on device" in failed[0]["error"]
    assert len(resumed) == 1 and resumed[0]["rows_lost"] == 40 and resumed[0]["path"] == str(path)
    assert [e["how"] for e in events if e["event"] == "record_file"] == ["created"]  # not one per target
    assert rec.rows_lost == 40 and rec.rows_written == 5
    np.testing.assert_array_equal(read_csv(path).t, NOON + np.array([0, 1, 2, 43, 44]))


def test_a_row_whose_fsync_fails_is_cut_back_off(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A full disk may first say so at the fsync (delayed allocation): that row is not kept either."""
    path = tmp_path / "run.csv"
    appender = CsvAppender(path, ["t_s", "x_um", "T1"])
    appender.append({"t_s": 1.0, "x_um": 2.0, "T1": 21.0})
    real_fsync = os.fsync

    def full(fd: int) -> None:
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(dataset_module.os, "fsync", full)
    with pytest.raises(OSError):
        appender.append({"t_s": 2.0, "x_um": 3.0, "T1": 21.5})
    monkeypatch.setattr(dataset_module.os, "fsync", real_fsync)
    assert appender.intact and path.read_text().splitlines() == ["t_s,x_um,T1", "1.0,2.0,21.0"]
    appender.append({"t_s": 3.0, "x_um": 4.0, "T1": 22.0})
    appender.close()
    np.testing.assert_array_equal(read_csv(path).t, [1.0, 3.0])


# --- every polled channel (issue 19) ---------------------------------------------------------------------------


def test_the_window_of_every_polled_channel_and_when_a_row_is_not_valid() -> None:
    polled = PolledChannels({"T1": 2.0, "T4": 2.0, "T9": 4.0}, keep_s=30.0)
    for t, t1, t4 in ((9.0, 21.0, 30.0), (10.5, 21.2, 23.0), (11.5, 21.4, 23.2), (12.5, 21.6, 99.0)):
        polled.observe("T1", t, t1, True)
        polled.observe("T4", t, t4, True)
    polled.observe("T9", 8.5, 19.0, True)  # polled slower than the window: its latest, fresh at the end
    polled.observe("other", 10.5, 1.0, True)  # not configured: never in a row
    window = polled.window(10.0, 12.0)  # the mean of each channel's ok readings inside the window
    assert window.valid and window.values_c == pytest.approx({"T1": 21.3, "T4": 23.1, "T9": 19.0})

    polled.observe("T9", 12.6, 0.0, False)
    assert not polled.window(12.0, 13.0).valid  # faulted inside the window
    stale = polled.window(13.0, 14.0)  # T1, T4 read last at 12.5: fresh (2 s); T9's latest is its fault
    assert not stale.valid and stale.values_c["T9"] == 19.0  # its last ok value: never a NaN
    assert polled.window(13.0, 14.6).values_c["T1"] == 21.6 and not polled.window(13.0, 14.6).valid

    never = PolledChannels({"T1": 2.0}, keep_s=30.0)
    never.observe("T1", 10.5, 0.0, False)
    assert never.window(10.0, 12.0) == Polled({"T1": 0.0}, False)


def test_a_row_holds_every_polled_channel_and_an_invalid_one_is_kept_with_valid_0(tmp_path: Path) -> None:
    rec = DayRecorder(tmp_path, clock=lambda: NOON)
    every = {"T1": 21.0, "T2": 22.0, "T4": 23.0}
    assert rec.record(settled(0), NOON, Polled(every, True))  # the model's T1, T2 and a polled T4
    assert rec.record(settled(1), NOON + 1, Polled({**every, "T4": 23.5}, False))
    assert rec.record(settled(2), NOON + 2, Polled({"T1": 21.0, "T2": 22.0}, True))  # a reload stopped polling T4
    first = read_csv(tmp_path / file_name(DAY))
    assert set(first.channel_names) == {"T1", "T2", "T4"} and len(first) == 2
    np.testing.assert_array_equal(first.extra["valid"], [1, 0])
    np.testing.assert_array_equal(first.channels["T4"], [23.0, 23.5])
    assert len(first.valid_rows()) == 1  # what fit uses
    assert read_csv(tmp_path / file_name(DAY, 2)).channel_names == ("T1", "T2")


def test_the_health_unit_hands_every_polled_channel_over_the_window_to_the_recorder(tmp_path: Path) -> None:
    sensors = [SensorConfig(name=n, kind="x", max_age_s=5.0) for n in ("T1", "T2", "T4")]
    sensors.append(SensorConfig(name="interferometer", kind="x", role="position", max_age_s=1.0))
    config = parse_config({"health": {"settle_s": 3.0, "window_s": 2.0}, "sensors": []}, source="unit.toml")
    config = config.model_copy(update={"sensors": sensors})
    model = write_test_model(tmp_path / "m.json")  # its channels: T1, T2
    table = SensorTable(config.sensors)
    health = HealthUnit(config, model, get_logger("nanodrift.daemon"))
    compensator = Compensator(model, config.axis_actuators(), table, monitor=health)
    handed: list[tuple[dict[str, Settled], float, Polled]] = []
    health.settled_listeners.append(lambda s, unix_s, polled: handed.append((s, unix_s, polled)))

    def hold(t: float, t4: list[tuple[float, float, bool]]) -> None:
        for name, value in TEMPS.items():
            table.update(name, Reading(value, t=t))
        compensator.observe(t, TEMPS)
        compensator.compensate(Target(None, {"x": 100.0}), t, 1.7e9 + t)
        for k in range(1, 13):
            now = t + 0.5 * k
            for name, value in TEMPS.items():
                health.on_channel(name, now, value, True)
            for t_read, value, ok in t4:
                if now - 0.5 < t_read <= now:
                    health.on_channel("T4", t_read, value, ok)
            health.on_position(now, now, 100.1, True, channel="interferometer")
        health.flush()

    hold(0.0, [(3.2, 23.0, True), (4.2, 23.4, True), (6.0, 50.0, True)])  # window [3, 5]: 23.0 and 23.4
    hold(20.0, [(23.5, 0.0, False)])  # T4 faulted inside the window
    assert [s["x"].t for s, _, _ in handed] == [5.0, 25.0]
    first, second = handed[0][2], handed[1][2]
    assert first.valid and first.values_c == pytest.approx({**TEMPS, "T4": 23.2})
    assert not second.valid and second.values_c["T4"] == 50.0 and second.values_c["T1"] == TEMPS["T1"]

    fewer = config.model_copy(update={"sensors": [c for c in sensors if c.name != "T4"]})
    health.reconfigure(fewer, model)  # a reload that stops polling T4: its rows go on without it
    hold(40.0, [(43.5, 24.0, True)])
    assert handed[-1][2] == Polled(dict(TEMPS), True)

WRITER = """
import sys
from nanodrift.calibration.residuals import Settled
from nanodrift.config import HealthSettings
from nanodrift.service.recorder import DayRecorder

rec = DayRecorder(sys.argv[1])
t0 = float(sys.argv[2])
i = 0
while True:
    rec.record({"x": Settled(t=i, x_um=240.0, q_um=240.5, position_um=240.001, samples=10,
                             temperatures={"T1": 21.0 + 1e-4 * i, "T2": 22.0})}, t0 + 0.25 * i)
    i += 1
"""


def test_kill_9_mid_recording_leaves_a_readable_file_that_the_next_start_resumes(tmp_path: Path) -> None:
    folder = tmp_path / "records"
    path = folder / file_name(DAY)
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(folder), repr(NOON)])
    try:
        wait_until(lambda: path.exists() and path.stat().st_size > 40_000, 60, "the writer to record rows")
    finally:
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait(10)
    assert writer.returncode == -signal.SIGKILL
    data = read_csv(path)  # the project's reader: a cut-off row would be refused here, naming its row
    n = len(data)
    assert n > 300
    np.testing.assert_allclose(data.t, NOON + 0.25 * np.arange(n))  # no row lost before the last complete one

    rec = DayRecorder(folder)  # the next start, the same day
    assert rec.record(settled(0), NOON + 0.25 * n + 10.0)
    assert rec.path == path
    assert sorted(p.name for p in folder.iterdir() if p.name != AGREED_DAY_FILE) == [path.name]
    after = read_csv(path)
    assert len(after) == n + 1 and after.t[-1] == NOON + 0.25 * n + 10.0


def test_kill_9_cutting_a_row_leaves_it_out_on_resume(tmp_path: Path) -> None:
    """The same crash at the worst moment: the file ends inside a row (forced, as SIGKILL rarely lands there)."""
    folder = tmp_path / "records"
    path = folder / file_name(DAY)
    writer = subprocess.Popen([sys.executable, "-c", WRITER, str(folder), repr(NOON)])
    try:
        wait_until(lambda: path.exists() and path.stat().st_size > 4_000, 60, "the writer to record rows")
    finally:
        os.kill(writer.pid, signal.SIGKILL)
        writer.wait(10)
    complete = len(read_csv(path))
    size = path.stat().st_size
    os.truncate(path, size - 7)  # the last row loses its end
    rec = DayRecorder(folder)
    assert rec.record(settled(0), NOON + 1e4)
    data = read_csv(path)
    assert len(data) == complete  # the cut row is gone, the new one is in
    assert data.t[-1] == NOON + 1e4
