"""The serial_line driver against an instrument emulated on a pty: values, garbage, silence,
a vanished device and its recovery, the exact query bytes, and a loop that never blocks."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Awaitable, Iterator
from pathlib import Path

import pytest
import serial
from helpers.serial_helpers import FakeInterferometer
from pydantic import ValidationError

from nanodrift.drivers.base import DeviceError, DriverContext, State
from nanodrift.drivers.serial_line.config import SerialLineSensorConfig
from nanodrift.drivers.serial_line.line import SerialLineGroup
from nanodrift.drivers.serial_line.plugin import PLUGIN
from nanodrift.drivers.serial_line.reader import SerialLineReader

PATTERN = r"P (?P<value>[-+0-9.]+) nm"


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture
def device(tmp_path: Path) -> Iterator[FakeInterferometer]:
    fake = FakeInterferometer(tmp_path / "ttyIFM")
    yield fake
    fake.close()


def group_for(port: str, **kw: object) -> SerialLineGroup:
    settings: dict[str, object] = {"name": "interferometer", "role": "position", "kind": "serial_line",
                                   "port": port, "baudrate": 115200, "query": "POS?\r", "pattern": PATTERN,
                                   "scale": 0.001, "timeout_s": 0.3}
    settings.update(kw)
    [group] = PLUGIN.create([SerialLineSensorConfig.model_validate(settings)], DriverContext())
    assert isinstance(group, SerialLineGroup)
    return group


def test_query_mode_reads_scaled_value_and_sends_exact_bytes(device: FakeInterferometer) -> None:
    async def body() -> None:
        group = group_for(device.port)
        await group.open()
        before = time.time()
        first = (await group.read())["interferometer"]
        device.position_nm = -2500.0
        second = (await group.read())["interferometer"]
        await group.close()
        assert first.state is State.OK and first.value == pytest.approx(123.4567) and first.unit == "um"
        assert before <= first.t <= time.time()
        assert second.value == pytest.approx(-2.5)
        assert bytes(device.received) == b"POS?\rPOS?\r"  # the query exactly as configured, once per poll

    run(body())


def test_streaming_mode_keeps_the_newest_line(tmp_path: Path) -> None:
    fake = FakeInterferometer(tmp_path / "ttySTREAM", stream=True, period_s=0.01, eol=b"\n")

    async def body() -> None:
        group = group_for(fake.port, query="")
        await group.open()
        first = (await group.read())["interferometer"]
        assert first.state is State.OK and first.value == pytest.approx(123.4567)
        fake.position_nm = 1000.0
        deadline = time.monotonic() + 5
        reading = first
        while reading.value != pytest.approx(1.0):
            assert time.monotonic() < deadline, "the newest streamed value never showed up"
            await asyncio.sleep(0.02)
            reading = (await group.read())["interferometer"]
        assert reading.t > first.t  # stamped on arrival
        await group.close()
        assert fake.received == b""  # nothing is ever sent to a streaming device

    try:
        run(body())
    finally:
        fake.close()


def test_garbage_faults_naming_what_came_and_what_was_expected(device: FakeInterferometer) -> None:
    async def body() -> None:
        group = group_for(device.port)
        await group.open()
        device.reply = b"ERR 17: laser not locked\r\n"
        reading = (await group.read())["interferometer"]
        assert reading.state is State.FAULT
        assert reading.reason == (f"unexpected line from {device.port}: 'ERR 17: laser not locked' "
                                  f"(expected pattern {PATTERN!r})")
        device.reply = b"P " + b"9" * 100 + b"x nm\r\n"
        long_reason = (await group.read())["interferometer"].reason
        assert f": {'P ' + '9' * 58 + '...'!r} (expected" in long_reason  # truncated to 60 characters
        device.reply = None
        assert (await group.read())["interferometer"].state is State.OK
        await group.close()

    run(body())


@pytest.mark.parametrize("query", ["POS?\r", ""])
def test_silence_faults_with_the_port_and_timeout(tmp_path: Path, query: str) -> None:
    fake = FakeInterferometer(tmp_path / "ttyQUIET", stream=not query)
    fake.silent = True

    async def body() -> None:
        group = group_for(fake.port, query=query)
        await group.open()
        ticks = 0

        async def ticker() -> None:
            nonlocal ticks
            while True:
                await asyncio.sleep(0.01)
                ticks += 1

        task = asyncio.create_task(ticker())
        start = time.monotonic()
        # under the caller's limit, as the daemon polls: the driver's own verdict comes first
        reading = (await asyncio.wait_for(group.read(), group.timeout_s))["interferometer"]
        elapsed = time.monotonic() - start
        task.cancel()
        assert reading.state is State.FAULT
        assert reading.reason == f"no line from {fake.port} in 0.3 s"
        assert 0.25 <= elapsed < 1.0
        assert ticks >= 10  # the event loop kept running while the driver waited for the device
        fake.silent = False
        assert (await group.read())["interferometer"].state is State.OK
        await group.close()

    try:
        run(body())
    finally:
        fake.close()


def test_vanished_device_raises_then_recovers_after_reopen(device: FakeInterferometer,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    opened: list[str] = []  # every port the driver asks the OS for
    serial_for_url = serial.serial_for_url

    def counting(url: str, *args: object, **kwargs: object) -> object:
        opened.append(url)
        return serial_for_url(url, *args, **kwargs)

    monkeypatch.setattr(serial, "serial_for_url", counting)

    async def body() -> None:
        group = group_for(device.port)
        await group.open()
        assert (await group.read())["interferometer"].state is State.OK
        device.unplug()
        with pytest.raises(DeviceError, match=device.port):
            for _ in range(3):  # the EIO reaches the driver within a poll or two
                await group.read()
        for _ in range(3):  # each read while it is away: exactly one attempt to reopen, no timing of its own
            before = len(opened)
            with pytest.raises(DeviceError, match=f"cannot open {device.port}"):
                await group.read()
            assert len(opened) == before + 1  # when to try again is the caller's back-off
        await group.close()
        with pytest.raises(DeviceError, match=f"cannot open {device.port}"):
            await group.open()  # the daemon's explicit reopen always tries
        device.replug()
        device.position_nm = 42000.0
        deadline = time.monotonic() + 5
        while True:  # read() reopens by itself
            try:
                reading = (await group.read())["interferometer"]
                break
            except DeviceError:
                assert time.monotonic() < deadline, "no recovery after the device came back"
                await asyncio.sleep(0.05)
        assert reading.value == pytest.approx(42.0)
        await group.close()

    run(body())


@pytest.mark.parametrize("given_up_by", ["a cancellation", "its timeout"])
def test_an_open_given_up_on_closes_its_port_once_it_ends(device: FakeInterferometer, monkeypatch: pytest.MonkeyPatch,
                                                          given_up_by: str) -> None:
    """A reload cancels an open in flight, or the OS answers it after ``timeout_s``: the thread still opens the
    port. That reader must be closed, not left reading beside the next one (two readers steal each other's bytes:
    "readiness to read but returned no data" and lost answers; the serial chaos suite's hung reload)."""
    real_open, real_close = SerialLineReader.open, SerialLineReader.close
    entered, release, closed = threading.Event(), threading.Event(), threading.Event()
    late: list[SerialLineReader] = []

    def gated_open(cls: type[SerialLineReader], url: str, settings: dict[str, object],
                   **kwargs: object) -> SerialLineReader:
        if late:  # only the first open is held up
            return real_open(url, settings, **kwargs)
        entered.set()
        release.wait(10)
        reader = real_open(url, settings, **kwargs)
        late.append(reader)
        return reader

    def noting_close(self: SerialLineReader) -> None:
        real_close(self)
        if late and self is late[0]:
            closed.set()

    monkeypatch.setattr(SerialLineReader, "open", classmethod(gated_open))
    monkeypatch.setattr(SerialLineReader, "close", noting_close)

    async def body() -> None:
        group = group_for(device.port)
        opening = asyncio.create_task(group.open())
        assert await asyncio.to_thread(entered.wait, 10)
        if given_up_by == "a cancellation":
            opening.cancel()
            with pytest.raises(asyncio.CancelledError):
                await opening
        else:
            with pytest.raises(DeviceError, match=f"cannot open {device.port}: no answer from the OS within 0.3 s"):
                await opening
        release.set()
        assert await asyncio.to_thread(closed.wait, 10), "the open given up on left its reader on the port"
        assert not late[0].port.is_open
        readings = [(await group.read())["interferometer"] for _ in range(20)]  # read() opens the port anew
        await group.close()
        assert [r.state for r in readings] == [State.OK] * 20
        assert bytes(device.received) == b"POS?\r" * 20  # every query reached the device, each answer was read

    run(body())


def test_two_opens_at_once_open_the_port_once(device: FakeInterferometer, monkeypatch: pytest.MonkeyPatch) -> None:
    """The sensor's poll and the actuator reopen a shared port on their own (after a reload, a fault): at once,
    each opened it and the first reader was left reading beside the second, stealing its answers for good."""
    real_open = SerialLineReader.open
    opened: list[SerialLineReader] = []

    def counting_open(cls: type[SerialLineReader], url: str, settings: dict[str, object],
                      **kwargs: object) -> SerialLineReader:
        opened.append(real_open(url, settings, **kwargs))
        return opened[-1]

    monkeypatch.setattr(SerialLineReader, "open", classmethod(counting_open))

    async def body() -> None:
        group = group_for(device.port)
        await asyncio.gather(group.open(), group.open(), group.read())
        readings = [(await group.read())["interferometer"] for _ in range(10)]
        await group.close()
        assert len(opened) == 1, f"the port was opened {len(opened)} times"
        assert [r.state for r in readings] == [State.OK] * 10

    run(body())


def test_a_close_during_an_open_leaves_no_reader_on_the_port(device: FakeInterferometer,
                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    """A reload closes the line while a poll (or the actuator) reopens it: the open must not end after the close
    with the closed line holding a reader beside the next line's."""
    real_open = SerialLineReader.open
    entered, release = threading.Event(), threading.Event()
    opened: list[SerialLineReader] = []

    def gated_open(cls: type[SerialLineReader], url: str, settings: dict[str, object],
                   **kwargs: object) -> SerialLineReader:
        entered.set()
        release.wait(10)
        opened.append(real_open(url, settings, **kwargs))
        return opened[-1]

    monkeypatch.setattr(SerialLineReader, "open", classmethod(gated_open))

    async def body() -> None:
        group = group_for(device.port)
        opening = asyncio.create_task(group.open())
        assert await asyncio.to_thread(entered.wait, 10)
        closing = asyncio.create_task(group.close())
        release.set()
        await asyncio.gather(opening, closing)
        assert len(opened) == 1 and not opened[0].port.is_open, "the closed line kept a reader on the port"

    run(body())


def test_cr_only_device_with_eol_cr(tmp_path: Path) -> None:
    fake = FakeInterferometer(tmp_path / "ttyCR", eol=b"\r")

    async def body() -> None:
        group = group_for(fake.port, eol="\r")
        await group.open()
        values = [(await group.read())["interferometer"].value for _ in range(2)]
        await group.close()
        assert values == [pytest.approx(123.4567)] * 2

    try:
        run(body())
    finally:
        fake.close()


def test_config_refuses_a_pattern_without_value_group_and_unknown_keys() -> None:
    with pytest.raises(ValidationError, match="needs a named group 'value'"):
        SerialLineSensorConfig(name="i", kind="serial_line", port="/dev/null", pattern=r"P (\d+) nm")
    with pytest.raises(ValidationError, match="not a valid regular expression"):
        SerialLineSensorConfig(name="i", kind="serial_line", port="/dev/null", pattern=r"P (?P<value>\d+ nm")
    with pytest.raises(ValidationError, match="baud_rate"):
        SerialLineSensorConfig.model_validate({"name": "i", "kind": "serial_line", "port": "x", "baud_rate": 9600})
    default = SerialLineSensorConfig(name="i", kind="serial_line", port="loop://", role="position")
    assert default.streaming and default.value_unit == "um"
    assert default.eol == "\n"


def test_two_sensors_on_one_port_are_refused() -> None:
    configs = [SerialLineSensorConfig(name=n, kind="serial_line", port="/dev/ttyUSB0") for n in ("a", "b")]
    with pytest.raises(ValueError, match="port '/dev/ttyUSB0' is already used by sensor 'a'"):
        PLUGIN.create(configs, DriverContext())
