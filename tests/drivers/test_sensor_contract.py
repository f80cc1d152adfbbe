"""The sensor-group contract (``nanodrift.drivers.testing.contract``) run against every plugin, exactly as a lab
runs it against its own plugin: a rig per plugin, a ``Test...`` subclass per rig, each behind a real interface:

- ``simulated``: the simulated cell (its injected faults stand for the device's trouble);
- ``modbus``: two thermocouple channels on pymodbus' TCP server on 127.0.0.1 (``nanodrift.drivers.testing``);
- ``serial_line``: an interferometer on a pty, queried with ``POS?`` (``nanodrift.drivers.testing``);
- ``attocube_ids``: two axes of an IDS3010 emulated behind real TCP on 127.0.0.1 (JSON-RPC 2.0);
- ``dcon``: three channels of a 4-channel DCON thermocouple module on a pty (``#AA``);
- ``labbox``: a lab's own plugin (``tests/helpers/lab_plugin.py``), found through a real entry point.

Every group is built the daemon's way: the plugin found by name through the ``nanodrift.drivers``
entry points, its configs validated by its own ``config_model``, ``create`` with a context whose
clock is the kit's ``OffsetClock``, a time base no plugin could stamp by accident.
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any, ClassVar

import pytest
from helpers import lab_plugin
from helpers.daemon_harness import SensorFile
from pydantic import ValidationError

from nanodrift.drivers.base import DriverContext, Reading
from nanodrift.drivers.dcon.config import DconHubConfig
from nanodrift.drivers.modbus.codec import encode
from nanodrift.drivers.registry import available, load_plugin
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.plugin import RESOURCE_KEY
from nanodrift.drivers.testing import (
    DconBusEmulator,
    DconModule,
    FakeInterferometer,
    IdsEmulator,
    ModbusTestDevice,
    ModbusTestServer,
    tcp_context,
)
from nanodrift.drivers.testing.contract import SensorContract, SensorRig

# --- the rigs -------------------------------------------------------------------------------------


class SimulatedRig(SensorRig):
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


class ModbusRig(SensorRig):
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


class SerialRig(SensorRig):
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


class IdsRig(SensorRig):
    """Axes 0 and 1 of one IDS: one connection, one group."""

    kind = "attocube_ids"
    names = ("ifm_x", "ifm_y")
    roles: ClassVar[dict[str, str]] = {"ifm_x": "position", "ifm_y": "position"}
    units: ClassVar[dict[str, str]] = {"ifm_x": "um", "ifm_y": "um"}

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.device = IdsEmulator()

    def sensor_configs(self) -> list[dict[str, Any]]:
        return [{"name": name, "kind": "attocube_ids", "host": "127.0.0.1", "port": self.device.port,
                 "ids_axis": axis, "min_contrast_permille": 300, "interval_s": 0.1, "timeout_s": 0.5}
                for axis, name in enumerate(self.names)]

    async def stop(self) -> None:
        self.device.stop()

    def check_values(self, readings: dict[str, Reading]) -> None:
        assert readings["ifm_x"].value == pytest.approx(123.456789, abs=1e-9)  # pm -> um
        assert readings["ifm_y"].value == pytest.approx(-2.5, abs=1e-9)

    async def fault_channel(self) -> str:
        self.device.axes[1].contrast_permille = 40  # the beam of axis 1 is lost
        return "ifm_y"

    async def gone(self) -> None:
        self.device.stop()

    async def back(self) -> None:
        self.device.start()


class DconRig(SensorRig):
    """Channels 0, 1 and 3 of a 4-channel module at address 01: one #01 per poll."""

    kind = "dcon"
    names = ("T1", "T2", "T4")
    roles: ClassVar[dict[str, str]] = dict.fromkeys(names, "temperature")
    units: ClassVar[dict[str, str]] = dict.fromkeys(names, "degC")

    def __init__(self, tmp_path: Path) -> None:
        super().__init__(tmp_path)
        self.device = DconBusEmulator(tmp_path / "ttyRS485", [DconModule(1, [21.5, -3.25, 22.0, 23.75])])

    def sensor_configs(self) -> list[dict[str, Any]]:
        return [{"name": name, "kind": "dcon", "hub": "rs485", "address": 1, "channel": channel,
                 "interval_s": 0.2, "timeout_s": 1.0} for name, channel in zip(self.names, (0, 1, 3), strict=True)]

    def context(self) -> DriverContext:
        hub = DconHubConfig(name="rs485", type="serial", port=self.device.port, timeout_s=0.3)
        return DriverContext(clock=self.clock, hubs={"rs485": hub})

    async def stop(self) -> None:
        self.device.close()

    def check_values(self, readings: dict[str, Reading]) -> None:
        assert readings["T1"].value == pytest.approx(21.5)
        assert readings["T2"].value == pytest.approx(-3.25)
        assert readings["T4"].value == pytest.approx(23.75)

    async def fault_channel(self) -> str:
        self.device.modules[1].open_channels.add(1)  # an open thermocouple reads +9999
        return "T2"

    async def gone(self) -> None:
        self.device.unplug()

    async def back(self) -> None:
        self.device.replug()


class LabRig(SensorRig):
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


RIGS: dict[str, type[SensorRig]] = {"simulated": SimulatedRig, "modbus": ModbusRig, "serial_line": SerialRig,
                                    "attocube_ids": IdsRig, "dcon": DconRig, "labbox": LabRig}


@pytest.fixture(scope="module", autouse=True)
def lab_package(tmp_path_factory: pytest.TempPathFactory) -> Iterator[None]:
    """The lab's package installed for this module (an entry point the registry finds)."""
    with lab_plugin.installed(tmp_path_factory.mktemp("lab")):
        yield


# --- the contract, per rig ------------------------------------------------------------------------


class TestSimulated(SensorContract):
    rig = SimulatedRig


class TestModbus(SensorContract):
    rig = ModbusRig


class TestSerialLine(SensorContract):
    rig = SerialRig


class TestAttocubeIds(SensorContract):
    rig = IdsRig


class TestDcon(SensorContract):
    rig = DconRig


class TestLabBox(SensorContract):
    rig = LabRig


#: plugins that are an output only: their ``[[sensors]]`` entry is refused, saying so (checked below)
OUTPUT_ONLY = {"pi_gcs"}


def test_an_output_only_plugin_refuses_a_sensor_entry_naming_what_it_is() -> None:
    for kind in OUTPUT_ONLY:
        plugin = load_plugin(kind)
        assert plugin.actuator_model is not None
        with pytest.raises(ValidationError, match=f"{kind} is an output"):
            plugin.config_model.model_validate({"name": "p", "kind": kind, "role": "position"})


def test_every_installed_plugin_with_sensors_is_run_through_the_contract() -> None:
    """A new plugin in nanodrift's entry points must get a rig and a class here (the lab's is installed by
    the fixture)."""
    assert set(available()) - OUTPUT_ONLY == set(RIGS)
    tested = {cls.rig.kind for cls in SensorContract.__subclasses__() if cls.__module__ == __name__}
    assert tested == set(RIGS)
