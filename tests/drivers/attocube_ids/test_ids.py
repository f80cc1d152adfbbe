"""The ``attocube_ids`` plugin against an IDS3010 emulated behind real TCP on 127.0.0.1 (JSON-RPC 2.0)."""

from __future__ import annotations

import asyncio
import json
import math
from collections.abc import Awaitable, Callable, Iterator
from typing import Any

import pytest
from helpers.budget import examples
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from nanodrift.drivers.attocube_ids.config import IdsSensorConfig
from nanodrift.drivers.attocube_ids.group import IdsGroup
from nanodrift.drivers.attocube_ids.rpc import IdsRpc
from nanodrift.drivers.base import POSITION_FROZEN_AFTER_S, DeviceError, DriverContext, State
from nanodrift.drivers.registry import load_plugin
from nanodrift.drivers.testing import IdsEmulator


@pytest.fixture
def ids() -> Iterator[IdsEmulator]:
    with IdsEmulator() as device:
        yield device


def group_of(device: IdsEmulator, axes: dict[str, int], **keys: Any) -> IdsGroup:
    plugin = load_plugin("attocube_ids")
    configs = [plugin.config_model.model_validate({"name": name, "kind": "attocube_ids", "host": "127.0.0.1",
                                                   "port": device.port, "ids_axis": axis, "timeout_s": 0.5, **keys})
               for name, axis in axes.items()]
    [group] = plugin.create(configs, DriverContext())
    assert isinstance(group, IdsGroup)
    return group


def run(body: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(body(), 20))


def test_displacement_in_pm_is_read_as_um_with_the_documented_calls(ids: IdsEmulator) -> None:
    ids.axes[2].displacement_pm = 240_000_123.0
    group = group_of(ids, {"ifm_x": 0, "ifm_z": 2})

    async def body() -> None:
        await group.open()
        ids.requests.clear()
        readings = await group.read()
        await group.close()
        assert readings["ifm_x"].value == pytest.approx(123.456789, abs=1e-9)
        assert readings["ifm_z"].value == pytest.approx(240.000123, abs=1e-9)
        assert {r.unit for r in readings.values()} == {"um"}
        # what the device was asked: the state once, then each configured axis by its own number
        assert ids.requests == [
            ("com.attocube.ids.displacement.getMeasurementEnabled", []),
            ("com.attocube.ids.displacement.getAxisSignalQuality", [0]),
            ("com.attocube.ids.displacement.getAxisDisplacement", [0]),
            ("com.attocube.ids.displacement.getAxisSignalQuality", [2]),
            ("com.attocube.ids.displacement.getAxisDisplacement", [2]),
        ]
        assert ids.connections == 1  # one connection for the device's axes

    run(body)


def test_invert_and_offset_put_the_displacement_in_the_cells_frame(ids: IdsEmulator) -> None:
    ids.axes[0].displacement_pm = -240_000_000.0  # the stage moved 240 um towards the head
    group = group_of(ids, {"x": 0}, invert=True, offset_um=10.0)

    async def body() -> None:
        await group.open()
        reading = (await group.read())["x"]
        await group.close()
        assert reading.value == pytest.approx(250.0, abs=1e-9)

    run(body)


def test_a_json_rpc_error_keeps_the_connection_a_garbled_answer_drops_it(ids: IdsEmulator) -> None:
    group = group_of(ids, {"a": 0})

    async def body() -> None:
        await group.open()
        with pytest.raises(DeviceError, match="JSON-RPC error -32601"):
            await group.rpc.call("com.attocube.ids.nonsense")
        assert group.rpc.connected and (await group.read())["a"].state is State.OK
        ids.reply = b"garbage\n"
        with pytest.raises(DeviceError, match="is not JSON"):
            await group.read()
        assert not group.rpc.connected
        await group.close()
        assert ids.connections == 1  # the error answer did not cost a reconnection

    run(body)


def test_a_stopped_measurement_faults_every_axis_naming_it_and_the_mode(ids: IdsEmulator) -> None:
    group = group_of(ids, {"ifm_x": 0, "ifm_y": 1})

    async def body() -> None:
        await group.open()
        ids.measurement_running = False
        ids.system_error = 23
        ids.error_texts[23] = "beam lost during initialisation"
        readings = await group.read()
        ids.measurement_running = True
        again = await group.read()
        await group.close()
        for name, axis in (("ifm_x", 0), ("ifm_y", 1)):
            reading = readings[name]
            assert reading.state is State.FAULT and math.isnan(reading.value)
            assert f"axis {axis}" in reading.reason and "'system idle'" in reading.reason
            assert "system error 23: beam lost during initialisation" in reading.reason
            assert again[name].state is State.OK

    run(body)


def test_a_device_warning_faults_that_axis_with_the_devices_text(ids: IdsEmulator) -> None:
    ids.axes[1].warning = 7
    ids.error_texts[7] = "signal too low"
    group = group_of(ids, {"ifm_x": 0, "ifm_y": 1})

    async def body() -> None:
        await group.open()
        readings = await group.read()
        await group.close()
        assert readings["ifm_x"].state is State.OK
        assert readings["ifm_y"].state is State.FAULT
        assert "axis 1" in readings["ifm_y"].reason and "warning 7" in readings["ifm_y"].reason
        assert "signal too low" in readings["ifm_y"].reason

    run(body)


def test_a_low_contrast_is_a_bad_signal_only_below_the_operators_threshold(ids: IdsEmulator) -> None:
    ids.axes[0].contrast_permille = 250
    strict, lenient = group_of(ids, {"a": 0}, min_contrast_permille=300), group_of(ids, {"a": 0})

    async def body() -> None:
        for group in (strict, lenient):
            await group.open()
        bad, fine = (await strict.read())["a"], (await lenient.read())["a"]
        for group in (strict, lenient):
            await group.close()
        assert bad.state is State.FAULT and "contrast 250 permille" in bad.reason and "axis 0" in bad.reason
        assert fine.state is State.OK

    run(body)


@pytest.mark.parametrize(("misbehave", "expected"), [
    (lambda d: setattr(d, "silent", True), "no answer within 0.5 s"),
    (lambda d: setattr(d, "reply", b"hello\n"), "is not JSON"),
    (lambda d: setattr(d, "reply", b'{"jsonrpc": "2.0", "result": [0, true], "id": 999}\n'), "with id"),
    (lambda d: setattr(d, "reply", b'{"jsonrpc": "2.0", "error": {"code": -32601, "message": "Method not found"}, '
                                   b'"id": 2}\n'), "JSON-RPC error -32601"),
    (lambda d: d.stop(), "connection"),
])
def test_silence_garbage_and_a_lost_link_are_device_errors_naming_the_device(ids: IdsEmulator, misbehave: Any,
                                                                              expected: str) -> None:
    group = group_of(ids, {"a": 0})

    async def body() -> None:
        await group.open()
        misbehave(ids)
        with pytest.raises(DeviceError) as caught:
            await group.read()
        assert f"127.0.0.1:{ids.port}" in str(caught.value) and expected in str(caught.value)
        await group.close()

    run(body)


def test_nothing_listening_is_a_device_error_at_open() -> None:
    device = IdsEmulator()
    group = group_of(device, {"a": 0})
    device.stop()

    async def body() -> None:
        with pytest.raises(DeviceError, match=f"127.0.0.1:{device.port}: cannot connect"):
            await group.open()
        await group.close()

    run(body)


@given(st.binary(max_size=200))
def test_any_answer_line_is_a_result_or_a_device_error(line: bytes) -> None:
    try:
        result = IdsRpc._result(line, 1, "attocube IDS x")
    except DeviceError as error:
        assert "attocube IDS x" in str(error)
    else:
        assert isinstance(result, list) and result


# --- config ---------------------------------------------------------------------------------------


def test_role_is_position_by_default_with_the_position_defaults() -> None:
    config = IdsSensorConfig.model_validate({"name": "ifm", "kind": "attocube_ids", "host": "10.0.0.2",
                                             "ids_axis": 0})
    assert (config.role, config.port, config.frozen_after_s) == ("position", 9090, POSITION_FROZEN_AFTER_S)


@pytest.mark.parametrize(("key", "value"), [("ids_axis", 3), ("role", "temperature"), ("port", 0),
                                            ("min_contrast_permille", 1001), ("ids_axes", 1)])
def test_bad_keys_are_refused_naming_them(key: str, value: Any) -> None:
    raw = {"name": "ifm", "kind": "attocube_ids", "host": "10.0.0.2", "ids_axis": 0, key: value}
    with pytest.raises(ValidationError, match=key):
        IdsSensorConfig.model_validate(raw)


def test_one_device_axis_read_twice_is_a_config_problem() -> None:
    plugin = load_plugin("attocube_ids")
    configs = [IdsSensorConfig.model_validate({"name": n, "kind": "attocube_ids", "host": "10.0.0.2", "ids_axis": 1})
               for n in ("a", "b")]
    [problem] = plugin.config_problems(list(enumerate(configs)), None)
    assert problem.startswith("sensors[1] (b).ids_axis:") and "already read by sensors[0] (a)" in problem


@settings(max_examples=examples(40), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(reply=st.one_of(st.binary(max_size=80), st.builds(
    lambda result: json.dumps({"jsonrpc": "2.0", "result": result, "id": 2}).encode(),
    st.lists(st.one_of(st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=5)), max_size=4),
)).map(lambda b: b + b"\n"))
def test_whatever_comes_back_over_tcp_a_poll_is_readings_or_a_device_error(ids: IdsEmulator, reply: bytes) -> None:
    group = group_of(ids, {"a": 0})

    async def body() -> None:
        ids.reply = None
        await group.open()
        ids.reply = reply  # every answer replaced by hostile bytes
        try:
            readings = await group.read()
        except DeviceError as error:
            assert f"127.0.0.1:{ids.port}" in str(error)
        else:
            reading = readings["a"]
            assert (reading.state is State.OK) == math.isfinite(reading.value)
            assert reading.state is State.OK or "axis 0" in reading.reason
        finally:
            await group.close()

    run(body)
