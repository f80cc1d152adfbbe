"""Answers on a shared serial line go to the request that asked for them (issue 16, problem 7).

A PI controller (the ``serial_line`` actuator) and a position query share one port, built through the
plugin as the daemon builds them. When the controller answered ``SVA? 1`` after the actuator's
timeout, that late ``1=5.5300`` was read as the answer to the next ``POS? 1``: position ``ok``,
5.53 um while the stage was at 553 um. Over a real pty, no mocks.
"""

from __future__ import annotations

import asyncio
import time
import tomllib
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import pytest
from helpers.log_capture import captured_logging, json_lines
from helpers.serial_helpers import FakeGcsController

from daemon.config import ConfigError, parse_config
from drivers.base import DeviceError, DriverContext, State
from drivers.serial_line.actuator import SerialLineActuator
from drivers.serial_line.config import SerialLineActuatorConfig, SerialLineSensorConfig
from drivers.serial_line.line import SerialLineGroup
from drivers.serial_line.plugin import PLUGIN

POSITION = r"1=(?P<value>[-+0-9.]+)"  # an SVA? answer (1=5.5300) matches it too: only the matching can tell


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[FakeGcsController]:
    fake = FakeGcsController(tmp_path / "ttyPI")
    yield fake
    fake.close()


def shared(port: str, *, sensor_timeout_s: float = 1.0,
           actuator_timeout_s: float = 0.3) -> tuple[SerialLineGroup, SerialLineActuator]:
    """The position sensor and the actuator on one port, as the daemon builds them (one context)."""
    context = DriverContext()
    sensor = SerialLineSensorConfig(name="stage", role="position", port=port, baudrate=115200, query="POS? 1\n",
                                    pattern=POSITION, timeout_s=sensor_timeout_s)
    [group] = PLUGIN.create([sensor], context)
    actuator = PLUGIN.create_actuator(SerialLineActuatorConfig(port=port, readback="SVA? 1\n",
                                                               timeout_s=actuator_timeout_s), context)
    assert isinstance(group, SerialLineGroup) and isinstance(actuator, SerialLineActuator)
    assert actuator.port is group  # one port object, one lock
    actuator.limits_v = (-2.0, 12.0)
    return group, actuator


async def until(condition: Callable[[], bool], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout} s: {what}")
        await asyncio.sleep(0.01)


def test_a_late_readback_answer_is_never_read_as_the_next_position(controller: FakeGcsController) -> None:
    async def body() -> None:
        group, actuator = shared(controller.port)
        await group.open()
        await actuator.open()
        controller.voltage = 2.767  # the stage at 276.7 um
        assert (await group.read())["stage"].value == pytest.approx(276.7)
        # the controller answers SVA? 0.1 s after the actuator's 0.3 s (within the quiet period), then works
        # through what came next
        controller.late_s, controller.spacing_s = {"SVA?": 0.4}, 0.05
        with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n' within 0.3 s"):
            await actuator.command(276.5, 5.53)
        reading = (await group.read())["stage"]  # at once, as the poller would: the late 1=5.5300 is on its way
        assert reading.value != pytest.approx(5.53), "the late SVA? answer was taken as the position"
        assert reading.state is State.OK and reading.value == pytest.approx(553.0), reading
        assert group.late_answers == 1  # the late line, discarded
        late_sent_at = next(t for t, answer in controller.sent if answer == "1=5.5300")
        assert controller.lines[-1] == "POS? 1" and controller.line_times[-1] > late_sent_at  # asked after it
        controller.late_s = {}
        await actuator.command(276.5, 5.53)  # the line is clean: the readback matches again
        assert (await group.read())["stage"].value == pytest.approx(553.0)
        assert group.late_answers == 1
        await actuator.close()
        await group.close()

    run(body())


def test_a_late_position_answer_is_not_the_next_polls_value(controller: FakeGcsController) -> None:
    async def body() -> None:
        group, _ = shared(controller.port, sensor_timeout_s=0.3)
        await group.open()
        controller.voltage = 1.0  # 100 um
        controller.late_s, controller.spacing_s = {"POS?": 0.4}, 0.05
        first = (await group.read())["stage"]
        assert first.state is State.FAULT and first.reason == f"no line from {controller.port} in 0.3 s"
        controller.late_s = {}
        controller.voltage = 2.0  # the stage moved: 200 um now, while 1=100.0000 is still on its way
        second = (await group.read())["stage"]
        assert second.state is State.OK and second.value == pytest.approx(200.0), second
        assert group.late_answers == 1
        await group.close()

    run(body())


def test_unread_input_before_a_request_never_starts_its_answer(controller: FakeGcsController) -> None:
    async def body() -> None:
        group, _ = shared(controller.port)
        await group.open()
        controller.voltage = 5.53
        controller.inject(b"1=5.")  # a fragment nobody asked for: 1=5.1=553.0000 would read 5.1
        reader = group._reader
        assert reader is not None
        await until(lambda: reader.pending == 4, timeout=5.0, what="the reader holds the fragment")
        reading = (await group.read())["stage"]
        assert reading.state is State.OK and reading.value == pytest.approx(553.0), reading
        assert group.late_answers == 1  # the fragment, dropped with the flush
        controller.inject(b"1=9.9999\n")  # a whole line nobody asked for, between two polls
        await until(lambda: group.late_answers == 2, timeout=5.0, what="the stray line is counted")
        assert (await group.read())["stage"].value == pytest.approx(553.0)
        await group.close()

    run(body())


def test_late_answers_are_logged_once_per_episode(controller: FakeGcsController) -> None:
    async def body() -> None:
        group, _ = shared(controller.port)
        await group.open()
        controller.voltage = 1.0
        with captured_logging() as stream:
            for n in range(1, 4):  # an episode: three stray lines, and the poll between them drains
                controller.inject(b"1=9.9999\n")
                await until(lambda n=n: group.late_answers == n, timeout=5.0, what=f"stray line {n} counted")
            assert (await group.read())["stage"].value == pytest.approx(100.0)  # drained first: still the episode
            assert (await group.read())["stage"].value == pytest.approx(100.0)  # a clean request: it is over
            controller.inject(b"1=9.9999\n")  # a new episode
            await until(lambda: group.late_answers == 4, timeout=5.0, what="the next stray line counted")
            events = [e for e in json_lines(stream) if e.get("event") == "serial_late_answers"]
        assert len(events) == 2 and events[0]["port"] == controller.port and events[0]["line"] == "'1=9.9999'"
        await group.close()

    run(body())


def test_an_answer_that_does_not_match_is_a_fault_never_a_value(controller: FakeGcsController) -> None:
    async def body() -> None:
        group, actuator = shared(controller.port)
        await group.open()
        controller.answer = b"ERROR 17"
        reading = (await group.read())["stage"]
        assert reading.state is State.FAULT and "unexpected line" in reading.reason and "'ERROR 17'" in reading.reason
        with pytest.raises(DeviceError, match=r"unexpected answer 'ERROR 17' to 'SVA\? 1\\n' after 'opening the port'"):
            await actuator.read_back()
        controller.answer = b"1=1e999"  # matches the pattern, but is no voltage
        with pytest.raises(DeviceError, match=r"unexpected answer '1=1e999'"):
            await actuator.read_back()
        controller.answer = None
        controller.voltage = -1.2345
        assert await actuator.read_back() == ("voltage_v", -1.2345)  # faithfully what it said
        await group.close()

    run(body())


SHARED_PORT = """
[[sensors]]
name = "stage"
role = "position"
kind = "serial_line"
port = "/dev/ttyUSB0"
baudrate = 115200
{query}
[actuator]
kind = "serial_line"
port = "/dev/ttyUSB0"
{actuator}
"""


@pytest.mark.parametrize(("query", "actuator", "refused"), [
    ("", 'readback = "SVA? 1\\n"', True),
    ("", 'error_query = "ERR?\\n"', True),
    ("", "", False),  # write-only: nothing to match
    ('query = "POS? 1\\n"', 'readback = "SVA? 1\\n"', False),
], ids=["streaming+readback", "streaming+error_query", "streaming+write-only", "query+readback"])
def test_a_streaming_sensor_sharing_a_port_with_questions_is_refused_when_read(
        query: str, actuator: str, refused: bool) -> None:
    text = SHARED_PORT.format(query=query, actuator=actuator)
    if not refused:
        assert parse_config(tomllib.loads(text), source="t.toml").actuator.options.port == "/dev/ttyUSB0"
        return
    with pytest.raises(ConfigError) as caught:
        parse_config(tomllib.loads(text), source="t.toml")
    assert any(p.startswith("actuator.port: sensors[0] (stage) streams lines on '/dev/ttyUSB0': its lines cannot "
                            "be told from the answers") for p in caught.value.problems), caught.value.problems


def test_a_port_shared_with_other_settings_or_by_two_sensors_is_refused_when_read() -> None:
    text = SHARED_PORT.format(query='query = "POS? 1\\n"', actuator="baudrate = 9600") + (
        '[[sensors]]\nname = "T1"\nkind = "serial_line"\nport = "/dev/ttyUSB0"\nquery = "T?\\n"\n')
    with pytest.raises(ConfigError) as caught:
        parse_config(tomllib.loads(text), source="t.toml")
    problems = caught.value.problems
    assert "actuator.baudrate: port '/dev/ttyUSB0' is read by sensors[0] (stage) with baudrate = 115200, the " \
           "actuator says 9600 (one port, one setting)" in problems, problems
    assert any(p.startswith("sensors[1] (T1).port: port '/dev/ttyUSB0' is already used by sensors[0] (stage)")
               for p in problems), problems
