"""The ``dcon`` plugin against DCON modules emulated on a real pty, and its line parser against hostile input."""

from __future__ import annotations

import asyncio
import math
from collections.abc import Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest
from helpers.budget import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from nanodrift.drivers.base import DeviceError, DriverContext, State
from nanodrift.drivers.dcon.config import DconHubConfig, DconSensorConfig
from nanodrift.drivers.dcon.group import DconModuleGroup
from nanodrift.drivers.dcon.protocol import (
    DconFormatError,
    checksum,
    frame,
    parse_all_channels,
    parse_configuration,
    unframe,
)
from nanodrift.drivers.registry import load_plugin
from nanodrift.drivers.testing import DconBusEmulator, DconModule, DconTcpGateway

# --- the line parser ------------------------------------------------------------------------------

temperatures = st.floats(min_value=-270.0, max_value=1800.0, allow_nan=False).map(lambda v: round(v, 2))


@given(st.lists(temperatures, min_size=1, max_size=8), st.sets(st.integers(0, 7)))
def test_an_all_channels_answer_parses_to_each_channel_in_order(values: list[float], open_channels: set[int]) -> None:
    module = DconModule(1, values, open_channels=open_channels)
    parsed = parse_all_channels(module.answer("#01") or "")
    assert len(parsed) == len(values)
    for channel, (value, got) in enumerate(zip(values, parsed, strict=True)):
        if channel in open_channels:
            assert math.isnan(got.value) and "+9999" in got.problem
        else:
            assert got.problem == "" and got.value == pytest.approx(value, abs=0.005)


@given(st.text(max_size=80))
def test_any_line_is_channels_or_a_format_error_naming_what_was_expected(line: str) -> None:
    try:
        parsed = parse_all_channels(line)
    except DconFormatError as error:
        assert "expected" in str(error) or "invalid command" in str(error)
    else:
        assert line.startswith(">") and parsed
        assert all(math.isfinite(v.value) != bool(v.problem) for v in parsed)


def test_out_of_range_codes_are_problems_never_temperatures() -> None:
    over, under, cold, zero = parse_all_channels(">+9999-0000-0012.50+0000.00")
    assert math.isnan(over.value) and "over range" in over.problem
    assert math.isnan(under.value) and "under range" in under.problem
    assert cold.value == -12.5 and zero.value == 0.0 and not cold.problem and not zero.problem
    with pytest.raises(DconFormatError, match="invalid command"):
        parse_all_channels("?01")


def test_the_adam_manuals_examples_parse_as_it_says() -> None:
    # ADAM 4000 manual, #AA: "#21" -> channels 0 to 7 at +7.2111 ... +7.5678 (volts there)
    values = parse_all_channels(">+7.2111+7.2567+7.3125+7.1000+7.4712+7.2555+7.1234+7.5678")
    assert [v.value for v in values] == [7.2111, 7.2567, 7.3125, 7.1, 7.4712, 7.2555, 7.1234, 7.5678]
    # $AA2: "$452" -> "!45050600": input range 05, 9600 bps (06), engineering units, no checksum
    config = parse_configuration("!45050600", 0x45)
    assert (config.type_code, config.baud_code, config.engineering_units, config.checksum) == (5, 6, True, False)


def test_checksum_is_the_icp_das_example() -> None:
    # ICP DAS manuals' worked example: $012 -> B7, and the answer !01200600 -> AA
    assert frame("$012", with_checksum=True) == b"$012B7\r"
    assert checksum("!01200600") == "AA"
    assert unframe("!01200600AA\r", with_checksum=True) == "!01200600"


@given(st.text(alphabet="0123456789+-.>!?ABCDEF", min_size=1, max_size=40), st.data())
def test_a_single_changed_character_fails_the_checksum(body: str, data: st.DataObject) -> None:
    framed = body + checksum(body)
    index = data.draw(st.integers(0, len(body) - 1))
    replacement = data.draw(st.sampled_from("0123456789+-.>!?ABCDEF").filter(lambda c: c != body[index]))
    corrupted = framed[:index] + replacement + framed[index + 1:]
    with pytest.raises(DconFormatError, match="checksum"):
        unframe(corrupted, with_checksum=True)


def test_configuration_reads_format_and_checksum_bits() -> None:
    config = parse_configuration("!010F0640", 1)
    assert (config.type_code, config.engineering_units, config.checksum) == (0x0F, True, True)
    with pytest.raises(DconFormatError, match="expected !01TTCCFF"):
        parse_configuration("!01ZZ", 1)


# --- the plugin on a pty --------------------------------------------------------------------------


def groups(bus: DconBusEmulator, sensors: list[dict[str, Any]], timeout_s: float = 0.3) -> list[DconModuleGroup]:
    plugin = load_plugin("dcon")
    hub = DconHubConfig(name="rs485", port=bus.port, timeout_s=timeout_s)
    configs = [plugin.config_model.model_validate({"kind": "dcon", "hub": "rs485", **s}) for s in sensors]
    built = plugin.create(configs, DriverContext(hubs={"rs485": hub}))
    assert all(isinstance(g, DconModuleGroup) for g in built)
    return built  # type: ignore[return-value]


def run(body: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(body(), 20))


@pytest.fixture
def eight_channels(tmp_path: Path) -> Any:
    bus = DconBusEmulator(tmp_path / "ttyRS485", [DconModule(0x1A, [20.0 + c for c in range(8)], name="4018+",
                                                            open_channels={5}, checksum=True)])
    yield bus
    bus.close()


def test_eight_channels_from_one_exchange_and_the_open_one_alone_faults(eight_channels: DconBusEmulator) -> None:
    sensors = [{"name": f"T{c}", "address": 0x1A, "channel": c, "checksum": True, "open_detection": True}
               for c in range(8)]
    [group] = groups(eight_channels, sensors)

    async def body() -> None:
        await group.open()
        eight_channels.requests.clear()
        readings = await group.read()
        await group.close()
        assert group.module_name == "4018+"
        for channel in range(8):
            reading = readings[f"T{channel}"]
            if channel == 5:
                assert reading.state is State.FAULT and "channel 5" in reading.reason and "+9999" in reading.reason
            else:
                assert reading.state is State.OK and reading.value == pytest.approx(20.0 + channel)
        # what the bus received: one #AA for all eight, then the diagnosis, each with its checksum
        assert eight_channels.requests == ["#1A" + checksum("#1A"), "$1AB" + checksum("$1AB")]

    run(body)


def test_the_modules_own_diagnosis_faults_a_channel_whose_value_looks_fine(tmp_path: Path) -> None:
    module = DconModule(2, [21.0, 22.0, 23.0, 24.0])
    bus = DconBusEmulator(tmp_path / "tty", [module])
    [group] = groups(bus, [{"name": f"T{c}", "address": 2, "channel": c, "open_detection": True} for c in range(4)])

    async def body() -> None:
        await group.open()
        module.diagnosed_channels.add(3)  # its value still reads 24.00
        readings = await group.read()
        await group.close()
        assert readings["T3"].state is State.FAULT and "$AAB" in readings["T3"].reason
        assert [readings[f"T{c}"].state for c in range(3)] == [State.OK] * 3

    try:
        run(body)
    finally:
        bus.close()


def test_two_modules_on_one_bus_each_get_their_own_answer(tmp_path: Path) -> None:
    bus = DconBusEmulator(tmp_path / "tty", [DconModule(1, [11.0, 12.0, 13.0, 14.0]),
                                             DconModule(2, [21.0, 22.0, 23.0, 24.0], name="4118")])
    built = groups(bus, [{"name": "A0", "address": 1, "channel": 0}, {"name": "B3", "address": 2, "channel": 3}])

    async def body() -> None:
        for group in built:
            await group.open()
        for _ in range(5):  # concurrent polls: the bus lock keeps each answer with its request
            first, second = await asyncio.gather(*(group.read() for group in built))
            assert first["A0"].value == 11.0 and second["B3"].value == 24.0
        for group in built:
            await group.close()

    try:
        run(body)
    finally:
        bus.close()


@pytest.mark.parametrize(("misbehave", "expected"), [
    (lambda bus: setattr(bus, "silent", True), "no answer to '#01' within 0.3 s"),
    (lambda bus: setattr(bus, "reply", b"#$%garbage\r"), "expected '>' and the channels' values"),
    (lambda bus: setattr(bus, "reply", b"\xff\xfe\r"), "is not ASCII"),
])
def test_silence_and_garbage_are_device_errors_naming_the_port(tmp_path: Path, misbehave: Any, expected: str) -> None:
    bus = DconBusEmulator(tmp_path / "tty", [DconModule(1, [21.0, 22.0, 23.0, 24.0])])
    [group] = groups(bus, [{"name": "T1", "address": 1, "channel": 0}])

    async def body() -> None:
        await group.open()
        misbehave(bus)
        with pytest.raises(DeviceError) as caught:
            await group.read()
        assert bus.port in str(caught.value) and expected in str(caught.value)
        await group.close()

    try:
        run(body)
    finally:
        bus.close()


@pytest.mark.parametrize(("module", "config", "expected"), [
    (DconModule(1, [21.0] * 4, data_format=2), {}, "data format 2"),
    (DconModule(1, [21.0] * 4, checksum=True), {}, "no answer to '$01M'"),  # a module checking sums ignores ours
    (DconModule(1, [21.0] * 4), {"checksum": True}, "checksum"),
    (DconModule(7, [21.0] * 4), {}, "wrong address"),
])
def test_a_module_set_up_otherwise_is_refused_at_open(tmp_path: Path, module: DconModule, config: dict[str, Any],
                                                      expected: str) -> None:
    bus = DconBusEmulator(tmp_path / "tty", [module])
    [group] = groups(bus, [{"name": "T1", "address": 1, "channel": 0, **config}])

    async def body() -> None:
        with pytest.raises(DeviceError, match="DCON hub 'rs485'") as caught:
            await group.open()
        assert expected in str(caught.value)
        await group.close()

    try:
        run(body)
    finally:
        bus.close()


def test_a_channel_the_module_does_not_have_is_a_fault(tmp_path: Path) -> None:
    bus = DconBusEmulator(tmp_path / "tty", [DconModule(1, [21.0, 22.0, 23.0, 24.0])])
    [group] = groups(bus, [{"name": "T1", "address": 1, "channel": 0}, {"name": "T7", "address": 1, "channel": 7}])

    async def body() -> None:
        await group.open()
        readings = await group.read()
        await group.close()
        assert readings["T1"].value == 21.0
        assert readings["T7"].state is State.FAULT and "answered 4 channel(s)" in readings["T7"].reason

    try:
        run(body)
    finally:
        bus.close()


# --- bad config -----------------------------------------------------------------------------------


@pytest.mark.parametrize(("key", "value"), [("address", 256), ("channel", 8), ("address", "01")])
def test_bad_keys_are_refused_naming_them(key: str, value: Any) -> None:
    raw = {"name": "T1", "kind": "dcon", "hub": "rs485", "address": 1, "channel": 0, key: value}
    with pytest.raises(ValueError, match=key):
        DconSensorConfig.model_validate(raw)


def test_channels_of_one_module_must_agree_and_not_repeat() -> None:
    plugin = load_plugin("dcon")
    configs = [DconSensorConfig.model_validate({"name": n, "kind": "dcon", "hub": "h", "address": 1, **k})
               for n, k in [("T1", {"channel": 0}), ("T2", {"channel": 1, "checksum": True}), ("T3", {"channel": 0})]]
    problems = plugin.config_problems(list(enumerate(configs)), None)
    assert any(p.startswith("sensors[1] (T2).checksum:") and "sensors[0] (T1)" in p for p in problems)
    assert any(p.startswith("sensors[2] (T3).channel:") and "already read by sensors[0] (T1)" in p for p in problems)


@pytest.mark.parametrize(("hub", "expected"), [
    ({"name": "h", "type": "tcp", "port": "/dev/ttyUSB0"}, "TCP port"),
    ({"name": "h", "type": "serial", "port": 4001}, "serial device"),
])
def test_a_hub_whose_port_does_not_fit_its_type_is_refused(hub: dict[str, Any], expected: str) -> None:
    with pytest.raises(ValueError, match=expected):
        DconHubConfig.model_validate(hub)


def test_a_tcp_gateway_hub_reads_the_same_module_and_recovers_after_it_restarts() -> None:
    gateway = DconTcpGateway([DconModule(3, [19.5, 20.5, 21.5, 22.5, 23.5, 24.5, 25.5, 26.5], open_channels={0})])
    plugin = load_plugin("dcon")
    hub = DconHubConfig(name="gw", type="tcp", host="127.0.0.1", port=gateway.port, timeout_s=0.3)
    configs = [plugin.config_model.model_validate({"name": f"T{c}", "kind": "dcon", "hub": "gw", "address": 3,
                                                   "channel": c}) for c in (0, 7)]
    [group] = plugin.create(configs, DriverContext(hubs={"gw": hub}))

    async def body() -> None:
        await group.open()
        readings = await group.read()
        assert readings["T0"].state is State.FAULT and readings["T7"].value == 26.5
        gateway.stop()
        with pytest.raises(DeviceError, match=f"127.0.0.1:{gateway.port}"):
            await group.read()
        await group.close()
        gateway.start()
        await group.open()
        assert (await group.read())["T7"].value == 26.5
        await group.close()
        assert gateway.requests.count("#03") == 2

    try:
        run(body)
    finally:
        gateway.stop()


@pytest.fixture
def pty_bus(tmp_path: Path) -> Any:
    bus = DconBusEmulator(tmp_path / "tty", [DconModule(1, [21.0, 22.0, 23.0, 24.0])])
    [group] = groups(bus, [{"name": "T1", "address": 1, "channel": 0}, {"name": "T3", "address": 1, "channel": 2}],
                     timeout_s=1.0)  # every hostile reply ends in CR: nothing waits for the timeout
    yield bus, group
    bus.close()


@settings(max_examples=examples(40), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(reply=st.binary(max_size=60).map(lambda b: b + b"\r"))
def test_whatever_the_line_carries_a_poll_is_readings_or_a_device_error(pty_bus: tuple[DconBusEmulator, Any],
                                                                     reply: bytes) -> None:
    bus, group = pty_bus

    async def body() -> None:
        bus.reply = None
        await group.open()
        bus.reply = reply  # the module's answers replaced by hostile bytes
        try:
            readings = await group.read()
        except DeviceError as error:
            assert bus.port in str(error)
        else:  # what came parsed: every channel is a number or a fault naming its channel
            for reading in readings.values():
                assert (reading.state is State.OK) == math.isfinite(reading.value)
                assert reading.state is State.OK or "channel" in reading.reason
        finally:
            await group.close()

    run(body)


def test_a_position_role_is_refused_for_a_thermocouple_module() -> None:
    with pytest.raises(ValueError, match="role"):
        DconSensorConfig.model_validate({"name": "T1", "kind": "dcon", "hub": "h", "address": 1, "channel": 0,
                                         "role": "position"})


def test_the_bus_port_closes_when_its_last_module_closes_even_after_failed_opens(tmp_path: Path) -> None:
    bus = DconBusEmulator(tmp_path / "tty", [DconModule(1, [21.0] * 4), DconModule(2, [22.0] * 4)])
    first, second = groups(bus, [{"name": "A", "address": 1, "channel": 0}, {"name": "B", "address": 2, "channel": 0}])

    async def body() -> None:
        bus.unplug()
        for _ in range(2):
            with pytest.raises(DeviceError, match="cannot open"):
                await first.open()
            await first.close()
        bus.replug()
        await first.open()
        await second.open()
        await first.close()
        assert (await second.read())["B"].value == 22.0  # the other module keeps the shared port
        await second.close()
        assert not first.bus.is_open  # the last one out closed it

    try:
        run(body)
    finally:
        bus.close()
