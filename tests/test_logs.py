"""One JSON object per log line, always: the libraries' ``logging`` goes through the same renderer.

Unit tests drive :func:`nanodrift.logs.configure_logging` in-process with a fake clock; the last test
runs the daemon against a Modbus TCP peer on 127.0.0.1 that answers with a wrong protocol id, a
byte count that disagrees with the data, an unknown function code, a wrong transaction id and plain
garbage, and parses every line the daemon wrote on stderr.
"""

from __future__ import annotations

import asyncio
import io
import json
import logging
import re
import signal
import threading
from collections.abc import Iterator
from datetime import datetime
from itertools import pairwise
from pathlib import Path
from typing import Any

import pytest
from helpers.daemon_harness import Daemon, free_port, write_test_model
from helpers.log_capture import captured_logging
from helpers.modbus_peer import (
    CraftedModbusPeer,
    Request,
    Responder,
    byte_count_says,
    correct,
    garbage,
    mbap,
    too_many,
    wrong_protocol_id,
)

from nanodrift.drivers.base import DeviceError
from nanodrift.drivers.modbus.config import ModbusHubConfig
from nanodrift.drivers.modbus.hub import ModbusHub
from nanodrift.logs import CHATTER_WINDOW_S, configure_logging, get_logger


class FakeClock:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


@pytest.fixture
def captured() -> Iterator[tuple[io.StringIO, FakeClock]]:
    """configure_logging into a buffer; everything it changed is put back afterwards."""
    clock = FakeClock()
    with captured_logging("info", clock=clock) as stream:
        yield stream, clock


def lines(stream: io.StringIO) -> list[dict[str, Any]]:
    out = []
    for line in stream.getvalue().splitlines():
        doc = json.loads(line)  # every line is one JSON object
        assert isinstance(doc, dict), line
        out.append(doc)
    return out


PYMODBUS_ERROR = "Invalid Modbus protocol id: 1\n>>>>> send: 0x0 0x1 0x0 0x0\n>>>>> recv: 0x0 0x1 0x0 0x1 0x0 0x7"


def test_a_librarys_error_is_a_json_line_with_the_daemons_keys_and_no_hex_dump(captured) -> None:
    stream, _ = captured
    get_logger().info("serving", cell="c0")
    logging.getLogger("pymodbus.logging").error(PYMODBUS_ERROR)
    own, library = lines(stream)
    assert own["event"] == "serving" and own["cell"] == "c0"
    assert library["event"] == "Invalid Modbus protocol id: 1"
    assert library["level"] == "error" and library["logger"] == "pymodbus.logging"
    assert set(own) - {"cell"} <= set(library) and "timestamp" in library
    assert ">>>>>" not in stream.getvalue()


def test_a_traceback_is_one_field_of_one_line(captured) -> None:
    stream, _ = captured
    try:
        raise ConnectionResetError("peer sent garbage")
    except ConnectionResetError:
        logging.getLogger("asyncio").error("Fatal error: protocol.data_received() call failed.\nprotocol: <x>",
                                           exc_info=True)
    [line] = lines(stream)
    assert line["logger"] == "asyncio" and line["event"].startswith("Fatal error: protocol.data_received()")
    assert line["exception"].startswith("Traceback (most recent call last):")
    assert "ConnectionResetError: peer sent garbage" in line["exception"]


def test_an_exception_in_a_thread_is_one_json_line(captured) -> None:
    stream, _ = captured

    def crash() -> None:
        raise RuntimeError("callback bug")

    thread = threading.Thread(target=crash, name="zenoh-callback")
    thread.start()
    thread.join()
    [line] = lines(stream)
    assert line["event"] == "thread_exception" and line["thread"] == "zenoh-callback"
    assert "RuntimeError: callback bug" in line["exception"]


def test_repeated_device_chatter_is_one_line_then_a_suppressed_count(captured) -> None:
    stream, clock = captured
    chatter = logging.getLogger("pymodbus.logging")
    for tid in range(50):  # numbers differ (transaction ids): still the same message
        chatter.error(f"ERROR: request ask for transaction_id={tid} but got id={tid + 7}, Skipping.")
        clock.now += 0.1
    get_logger().warning("sensor_state", channel="T1", state="fault")  # the daemon's own: never throttled
    assert [d["event"] for d in lines(stream)] == [
        "ERROR: request ask for transaction_id=0 but got id=7, Skipping.", "sensor_state"]
    clock.now += 10.0  # the window is over: the next line says how many were dropped
    get_logger().info("reload_applied")
    _first, _own, summary, applied = lines(stream)
    assert summary["logger"] == "pymodbus.logging" and summary["suppressed"] == 49 and summary["window_s"] == 10.0
    assert applied["event"] == "reload_applied"
    chatter.error("ERROR: request ask for transaction_id=99 but got id=3, Skipping.")
    assert lines(stream)[-1]["event"].startswith("ERROR: request ask for transaction_id=99")  # a new window


def test_pymodbus_info_chatter_is_hidden_unless_debug(captured) -> None:
    stream, clock = captured
    logging.getLogger("pymodbus.logging").info("send: 0x0 0x1 0x0 0x0 0x0 0x6")
    assert stream.getvalue() == ""
    configure_logging("debug", json_lines=True, stream=stream, clock=clock)
    logging.getLogger("pymodbus.logging").debug("send: 0x0 0x1 0x0 0x0 0x0 0x6")
    [line] = lines(stream)
    assert line["level"] == "debug" and line["event"].startswith("send: 0x0")
    assert len([h for h in logging.getLogger().handlers if type(h).__name__ == "OneLineHandler"]) == 1


def test_pymodbus_connection_failures_are_debug_lines(captured) -> None:
    """A hub retrying a dead module: the daemon's sensor_group_failed says it once per episode; pymodbus'
    own "Failed to connect" / "Repeating...." per attempt would repeat it (they stay out at info)."""
    stream, clock = captured

    async def attempts(hub: ModbusHub, n: int) -> None:
        for _ in range(n):
            with pytest.raises(DeviceError, match="cannot connect"):
                await hub.ensure_connected()

    hub = ModbusHub(ModbusHubConfig(name="adam", port=free_port(), timeout_s=0.5))  # nobody listens there
    asyncio.run(attempts(hub, 3))
    assert hub.connect_attempts == 3
    assert stream.getvalue() == ""
    configure_logging("debug", json_lines=True, stream=stream, clock=clock)
    asyncio.run(attempts(ModbusHub(ModbusHubConfig(name="ipc", port=free_port(), timeout_s=0.5)), 2))
    library = [d for d in lines(stream) if d.get("logger", "").startswith("pymodbus")]
    assert library and all(d["level"] == "debug" for d in library), library
    assert any(d["event"].startswith("Failed to connect") for d in library), library


# --- the daemon against a misbehaving Modbus peer -------------------------------------------------


def unknown_function() -> Responder:
    """The right transaction id, but a function code pymodbus has no decoder for."""
    return lambda r: mbap(r.tid, r.unit, bytes.fromhex("41 02 0000"))


def wrong_transaction() -> Responder:
    return lambda r: mbap((r.tid + 7) & 0xFFFF, r.unit, bytes.fromhex("04 04 00d7 00dc"))


def rotation() -> list[Responder]:
    good = correct([215] * 8)  # between faults, so the daemon's reopen backoff starts small again
    bad = [wrong_protocol_id(), byte_count_says(6), garbage(), unknown_function(), too_many(), wrong_transaction()]
    return [step for fault in bad for step in (fault, good)]


def modbus_config(zenoh_port: int, modbus_port: int, model: Path) -> str:
    sensors = "".join(
        f'[[sensors]]\nname = "T{i + 1}"\nkind = "modbus"\nhub = "adam"\naddress = {i}\ninput_type = "input"\n'
        "scale = 0.1\ninterval_s = 0.05\nmax_age_s = 2.0\n"
        for i in range(2)
    )
    return (
        f'cell = "logs"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zenoh_port}"]\n'
        f'multicast_scouting = false\n[model]\npath = "{model}"\n'
        f'[[hubs]]\nname = "adam"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {modbus_port}\ntimeout_s = 0.3\n'
        + sensors
    )


def test_every_stderr_line_is_json_when_the_modbus_peer_misbehaves(tmp_path: Path) -> None:
    answers = rotation()
    with CraftedModbusPeer(answers) as peer:
        write_test_model(tmp_path / "model.json")
        config = tmp_path / "nanodrift.toml"
        config.write_text(modbus_config(free_port(), peer.port, tmp_path / "model.json"))
        daemon = Daemon(["--config", str(config)], tmp_path / "daemon.log")
        try:
            daemon.wait_log("serving", timeout=30)
            peer.wait_requests(2 * len(answers), timeout=90)  # every misbehaviour, twice
            daemon.check_alive()
            daemon.signal(signal.SIGTERM)
            assert daemon.proc.wait(20) == 0
        finally:
            daemon.stop()
        served = list(peer.requests)
    assert all(r.function == 4 and (r.address, r.count) == (0, 2) for r in served)
    text = (tmp_path / "daemon.log").read_text()
    docs = []
    for number, line in enumerate(text.splitlines(), start=1):
        try:
            doc = json.loads(line)
        except ValueError:
            raise AssertionError(f"stderr line {number} is not JSON: {line!r}\n{text[-4000:]}") from None
        assert isinstance(doc, dict) and {"event", "level", "timestamp"} <= set(doc), line
        docs.append(doc)
    assert ">>>>>" not in text  # pymodbus' hex dumps never reach the journal at info level
    library = [d for d in docs if str(d.get("logger", "")).startswith(("pymodbus", "asyncio"))]
    assert any(d["event"].startswith("Invalid Modbus protocol id") for d in library), library
    for d in library:
        if d["logger"] == "asyncio" and "suppressed" not in d:  # its traceback is a field, not more lines
            assert d["exception"].startswith("Traceback (most recent call last):"), d
    written: dict[tuple[str, str], list[datetime]] = {}
    for d in library:  # the same chatter is written at most once per window (then summarised)
        if "suppressed" not in d:
            key = (d["logger"], re.sub(r"0x[0-9a-fA-F]+|\d+", "#", d["event"].split("\n")[0]))
            written.setdefault(key, []).append(datetime.fromisoformat(d["timestamp"]))
    for key, times in written.items():
        gaps = [(b - a).total_seconds() for a, b in pairwise(times)]
        assert all(gap >= CHATTER_WINDOW_S for gap in gaps), (key, gaps)
    assert "malformed answer from device 1 input register 0 (count 2)" in text  # the byte count was checked


def test_request_helper_records_what_the_daemon_asked(tmp_path: Path) -> None:
    """The peer's request parsing, against bytes written by hand (FC 4, address 0, 2 registers)."""
    request = Request(tid=5, protocol=0, unit=1, function=4, address=0, count=2,
                      raw=bytes.fromhex("0005 0000 0006 01 04 0000 0002"))
    assert wrong_protocol_id()(request) == bytes.fromhex("0005 0001 0007 01 04 04 00d7 00d7")
    assert byte_count_says(6)(request)[7:] == bytes.fromhex("04 06 00d7 00d8")  # says 6, carries 4
    assert too_many()(request)[7:] == bytes.fromhex("04 06 00d7 00d8 00d9")
