"""The sensor-group contract (``nanodrift.drivers.base.SensorGroup``), one set of checks run against every plugin.

In the style of python-can's ``test/back2back_test.py``: one test class, and a fixture that gives it
each backend in turn, behind a real interface:

- ``simulated``: the simulated cell (its injected faults stand for the device's trouble);
- ``modbus``: two thermocouple channels on pymodbus' TCP server on 127.0.0.1 (``nanodrift.drivers.testing``);
- ``serial_line``: an interferometer on a pty, queried with ``POS?`` (``nanodrift.drivers.testing``);
- ``labbox``: a lab's own plugin (``tests/helpers/lab_plugin.py``), found through a real entry point.

Every group is built the daemon's way: the plugin found by name through the ``nanodrift.drivers``
entry points, its configs validated by its own ``config_model``, ``create`` with a context whose
clock is :class:`OffsetClock`, a time base no plugin could stamp by accident (neither ``time.time``
nor ``time.monotonic``).

The contract: ``open``/``read``/``close``; ``read`` returns a reading for every name in ``names`` and
no other, stamped on ``context.clock`` during the read; ``ok`` readings carry the device's value
(finite, in the channel's unit); a channel-level problem on a working device is a ``fault`` reading
(NaN, with a reason) while the others stay ``ok``; a device that is gone raises :class:`DeviceError`
(never another exception) from ``read``, and from ``open`` while it stays gone; ``close`` is safe
twice and after a failed ``open``; close then open again recovers once the device is back.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable, Iterator
from pathlib import Path
from typing import Any, ClassVar

import pytest
from helpers import lab_plugin
from helpers.daemon_harness import SensorFile

from nanodrift.drivers.base import DeviceError, DriverContext, Reading, SensorGroup, State
from nanodrift.drivers.modbus.codec import encode
from nanodrift.drivers.registry import available, load_plugin
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.plugin import RESOURCE_KEY
from nanodrift.drivers.testing import FakeInterferometer, ModbusTestDevice, ModbusTestServer, tcp_context

T = 30.0  # a whole test's wall-clock bound


class OffsetClock:
    """Monotonic time 123456789 s ahead: neither the wall clock nor the raw monotonic clock."""

    OFFSET_S = 123_456_789.0

    def now(self) -> float:
        return time.monotonic() + self.OFFSET_S

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(max(0.0, seconds))


def run(body: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(body(), T))


# --- the backends ---------------------------------------------------------------------------------


class Rig:
    """One backend behind a real interface: what it builds, and how its device misbehaves."""

    kind: str
    names: tuple[str, ...]
    roles: ClassVar[dict[str, str]]
    units: ClassVar[dict[str, str]]
    #: whether ``open`` can fail (a simulated cell is always there)
    can_fail_open = True

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path
        self.clock = OffsetClock()

    def sensor_configs(self) -> list[dict[str, Any]]:
        raise NotImplementedError

    def context(self) -> DriverContext:
        return DriverContext(clock=self.clock)

    async def start(self) -> None: ...

    async def stop(self) -> None: ...

    def check_values(self, readings: dict[str, Reading]) -> None:
        """The ok readings carry what the device holds."""
        raise NotImplementedError

    async def fault_channel(self) -> str:
        """Make one channel report a problem while the device keeps answering; its name."""
        raise NotImplementedError

    async def gone(self) -> None:
        raise NotImplementedError

    async def back(self) -> None:
        raise NotImplementedError

    def group(self) -> SensorGroup:
        self.built_context = self.context()
        plugin = load_plugin(self.kind)  # through the entry point, as the daemon finds it
        configs = [plugin.config_model.model_validate(raw) for raw in self.sensor_configs()]
        [group] = plugin.create(configs, self.built_context)
        return group


class SimulatedRig(Rig):
    kind = "simulated"
    names = ("T1", "T2")
    roles: ClassVar[dict[str, str]] = {"T1": "temperature", "T2": "temperature"}
    units: ClassVar[dict[str, str]] = {"T1": "degC", "T2": "degC"}
    can_fail_open = False

    def sensor_configs(self) -> list[dict[str, Any]]:
        return [{"name": name, "kind": "simulated", "interval_s": 0.5} for name in self.names]

    @property
    def cell(self) -> SimulatedCell:
        cell = self.built_context.resources.get(RESOURCE_KEY, SimulatedCell)
        assert cell is not None
        return cell

    def check_values(self, readings: dict[str, Reading]) -> None:
        for reading in readings.values():
            assert 15.0 < reading.value < 35.0, reading  # a room's thermocouples, not a raw count

    async def fault_channel(self) -> str:
        self.cell.inject_fault("T2", self.cell.sim_time() - 1.0, 1e12, "fault")
        return "T2"

    async def gone(self) -> None:
        for name in self.names:
            self.cell.inject_fault(name, self.cell.sim_time() - 1.0, 1e12, "device_error")

    async def back(self) -> None:
        self.cell.faults.clear()


class ModbusRig(Rig):
    kind = "modbus"
    names = ("T1", "T2")
    roles: ClassVar[dict[str, str]] = {"T1": "temperature", "T2": "temperature"}
    units: ClassVar[dict[str, str]] = {"T1": "degC", "T2": "degC"}

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.device = ModbusTestDevice(1, input_ranges=((0, 8),))
        self.server = ModbusTestServer([self.device])

    def sensor_configs(self) -> list[dict[str, Any]]:
        return [{"name": name, "kind": "modbus", "hub": "adam", "address": index, "input_type": "input",
                 "scale": 0.01, "nan_value": -32768, "timeout_s": 1.0} for index, name in enumerate(self.names)]

    def context(self) -> DriverContext:
        return DriverContext(clock=self.clock, hubs=tcp_context(self.server.port, timeout_s=0.3).hubs)

    async def start(self) -> None:
        await self.server.start()
        await self.server.set_registers(1, 0, [2150, encode(-1234, "int16")[0]], "input")

    async def stop(self) -> None:
        await self.server.stop()

    def check_values(self, readings: dict[str, Reading]) -> None:
        assert readings["T1"].value == pytest.approx(21.5)
        assert readings["T2"].value == pytest.approx(-12.34)

    async def fault_channel(self) -> str:
        await self.server.set_registers(1, 1, [encode(-32768, "int16")[0]], "input")  # the burnout code
        return "T2"

    async def gone(self) -> None:
        await self.server.stop()

    async def back(self) -> None:
        await self.server.start()


class SerialRig(Rig):
    kind = "serial_line"
    names = ("ifm",)
    roles: ClassVar[dict[str, str]] = {"ifm": "position"}
    units: ClassVar[dict[str, str]] = {"ifm": "um"}

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.device = FakeInterferometer(tmp_path / "ttyIFM")

    def sensor_configs(self) -> list[dict[str, Any]]:
        return [{"name": "ifm", "role": "position", "kind": "serial_line", "port": self.device.port,
                 "baudrate": 115200, "query": "POS?\r", "pattern": "P (?P<value>[-+0-9.]+) nm", "scale": 0.001,
                 "interval_s": 0.1, "timeout_s": 0.3}]

    async def stop(self) -> None:
        self.device.close()

    def check_values(self, readings: dict[str, Reading]) -> None:
        assert readings["ifm"].value == pytest.approx(123.4567)

    async def fault_channel(self) -> str:
        self.device.reply = b"ERR 17 beam lost\r\n"
        return "ifm"

    async def gone(self) -> None:
        self.device.unplug()

    async def back(self) -> None:
        self.device.replug()


class LabRig(Rig):
    """A lab's own plugin: its ``file`` sensors read a JSON file."""

    kind = "labbox"
    names = ("T1", "T2")
    roles: ClassVar[dict[str, str]] = {"T1": "temperature", "T2": "position"}
    units: ClassVar[dict[str, str]] = {"T1": "degC", "T2": "um"}

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.path = tmp_path / "sensors.json"
        self.file = SensorFile(self.path, {"T1": 21.5, "T2": 240.25})

    def sensor_configs(self) -> list[dict[str, Any]]:
        return [{"name": name, "role": self.roles[name], "kind": "labbox", "path": str(self.path)}
                for name in self.names]

    def check_values(self, readings: dict[str, Reading]) -> None:
        assert readings["T1"].value == 21.5 and readings["T2"].value == 240.25

    async def fault_channel(self) -> str:
        self.file.write(fault={"T2": "beam lost"})
        return "T2"

    async def gone(self) -> None:
        self.path.unlink()

    async def back(self) -> None:
        self.file.write()


RIGS: dict[str, type[Rig]] = {"simulated": SimulatedRig, "modbus": ModbusRig, "serial_line": SerialRig,
                              "labbox": LabRig}
FAILING = [name for name, rig in RIGS.items() if rig.can_fail_open]


@pytest.fixture(scope="module", autouse=True)
def lab_package(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The lab's package installed for this module (an entry point the registry finds)."""
    with lab_plugin.installed(tmp_path_factory.mktemp("lab")):
        yield


@pytest.fixture(params=list(RIGS))
def rig(request: pytest.FixtureRequest, tmp_path: Path) -> Rig:
    return RIGS[request.param](tmp_path)


@pytest.fixture(params=FAILING)
def failing_rig(request: pytest.FixtureRequest, tmp_path: Path) -> Rig:
    return RIGS[request.param](tmp_path)


async def read(group: SensorGroup) -> dict[str, Reading]:
    """One poll, bounded as the daemon bounds it (``timeout_s``) plus a margin."""
    return await asyncio.wait_for(group.read(), group.timeout_s + 2.0)


async def read_stamped(rig: Rig, group: SensorGroup) -> dict[str, Reading]:
    """A poll whose readings were all stamped on the rig's clock while it ran."""
    before = rig.clock.now()
    readings = await read(group)
    after = rig.clock.now()
    assert set(readings) == set(group.names), readings  # one per name, nothing else
    for name, reading in readings.items():
        assert before <= reading.t <= after, (name, reading.t, before, after)
        assert reading.unit == rig.units[name], (name, reading)
    return readings


def assert_all_ok(rig: Rig, readings: dict[str, Reading]) -> None:
    for name, reading in readings.items():
        assert reading.state is State.OK and reading.reason == "", (name, reading)
        assert math.isfinite(reading.value), (name, reading)
    rig.check_values(readings)


class TestSensorContract:
    def test_open_read_close_a_reading_per_name_on_the_context_clock(self, rig: Rig) -> None:
        async def body() -> None:
            await rig.start()
            try:
                group = rig.group()
                assert group.names == rig.names
                assert dict(group.roles) == rig.roles
                assert group.interval_s > 0 and group.timeout_s > 0
                await group.open()
                for _ in range(3):
                    assert_all_ok(rig, await read_stamped(rig, group))
                await group.close()
            finally:
                await rig.stop()

        run(body)

    def test_close_is_safe_twice_and_the_group_reopens(self, rig: Rig) -> None:
        async def body() -> None:
            await rig.start()
            try:
                group = rig.group()
                await group.open()
                await read(group)
                await group.close()
                await group.close()
                await group.open()  # the daemon reopens a closed group
                assert_all_ok(rig, await read_stamped(rig, group))
                await group.close()
            finally:
                await rig.stop()

        run(body)

    def test_a_channel_problem_is_a_fault_reading_and_the_others_stay_ok(self, rig: Rig) -> None:
        async def body() -> None:
            await rig.start()
            try:
                group = rig.group()
                await group.open()
                assert_all_ok(rig, await read_stamped(rig, group))
                faulted = await rig.fault_channel()
                readings = await read_stamped(rig, group)
                bad = readings[faulted]
                assert bad.state is State.FAULT and math.isnan(bad.value) and bad.reason, bad
                for name, reading in readings.items():
                    if name != faulted:
                        assert reading.state is State.OK and math.isfinite(reading.value), (name, reading)
                await group.close()
            finally:
                await rig.stop()

        run(body)

    def test_a_device_that_is_gone_raises_device_error_and_recovers_after_reopening(self, rig: Rig) -> None:
        async def body() -> None:
            await rig.start()
            try:
                group = rig.group()
                await group.open()
                assert_all_ok(rig, await read_stamped(rig, group))
                await rig.gone()
                for _ in range(2):  # every poll while it is gone, not only the first
                    with pytest.raises(DeviceError):
                        await read(group)
                await group.close()  # what the daemon does on DeviceError: close, back off, open
                await rig.back()
                await group.open()
                assert_all_ok(rig, await read_stamped(rig, group))
                await group.close()
            finally:
                await rig.stop()

        run(body)

    def test_close_is_safe_after_a_failed_open(self, failing_rig: Rig) -> None:
        rig = failing_rig

        async def body() -> None:
            await rig.start()
            try:
                group = rig.group()
                await rig.gone()
                with pytest.raises(DeviceError):
                    await asyncio.wait_for(group.open(), group.timeout_s + 5.0)
                await group.close()
                await group.close()
                with pytest.raises(DeviceError):  # calling open again retries, and fails again
                    await asyncio.wait_for(group.open(), group.timeout_s + 5.0)
                await group.close()
                await rig.back()
                await group.open()
                assert_all_ok(rig, await read_stamped(rig, group))
                await group.close()
            finally:
                await rig.stop()

        run(body)


def test_every_installed_plugin_with_sensors_is_run_through_the_contract() -> None:
    """A new plugin in nanodrift's entry points must get a rig here (the lab's is installed by the fixture)."""
    assert set(available()) == set(RIGS)
