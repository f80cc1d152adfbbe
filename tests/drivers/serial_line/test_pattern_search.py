"""Serial patterns are searched in the line (re.search), as operators use grep; ^...$ demands all of it.

Over a real pty: a device answering ``P +123456.7 nm OK`` used to be faulted with the documented
example pattern because the whole line had to match.
"""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Iterator
from pathlib import Path

import pytest
from helpers.serial_helpers import FakeInterferometer

from nanodrift.drivers.base import DriverContext, Reading, State
from nanodrift.drivers.serial_line.config import DEFAULT_PATTERN, SerialLineSensorConfig
from nanodrift.drivers.serial_line.line import SerialLineGroup
from nanodrift.drivers.serial_line.plugin import PLUGIN

DOCUMENTED = r"P (?P<value>[-+0-9.]+) nm"  # README and config/lab.toml


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture
def device(tmp_path: Path) -> Iterator[FakeInterferometer]:
    fake = FakeInterferometer(tmp_path / "ttyIFM")
    yield fake
    fake.close()


def group_for(port: str, pattern: str) -> SerialLineGroup:
    config = SerialLineSensorConfig(name="interferometer", role="position", port=port, baudrate=115200,
                                    query="POS?\r", pattern=pattern, scale=0.001, timeout_s=0.3)
    [group] = PLUGIN.create([config], DriverContext())
    assert isinstance(group, SerialLineGroup)
    return group


async def read_line(device: FakeInterferometer, pattern: str, line: bytes) -> Reading:
    device.reply = line
    group = group_for(device.port, pattern)
    await group.open()
    try:
        return (await group.read())["interferometer"]
    finally:
        await group.close()


def test_the_documented_pattern_reads_a_line_with_a_trailing_status(device: FakeInterferometer) -> None:
    async def body() -> None:
        reading = await read_line(device, DOCUMENTED, b"P +123456.7 nm OK\r\n")
        assert reading.state is State.OK, reading.reason
        assert reading.value == pytest.approx(123.4567)
        reading = await read_line(device, DOCUMENTED, b"#12 P -250.0 nm\r\n")  # a prefix is fine too
        assert reading.state is State.OK and reading.value == pytest.approx(-0.25)

    run(body())


def test_an_anchored_pattern_demands_the_whole_line(device: FakeInterferometer) -> None:
    async def body() -> None:
        anchored = "^" + DOCUMENTED + "$"
        reading = await read_line(device, anchored, b"P +123456.7 nm OK\r\n")
        assert reading.state is State.FAULT
        assert reading.reason == (f"unexpected line from {device.port}: 'P +123456.7 nm OK' "
                                  f"(expected pattern {anchored!r})")
        assert (await read_line(device, anchored, b"P +123456.7 nm\r\n")).value == pytest.approx(123.4567)

    run(body())


def test_the_default_pattern_still_wants_a_line_that_is_just_a_number(device: FakeInterferometer) -> None:
    async def body() -> None:
        assert (await read_line(device, DEFAULT_PATTERN, b"  -12.5e1 \r\n")).value == pytest.approx(-0.125)
        assert (await read_line(device, DEFAULT_PATTERN, b"ERR 17 laser\r\n")).state is State.FAULT

    run(body())


def test_the_config_says_how_patterns_are_matched() -> None:
    doc = SerialLineSensorConfig.__doc__ or ""
    assert "re.search" in doc and "^...$" in doc
    assert "re.search" in (SerialLineSensorConfig.model_fields["pattern"].description or "")
