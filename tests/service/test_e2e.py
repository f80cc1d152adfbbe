"""The daemon as a separate process, driven by a real Zenoh client session over 127.0.0.1.

Sensors come from the harness's ``file`` plugin (registered through a real entry point), so each
test sets the temperatures exactly and can make a channel stale, faulted, or its device fail.
"""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import pytest
import zenoh
from helpers.daemon_harness import MODEL_TERMS, TEMPS, Served, expected_q, wait_until, write_test_model


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory):
    s = Served(tmp_path_factory.mktemp("e2e"), "e2e").start()
    yield s
    s.close()


def test_good_target_gets_the_model_command_by_query_and_on_the_command_key(served: Served) -> None:
    ok, command = served.client.query({"x_um": 240.0, "id": "a1"})
    assert ok, command
    assert set(command) >= {"id", "x_um", "q_um", "voltage_v", "temperatures_c", "model", "t"}
    assert command["id"] == "a1"
    assert command["x_um"] == 240.0
    assert command["temperatures_c"] == TEMPS
    assert command["q_um"] == pytest.approx(expected_q(240.0, TEMPS), abs=1e-9)
    assert command["voltage_v"] == pytest.approx(0.0 + 0.02 * command["q_um"], abs=1e-12)
    assert command["model"] == served.model.id
    assert abs(command["t"] - time.time()) < 5
    assert command["extrapolating"] == []
    published = served.client.wait(lambda: served.client.answers_for("a1"), 5, "command a1 published")
    assert published == [("command", command)]


def test_target_by_put_is_answered_once_on_command(served: Served) -> None:
    served.client.put(json.dumps({"x_um": 100, "id": 42}))
    answers = served.client.wait(lambda: served.client.answers_for(42), 5, "answer to id 42")
    served.client.put(json.dumps({"x_um": 1, "id": "sentinel-42"}))
    served.client.wait(lambda: served.client.answers_for("sentinel-42"), 5, "sentinel")
    assert served.client.answers_for(42) == answers
    assert len(answers) == 1 and answers[0][0] == "command"
    assert answers[0][1]["q_um"] == pytest.approx(expected_q(100.0, TEMPS), abs=1e-9)


BAD = [
    (b"not json at all", None, "not valid JSON"),
    (b"\xff\xfe\x00\x01binary\x80junk", None, "not UTF-8"),
    (b"", None, "not valid JSON"),
    (b"[1, 2, 3]", None, "JSON object"),
    (b'"x_um"', None, "JSON object"),
    (b'{"id": 7}', 7, "missing field 'x_um'"),
    (b'{"x_um": "100", "id": 8}', 8, "must be a number"),
    (b'{"x_um": true, "id": 9}', 9, "must be a number"),
    (b'{"x_um": null, "id": 10}', 10, "must be a number"),
    (b'{"x_um": NaN, "id": 11}', 11, "finite"),
    (b'{"x_um": Infinity, "id": 12}', 12, "finite"),
    (b'{"x_um": -Infinity, "id": "n13"}', "n13", "finite"),
    (b'{"x_um": 1e999, "id": 14}', 14, "finite"),
    (b'{"x_um": 600.5, "id": 15}', 15, "outside the workspace"),
    (b'{"x_um": -0.001, "id": 16}', 16, "outside the workspace"),
    (b'{"x_um": 100, "id": 1.5}', None, "'id' must be a string or an integer"),
    (b'{"x_um": 100, "id": true}', None, "'id' must be a string or an integer"),
    (b'{"x_um": 100, "id": [1]}', None, "'id' must be a string or an integer"),
    (b'{"x_um": 100, "id": "' + b"a" * 100_000 + b'"}', None, "exceeds"),
    (b"[" * 50_000, None, "exceeds"),
]


@pytest.mark.parametrize(("payload", "target_id", "message"), BAD, ids=[f"bad{i}" for i in range(len(BAD))])
def test_bad_payload_by_query_gets_exactly_one_error_with_its_id(served, payload, target_id, message) -> None:
    ok, error = served.client.query(payload)
    assert not ok
    assert error["id"] == target_id
    assert message in error["error"]
    assert error["kind"] in {"bad_payload", "out_of_workspace"}


def test_bad_payloads_by_put_each_get_one_error_and_the_log_is_rate_limited(served: Served) -> None:
    client = served.client
    client.put(json.dumps({"x_um": 5, "id": "before-flood"}))  # earlier tests' publications are all in
    client.wait(lambda: client.answers_for("before-flood"), 10, "the good target before the flood")
    before = len(client.errors)
    lines_before = len(served.daemon.log_events("target_refused"))
    started = time.monotonic()
    ids = [f"flood-{i}" for i in range(300)]
    for target_id in ids:  # recoverable ids, wrong type for x
        client.put(json.dumps({"x_um": "oops", "id": target_id}))
    for payload, _, _ in BAD:
        client.put(payload)
    client.put(json.dumps({"x_um": 5, "id": "after-flood"}))
    client.wait(lambda: client.answers_for("after-flood"), 10, "the good target after the flood")
    client.wait(lambda: len(client.errors) - before >= len(ids) + len(BAD), 10, "every bad payload answered")
    for target_id in ids:
        answers = client.answers_for(target_id)
        assert len(answers) == 1 and answers[0][0] == "error", (target_id, answers)
    assert len(client.errors) - before == len(ids) + len(BAD)
    logged = len(served.daemon.log_events("target_refused")) - lines_before
    assert logged <= 20 + 5 * (time.monotonic() - started) + 1  # the bucket's burst and rate, not 320 lines
    summary = served.daemon.wait_log("target_refused_suppressed", timeout=10)
    assert summary["suppressed"] > 0


def test_stale_channel_is_refused_by_name_then_recovers(served: Served) -> None:
    client = served.client
    try:
        served.sensors.write(age={"T2": 100.0})

        def refused():
            ok, answer = client.query({"x_um": 50, "id": "stale?"})
            return None if ok else answer

        error = wait_until(refused, 10, "a refusal for the stale channel", interval=0.05)
        assert error["kind"] == "stale" and "T2" in error["error"] and "old" in error["error"]
        assert error["id"] == "stale?"
        status = client.status()
        assert status["sensors"]["T2"]["state"] == "stale"
        assert status["sensors"]["T1"]["state"] == "ok"
    finally:
        served.sensors.write(age={})
    wait_until(lambda: client.query({"x_um": 50, "id": "fresh"})[0], 10, "commands again after recovery",
               interval=0.05)


def test_faulted_channel_is_refused_with_the_device_reason(served: Served) -> None:
    client = served.client
    try:
        served.sensors.write(fault={"T1": "thermocouple open circuit"})
        error = wait_until(lambda: (a := client.query({"x_um": 50, "id": "f"}))[0] is False and a[1], 10,
                           "a fault refusal", interval=0.05)
        assert error["kind"] == "fault" and "T1" in error["error"] and "open circuit" in error["error"]
        assert client.wait(lambda: client.telemetry.get("temperature/T1", {}).get("state") == "fault", 5,
                           "fault telemetry")
    finally:
        served.sensors.write(fault={})
    wait_until(lambda: client.query({"x_um": 50, "id": "f2"})[0], 10, "recovered", interval=0.05)


def test_failing_device_is_reopened_with_backoff_and_recovers(served: Served) -> None:
    client = served.client
    failed_before = len(served.daemon.log_events("sensor_group_failed"))
    recovered_before = len(served.daemon.log_events("sensor_group_recovered"))
    try:
        served.sensors.write(error="link down")
        error = wait_until(lambda: (a := client.query({"x_um": 50, "id": "d"}))[0] is False and a[1], 10,
                           "a refusal while the device fails", interval=0.05)
        assert "link down" in error["error"]
        first = served.daemon.wait_log("sensor_group_failed", count=failed_before + 1)
        assert "link down" in first["reason"] and first["retry_in_s"] > 0
        served.sensors.write(error="link still down")  # only a reopen attempt can report the new reason
        wait_until(lambda: "link still down" in str(client.query({"x_um": 50, "id": "d1"})[1].get("error")), 10,
                   "a refusal with the reason of a later attempt", interval=0.05)
    finally:
        served.sensors.write(error=None)
    wait_until(lambda: client.query({"x_um": 50, "id": "d2"})[0], 15, "recovered after reopen", interval=0.05)
    recovered = served.daemon.wait_log("sensor_group_recovered", count=recovered_before + 1)
    assert recovered["failures"] >= 2 and recovered["down_s"] > 0  # retried: closed and reopened
    # one line for the whole episode, not one per attempt
    assert len(served.daemon.log_events("sensor_group_failed")) == failed_before + 1


def test_extrapolation_is_flagged_in_command_and_status(served: Served) -> None:
    client = served.client
    try:
        served.sensors.set(T1=22.6)
        client.wait(lambda: client.telemetry.get("temperature/T1", {}).get("value") == 22.6, 5, "T1 22.6")
        ok, command = client.query({"x_um": 490, "id": "ex"})
        assert ok, command
        assert sorted(command["extrapolating"]) == ["T1", "x"]
        assert command["q_um"] == pytest.approx(expected_q(490, {**TEMPS, "T1": 22.6}), abs=1e-9)
        assert "T1" in client.status()["extrapolating"]
    finally:
        served.sensors.set(T1=TEMPS["T1"])
        client.wait(lambda: client.telemetry.get("temperature/T1", {}).get("value") == TEMPS["T1"], 5, "T1 back")


def test_telemetry_and_status_follow_the_contract(served: Served) -> None:
    client = served.client
    sample = client.wait(lambda: client.telemetry.get("temperature/T2"), 5, "T2 telemetry")
    assert set(sample) >= {"value", "unit", "t", "state"}
    assert sample["unit"] == "degC" and sample["state"] == "ok"
    status = client.status()
    assert status["cell"] == "e2e"
    assert status["model"]["id"] == served.model.id
    assert status["model"]["training"]["channels"]["T1"] == [21.5, 22.1]
    assert set(status["sensors"]["T1"]) >= {"value", "age_s", "state", "reason"}
    counters = status["counters"]
    assert counters["targets"] >= counters["commands"] > 0
    assert counters["errors"].get("bad_payload", 0) > 0


def test_missing_model_channel_starts_and_refuses_naming_it(tmp_path: Path) -> None:
    s = Served(tmp_path, "missing", channels=("T1",)).start(channels=("T1",))
    try:
        ok, error = s.client.query({"x_um": 10, "id": "m"})
        assert not ok and error["kind"] == "missing_channel" and "T2" in error["error"]
        assert s.daemon.wait_log("starting")["missing_channels"] == ["T2"]
    finally:
        assert s.close() == 0


def test_sighup_applies_a_good_edit_and_refuses_a_bad_one(tmp_path: Path) -> None:
    s = Served(tmp_path, "reload").start()
    client = s.client
    try:
        ok, before = client.query({"x_um": 300, "id": 1})
        assert ok and before["voltage_v"] == pytest.approx(0.02 * before["q_um"])

        s.write_config(actuator="volts_per_um = 0.01\noffset_v = 0.5\nv_max = 3.0")
        s.daemon.signal(signal.SIGHUP)
        s.daemon.wait_log("reload_applied")
        ok, after = client.query({"x_um": 200, "id": 2})
        assert ok and after["voltage_v"] == pytest.approx(0.5 + 0.01 * after["q_um"], abs=1e-12)
        ok, refused = client.query({"x_um": 300, "id": 3})  # 0.5 + 0.01 * ~300 > 3.0 V
        assert not ok and refused["kind"] == "voltage_limit" and refused["id"] == 3

        s.write_config(actuator="volts_per_umm = 0.01\noffset_v = 0.5\nv_max = 3.0")  # a typo
        s.daemon.signal(signal.SIGHUP)
        line = s.daemon.wait_log("reload_refused")
        assert any("actuator.volts_per_umm" in p for p in line["problems"]), line
        ok, still = client.query({"x_um": 200, "id": 4})
        assert ok and still["voltage_v"] == pytest.approx(0.5 + 0.01 * still["q_um"], abs=1e-12)

        s.write_config(actuator="volts_per_um = 0.01\noffset_v = 0.5\nv_max = 3.0")
        s.model_path.write_text('{"format": "nanodrift-model/1", "terms": [')  # an editor's half-saved file
        s.daemon.signal(signal.SIGHUP)
        line = s.daemon.wait_log("reload_refused", count=2)
        assert any("model.path" in p for p in line["problems"]), line
        ok, still = client.query({"x_um": 200, "id": 5})
        assert ok and still["model"] == s.model.id
        assert client.status()["counters"]["reload_failures"] == 2
    finally:
        assert s.close() == 0


def test_sighup_adds_the_missing_sensor_and_swaps_the_model(tmp_path: Path) -> None:
    s = Served(tmp_path, "swap", channels=("T1",)).start(channels=("T1",))
    try:
        ok, error = s.client.query({"x_um": 10, "id": "before"})
        assert not ok and error["kind"] == "missing_channel"
        terms = {**MODEL_TERMS, "1": 0.75}
        model2 = write_test_model(tmp_path / "model2.json", terms)
        s.model_path = tmp_path / "model2.json"
        s.write_config(channels=("T1", "T2"))
        s.daemon.signal(signal.SIGHUP)
        line = s.daemon.wait_log("reload_applied")
        assert line["drivers_restarted"] is True and line["model"] == model2.id
        s.client.wait_ready(("T1", "T2"))
        ok, command = s.client.query({"x_um": 10, "id": "after"})
        assert ok, command
        assert command["model"] == model2.id != s.model.id
        assert command["q_um"] == pytest.approx(expected_q(10, TEMPS, terms), abs=1e-9)
    finally:
        assert s.close() == 0


def test_sigterm_withdraws_the_token_and_exits_zero(tmp_path: Path) -> None:
    s = Served(tmp_path, "term").start()
    present, gone = threading.Event(), threading.Event()

    def on_liveliness(sample: zenoh.Sample) -> None:
        (gone if sample.kind == zenoh.SampleKind.DELETE else present).set()

    watcher = s.client.session.liveliness().declare_subscriber("nanodrift/term/alive", on_liveliness, history=True)
    try:
        assert present.wait(5), "liveliness token not seen"
        s.daemon.signal(signal.SIGTERM)
        assert s.daemon.proc.wait(10) == 0
        assert gone.wait(5), "liveliness token not withdrawn"
        assert not s.client.alive(0.5)
        events = [d["event"] for d in s.daemon.logs()]
        assert "stopping" in events and "stopped" in events
    finally:
        watcher.undeclare()
        s.close()
