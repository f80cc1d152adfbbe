"""Device emulators for testing driver plugins, nanodrift's own and a lab's, against real interfaces.

Installed with nanodrift (it needs only pymodbus and pyserial, which nanodrift depends on), so a lab
that writes a plugin for its own instrument tests it the way nanodrift tests its plugins: the
plugin opens a real socket or a real serial port, and the test looks at what the device received.

- :mod:`nanodrift.drivers.testing.modbus_server`: :class:`ModbusTestServer` (pymodbus' own TCP server on
  127.0.0.1, or RTU on a serial port) serving :class:`ModbusTestDevice` register maps, which record
  every request and can be told to fail (exception codes, refused or slow writes);
- :mod:`nanodrift.drivers.testing.pty_devices`: instruments on a pty behind a stable link, which can be
  unplugged and plugged back: :class:`FakeInterferometer` (``P <nm> nm`` lines, queried or streamed),
  :class:`FakeGcsController` (a PI controller speaking GCS), and :class:`PtyDevice` to write another;
- :mod:`nanodrift.drivers.testing.ids_emulator`: :class:`IdsEmulator`, an attocube IDS3010 answering its
  JSON-RPC 2.0 API on TCP 127.0.0.1 (axes in pm, signal contrast, a measurement that can be stopped);
- :mod:`nanodrift.drivers.testing.dcon_emulator`: :class:`DconBusEmulator`, DCON thermocouple modules
  (:class:`DconModule`, 4 or 8 channels, open thermocouples, checksums) on an RS-485 bus emulated by a pty,
  or behind a TCP gateway (:class:`DconTcpGateway`);
- :mod:`nanodrift.drivers.testing.pi_gcs_emulator`: :class:`PiGcsEmulator`, a PI piezo controller in GCS 2.0
  that enforces the servo state, the travel and voltage ranges and keeps an error register, served over
  TCP on 127.0.0.1 (:class:`PiGcsTcpServer`) or on a pty (:class:`PiGcsPtyDevice`), logging every line;
- :mod:`nanodrift.drivers.testing.protocol`: :func:`expected_protocol`, a pty device that expects an exact
  conversation (PyMeasure's ``expected_protocol``) and fails on anything else.

A lab's plugin (registered in the ``nanodrift.drivers`` entry-point group) tested against them::

    import asyncio
    from nanodrift.drivers.base import DriverContext
    from nanodrift.drivers.registry import load_plugin
    from nanodrift.drivers.testing import FakeGcsController

    def test_my_controller_gets_the_voltage(tmp_path):
        controller = FakeGcsController(tmp_path / "ttyPI")
        plugin = load_plugin("mylab")                      # found through its entry point
        config = plugin.actuator_model.model_validate({"kind": "mylab", "port": controller.port})
        actuator = plugin.create_actuator(config, DriverContext())

        async def body():
            await actuator.open()
            await actuator.command(100.0, 2.0)
            await actuator.close()

        try:
            asyncio.run(asyncio.wait_for(body(), 10))
            assert controller.voltage == actuator.sent_voltage(2.0)
        finally:
            controller.close()

The checks every plugin must pass are the contract kit, :mod:`nanodrift.drivers.testing.contract`
(pytest test classes and the rigs a lab subclasses); it needs pytest, so this package does not import
it: import it by its full name. nanodrift's contract tests (``tests/drivers/test_sensor_contract.py``,
``tests/drivers/test_actuator_contract.py``) run its own plugins and a lab's through it. Nothing in
nanodrift itself imports this package (``tests/test_architecture.py`` enforces it).
"""

from nanodrift.drivers.local_port import free_port
from nanodrift.drivers.testing.dcon_emulator import DconBusEmulator, DconModule, DconTcpGateway
from nanodrift.drivers.testing.ids_emulator import IdsAxis, IdsEmulator
from nanodrift.drivers.testing.modbus_server import (
    FC_READ_HOLDING,
    FC_READ_INPUT,
    ModbusTestDevice,
    ModbusTestServer,
    PtyNullModem,
    crc16_modbus,
    device_registers,
    tcp_context,
)
from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice, PiGcsTcpServer
from nanodrift.drivers.testing.protocol import ScriptedDevice, expected_protocol
from nanodrift.drivers.testing.pty_devices import FakeGcsController, FakeInterferometer, PtyDevice

__all__ = [
    "FC_READ_HOLDING",
    "FC_READ_INPUT",
    "DconBusEmulator",
    "DconModule",
    "DconTcpGateway",
    "EmulatedAxis",
    "FakeGcsController",
    "FakeInterferometer",
    "IdsAxis",
    "IdsEmulator",
    "ModbusTestDevice",
    "ModbusTestServer",
    "PiGcsEmulator",
    "PiGcsPtyDevice",
    "PiGcsTcpServer",
    "PtyDevice",
    "PtyNullModem",
    "ScriptedDevice",
    "crc16_modbus",
    "device_registers",
    "expected_protocol",
    "free_port",
    "tcp_context",
]
