"""Answers on a shared serial line go to the request that asked for them (issue 16, problem 7).

A PI controller (the ``serial_line`` actuator) and a position query share one port, built through the
plugin as the daemon builds them. When the controller answered ``SVA? 1`` after the actuator's
timeout, that late ``1=5.5300`` was read as the answer to the next ``POS? 1``: position ``ok``,
5.53 um while the stage was at 553 um. Over a real pty, no mocks.

An answer later than the quiet period that follows its timeout was still taken for the next one (the
serial chaos suite: ``1=-0.5883``, an ``SVA?`` answer, published as the position): the resync query
(``resync_query = "*IDN?\\n"``, ``resync_pattern = 'PI|Physik'``) closes that gap, and check-config
warns about a shared port without one.
"""

from __future__ import annotations

import asyncio
import time
import tomllib
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path

import pytest
from helpers.daemon_harness import write_test_model
from helpers.log_capture import captured_logging, json_lines
from helpers.serial_helpers import FakeGcsController

from nanodrift.cli import main
from nanodrift.config import ConfigError, parse_config
from nanodrift.drivers.base import DeviceError, DriverContext, Reading, State
from nanodrift.drivers.serial_line.actuator import SerialLineActuator
from nanodrift.drivers.serial_line.config import SerialLineActuatorConfig, SerialLineSensorConfig
from nanodrift.drivers.serial_line.line import SerialLineGroup
from nanodrift.drivers.serial_line.plugin import PLUGIN

POSITION = r"1=(?P<value>[-+0-9.]+)"  # an SVA? answer (1=5.5300) matches it too: only the matching can tell


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[FakeGcsController]:
    fake = FakeGcsController(tmp_path / "ttyPI")
    yield fake
    fake.close()


RESYNC = {"resync_query": "*IDN?\n", "resync_pattern": "PI|Physik"}


def shared(port: str, *, sensor_timeout_s: float = 1.0, actuator_timeout_s: float = 0.3,
           resync_on: str | None = None) -> tuple[SerialLineGroup, SerialLineActuator]:
    """The position sensor and the actuator on one port, as the daemon builds them (one context);
    ``resync_on``: "sensor" or "actuator" declares the resync keys (None: nobody)."""
    context = DriverContext()
    sensor = SerialLineSensorConfig(name="stage", role="position", port=port, baudrate=115200, query="POS? 1\n",
                                    pattern=POSITION, timeout_s=sensor_timeout_s,
                                    **(RESYNC if resync_on == "sensor" else {}))
    [group] = PLUGIN.create([sensor], context)
    actuator = PLUGIN.create_actuator(SerialLineActuatorConfig(port=port, readback="SVA? 1\n",
                                                               timeout_s=actuator_timeout_s,
                                                               **(RESYNC if resync_on == "actuator" else {})),
                                      context)
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


#: the chaos suite's case: SVA? answered later than the actuator's timeout (0.3 s) plus the quiet period
#: (0.2 s) that follows it, well within the sensor's 1 s: 0.9 s after it was asked
BEYOND_THE_QUIET_PERIOD_S = 0.9


def test_without_resync_an_answer_later_than_the_quiet_period_is_taken_for_the_next(
        controller: FakeGcsController) -> None:
    """The gap the check-config warning names: the line cannot tell a late answer from a fresh one."""
    async def body() -> None:
        group, actuator = shared(controller.port)
        await group.open()
        controller.voltage = 2.767
        controller.late_s, controller.spacing_s = {"SVA?": BEYOND_THE_QUIET_PERIOD_S}, 0.05
        with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n' within 0.3 s"):
            await actuator.command(276.5, 5.53)
        reading = (await group.read())["stage"]  # quiet for 0.2 s, then POS? 1: the SVA? answer comes first
        assert reading.state is State.OK and reading.value == pytest.approx(5.53), reading
        await group.close()

    run(body())


@pytest.mark.parametrize("resync_on", ["sensor", "actuator"])
def test_with_resync_an_answer_however_late_is_never_the_next_position(
        controller: FakeGcsController, resync_on: str) -> None:
    async def body() -> None:
        group, actuator = shared(controller.port, resync_on=resync_on)
        assert group.resync == ("*IDN?\n", "PI|Physik")  # the line's, whichever declares it
        await group.open()
        controller.voltage = 2.767
        assert (await group.read())["stage"].value == pytest.approx(276.7)
        assert group.resyncs == 0  # a clean line sends no resync query
        controller.late_s, controller.spacing_s = {"SVA?": BEYOND_THE_QUIET_PERIOD_S}, 0.05
        with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n' within 0.3 s"):
            await actuator.command(276.5, 5.53)
        reading = (await group.read())["stage"]  # at once: *IDN?, whose answer comes after 1=5.5300, then POS?
        assert reading.value != pytest.approx(5.53), "the late SVA? answer was taken as the position"
        assert reading.state is State.OK and reading.value == pytest.approx(553.0), reading
        assert group.resyncs == 1 and group.late_answers == 1  # the late 1=5.5300, discarded
        assert controller.lines[-2:] == ["*IDN?", "POS? 1"]
        late_sent_at = next(t for t, answer in controller.sent if answer == "1=5.5300")
        assert controller.line_times[-1] > late_sent_at  # POS? was asked after the late answer came
        controller.late_s = {}
        await actuator.command(276.5, 5.53)  # clean: no resync, the readback matches
        assert (await group.read())["stage"].value == pytest.approx(553.0)
        assert group.resyncs == 1 and group.late_answers == 1
        await actuator.close()
        await group.close()

    run(body())


def test_a_late_answer_is_never_taken_by_the_line_a_reload_opens_next(controller: FakeGcsController) -> None:
    """The serial chaos suite's finding: a reload closes the line while its SVA? is unanswered and builds a new
    line for the port; the late answer must not be the new line's first position."""
    async def body() -> None:
        group, actuator = shared(controller.port, resync_on="sensor")
        await group.open()
        controller.voltage = 2.767
        assert (await group.read())["stage"].value == pytest.approx(276.7)
        controller.late_s, controller.spacing_s = {"SVA?": 0.5}, 0.05
        with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n'"):
            await actuator.command(276.5, 5.53)
        await actuator.close()  # the reload stops the drivers ...
        await group.close()
        controller.late_s = {}
        group2, actuator2 = shared(controller.port, resync_on="sensor")  # ... and builds new ones
        await group2.open()
        reading = (await group2.read())["stage"]
        assert reading.value != pytest.approx(5.53), "the late SVA? answer was taken as the position"
        assert reading.state is State.OK and reading.value == pytest.approx(553.0), reading
        assert group2.resyncs == 1  # the new line knew the port was left unsettled
        assert (await group2.read())["stage"].value == pytest.approx(553.0)
        assert group2.resyncs == 1  # and only once
        await actuator2.close()
        await group2.close()

    run(body())


async def a_late_sva_then_a_late_resync(
        controller: FakeGcsController) -> tuple[SerialLineGroup, SerialLineActuator, Reading]:
    """A shared line whose controller answers SVA? and *IDN? after the 0.3 s timeouts: the command fails, and the
    sensor's next read (its resync query unanswered in time) is a fault. Returns the group, the actuator and that
    reading."""
    group, actuator = shared(controller.port, sensor_timeout_s=0.3, resync_on="sensor")
    await group.open()
    controller.voltage = 5.53
    controller.late_s, controller.spacing_s = {"SVA?": 0.5, "*IDN?": 0.5}, 0.05
    with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n'"):
        await actuator.command(276.5, 5.53)
    first = (await group.read())["stage"]
    assert first.state is State.FAULT, first
    return group, actuator, first


def test_a_resync_answer_that_comes_late_is_a_fault_then_never_an_answer(controller: FakeGcsController) -> None:
    async def body() -> None:
        group, _, first = await a_late_sva_then_a_late_resync(controller)  # POS? never sent
        assert first.reason.startswith(f"{controller.port}: no answer matching resync_pattern 'PI|Physik' to the "
                                       "resync query '*IDN?\\n' within 0.3 s"), first.reason
        assert "POS? 1" not in controller.lines[-2:]
        controller.late_s = {}
        # the first *IDN?'s answer syncs the line; the second's, which follows it, is skipped: then 1=553.0000
        second = (await group.read())["stage"]
        assert second.state is State.OK and second.value == pytest.approx(553.0), second
        assert group.resyncs == 2
        await until(lambda: len([a for _, a in controller.sent if a == controller.IDN]) == 2, 5.0,
                    "both *IDN? answered")
        assert (await group.read())["stage"].value == pytest.approx(553.0)  # and nothing is left over
        await group.close()

    run(body())


def test_a_resync_answer_still_due_when_a_reload_opens_the_next_line_is_never_an_answer(
        controller: FakeGcsController) -> None:
    """The serial chaos release run's finding: a resync query went unanswered, a reload built a new line for the
    port, whose own resync query took the old one's answer; its own answer then came as the actuator's SVA?
    answer ("unexpected answer '(c)2015 Physik...' to 'SVA? 1'"), and that SVA? answer as the next position
    (published ok). The new line inherits the count of resync answers still due on the port."""
    async def body() -> None:
        group, actuator, first = await a_late_sva_then_a_late_resync(controller)  # the resync answer still due
        assert "resync query" in first.reason, first
        await actuator.close()  # the reload stops the drivers ...
        await group.close()
        controller.late_s = {}
        group2, actuator2 = shared(controller.port, sensor_timeout_s=0.3, resync_on="sensor")  # ... builds new ones
        await group2.open()
        readings = [(await group2.read())["stage"]]
        await until(lambda: len([a for _, a in controller.sent if a == controller.IDN]) == 2, 5.0,
                    "both *IDN? answered")
        readings.append((await group2.read())["stage"])
        await actuator2.close()
        await group2.close()
        assert [(r.state, r.value) for r in readings] == [(State.OK, pytest.approx(553.0))] * 2, readings
        assert group2.resyncs == 1  # the old *IDN?'s answer synced the line; the new one's was skipped

    run(body())


class StrayBeforeReadback(FakeGcsController):
    """A controller whose line carries a stray answer-shaped line just after each ``SVA?`` it receives (noise
    on the line, another program on the port), before its own late answer."""

    STRAY = b"1=-777.0000\n"  # no voltage the limits allow, no position in the valid range

    def _reply(self, line: str) -> str | None:
        if line.startswith("SVA?"):
            self.inject(self.STRAY)
        return super()._reply(line)


@pytest.mark.parametrize("when", ["opening", "commanding"])
def test_a_stray_line_taken_for_the_readback_never_shifts_the_real_answer_onto_the_position(
        tmp_path: Path, when: str) -> None:
    """The serial chaos release run's finding: a stray ``1=-777.0000`` came just after the actuator's ``SVA?``
    and was taken for its answer (untrusted: outside the limits); the real answer came after it, as the first
    line after the sensor's next ``POS?``, and was published as the position, ok. An answer the actuator does
    not believe leaves the line dirty: the next request resynchronises first."""
    controller = StrayBeforeReadback(tmp_path / "ttyPI")

    async def body() -> None:
        group, actuator = shared(controller.port, resync_on="sensor")
        await group.open()
        controller.voltage = 2.0
        controller.late_s = {"SVA?": 0.25}  # the real answer: after the stray, within the actuator's 0.3 s
        if when == "opening":
            assert await actuator.read_back() == ("voltage_v", -777.0)  # (the daemon's actuator_readback_untrusted)
        else:
            with pytest.raises(DeviceError, match=r"read back -777"):
                await actuator.command(250.0, 2.5)
        readings = [(await group.read())["stage"] for _ in range(3)]
        await group.close()
        want = controller.voltage * 100.0  # the position of the voltage held
        assert [(r.state, r.value) for r in readings] == [(State.OK, pytest.approx(want))] * 3, readings
        assert group.resyncs == 1  # the first POS? waited for the resync, the next ones found the line clean

    try:
        run(body())
    finally:
        controller.close()


def test_a_controller_that_does_not_answer_the_resync_query_fails_the_request_and_stays_dirty(
        controller: FakeGcsController) -> None:
    async def body() -> None:
        group, actuator = shared(controller.port, resync_on="actuator")
        await group.open()
        controller.silent = True
        with pytest.raises(DeviceError, match=r"no answer to 'SVA\? 1\\n'"):
            await actuator.command(100.0, 2.0)
        controller.voltage = 0.0
        with pytest.raises(DeviceError, match=r"no answer matching resync_pattern 'PI\|Physik' to the resync query "
                                              r"'\*IDN\?\\n' within 0.3 s .*nothing was sent"):
            await actuator.command(100.0, 2.0)  # SVA goes out (it takes no answer), its readback waits for *IDN?
        assert controller.lines[-2:] == ["SVA 1 2.0000", "*IDN?"] and controller.voltage == 2.0
        controller.silent = False
        await actuator.command(150.0, 3.0)  # *IDN? answered: clean again, the readback matches
        assert controller.lines[-3:] == ["SVA 1 3.0000", "*IDN?", "SVA? 1"]
        assert (await group.read())["stage"].value == pytest.approx(300.0)
        await group.close()

    run(body())


def test_an_actuator_alone_on_its_port_resynchronises_too(controller: FakeGcsController) -> None:
    async def body() -> None:
        actuator = PLUGIN.create_actuator(SerialLineActuatorConfig(port=controller.port, readback="SVA? 1\n",
                                                                   timeout_s=0.4, **RESYNC), DriverContext())
        assert isinstance(actuator, SerialLineActuator) and actuator.owns_port
        actuator.limits_v = (-2.0, 12.0)
        await actuator.open()
        # later than the timeout plus the quiet period (0.6 s), soon enough for the next *IDN? within 0.4 s
        controller.late_s, controller.spacing_s = {"SVA?": 0.65}, 0.05
        with pytest.raises(DeviceError, match="no answer"):
            await actuator.command(100.0, 2.0)
        controller.late_s = {}
        await actuator.command(300.0, 6.0)  # the late 1=2.0000 is not this readback: it would be a mismatch
        assert actuator.port.resyncs == 1 and actuator.port.late_answers == 1
        await actuator.close()

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


def test_resync_keys_are_checked_when_read() -> None:
    base = SHARED_PORT.format(query='query = "POS? 1\\n"', actuator='readback = "SVA? 1\\n"')
    for extra, where, why in [
        ('resync_query = "*IDN?\\n"\n', "actuator", "resync_pattern: resync_query and resync_pattern go together"),
        ("resync_pattern = '('\n", "actuator", "not a valid regular expression"),
    ]:
        with pytest.raises(ConfigError) as caught:
            parse_config(tomllib.loads(base + extra), source="t.toml")
        assert any(p.startswith(where) and why in p for p in caught.value.problems), caught.value.problems
    both = base.replace("baudrate = 115200\n", "baudrate = 115200\nresync_query = \"*IDN?\\n\"\n"
                                                "resync_pattern = 'PI'\n", 1)
    mismatch = both + 'resync_query = "*IDN?\\n"\nresync_pattern = "Physik"\n'
    with pytest.raises(ConfigError) as caught:
        parse_config(tomllib.loads(mismatch), source="t.toml")
    assert any(p.startswith("actuator.resync_query: port '/dev/ttyUSB0' is resynchronised by sensors[0] (stage) "
                            "with resync_query = '*IDN?\\n', resync_pattern = 'PI', the actuator says")
               for p in caught.value.problems), caught.value.problems
    assert parse_config(tomllib.loads(both + 'resync_query = "*IDN?\\n"\nresync_pattern = "PI"\n'),
                        source="t.toml").sensors[0].resync == ("*IDN?\n", "PI")  # the same twice: fine
    streaming = SHARED_PORT.format(query="resync_query = \"*IDN?\\n\"\nresync_pattern = 'PI'", actuator="")
    with pytest.raises(ConfigError) as caught:
        parse_config(tomllib.loads(streaming), source="t.toml")
    assert any("resync_query: a sensor that streams" in p for p in caught.value.problems), caught.value.problems


def write_cell(tmp_path: Path, sensor_extra: str = "", actuator_extra: str = "") -> Path:
    write_test_model(tmp_path / "model.json")
    path = tmp_path / "nanodrift.toml"
    path.write_text('[model]\npath = "model.json"\n[[hubs]]\nname = "adam"\nhost = "127.0.0.1"\n'
                    + "".join(f'[[sensors]]\nname = "{name}"\nkind = "modbus"\nhub = "adam"\naddress = {i}\n'
                              'input_type = "input"\n' for i, name in enumerate(("T1", "T2")))
                    + SHARED_PORT.format(query='query = "POS? 1\\n"\n' + sensor_extra,
                                         actuator='readback = "SVA? 1\\n"\n' + actuator_extra))
    return path


@pytest.mark.parametrize(("sensor_extra", "actuator_extra", "warned"), [
    ("", "", True),
    ("resync_query = \"*IDN?\\n\"\nresync_pattern = 'PI|Physik'\n", "", False),
    ("", "resync_query = \"*IDN?\\n\"\nresync_pattern = 'PI|Physik'\n", False),
], ids=["no-resync", "on-the-sensor", "on-the-actuator"])
def test_check_config_warns_about_a_shared_port_without_resync(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], sensor_extra: str, actuator_extra: str,
        warned: bool) -> None:
    """Not refused (controllers without an identification query exist, configs that ran before the keys);
    --strict makes it an error."""
    path = write_cell(tmp_path, sensor_extra, actuator_extra)
    code = main(["check-config", str(path)])
    err = capsys.readouterr().err
    assert code == 0, err
    warning = ("warning: actuator.port: port '/dev/ttyUSB0' is shared by sensors[2] (stage), querying 'POS? 1\\n', "
               "and the actuator asking 'SVA? 1\\n', with no resync_query: an answer that comes later than "
               "min(timeout_s, 0.2 s) after its request timed out looks like a fresh one")
    assert (warning in err) is warned, err
    if warned:
        assert "declare resync_query and resync_pattern" in err
        port_line = max(n for n, line in enumerate(path.read_text().splitlines(), 1)  # [actuator]'s
                        if line.startswith("port ="))
        assert f"{path}:{port_line}: {warning}" in err, err
        assert main(["check-config", "--strict", str(path)]) == 2
