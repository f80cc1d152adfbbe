"""A cell for hardware-in-the-loop tests: the simulated cell's physics behind real interfaces.

- a Modbus TCP module on 127.0.0.1 (pymodbus' server, in its own thread and event loop): input
  registers 0..3 hold T1..T4 (int16, 0.01 degC) measured at each read; holding register 10 is an
  analog output (int16, 1 mV per count) wired to the amplifier: a write moves the stage;
- an interferometer on a pty answering ``POS?\\r`` with ``P <nm> nm`` at the moment of the query;
- optionally a PI controller on a pty (GCS ``SVA``: the generic ``serial_line`` path's ``FakeGcsController``, and
  the ``pi_gcs`` plugin's emulator, servo on at power-up) and a Zenoh output node applying ``command``.

The physics runs on a :class:`~nanodrift.drivers.simulated.clock.ScaledClock` (``speed`` simulated seconds per wall
second), so a shortened calibration sees hours of room temperature. ``amplifier_connected = False``
is a cable pulled out: the output still takes its value, the stage no longer moves.
"""

from __future__ import annotations

import asyncio
import json
import threading
from dataclasses import replace
from pathlib import Path
from typing import Any

import zenoh

from helpers.modbus_helpers import FC_READ_INPUT, ModbusTestDevice, ModbusTestServer, free_port
from helpers.serial_helpers import FakeGcsController, FakeInterferometer
from nanodrift.drivers.modbus.codec import decode, encode
from nanodrift.drivers.simulated.cell import SimulatedCell
from nanodrift.drivers.simulated.clock import ScaledClock
from nanodrift.drivers.simulated.config import SimulationConfig
from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice

VOLTS_PER_UM = 0.02  # the amplifier's gain, as [actuator] volts_per_um says
AO_ADDRESS = 10
AO_VOLTS_PER_COUNT = 0.001
TC_DEGC_PER_COUNT = 0.01
THERMOCOUPLES = ("T1", "T2", "T3", "T4")
#: a controller, module or interferometer emulated by a thread of the pytest process answers late on a loaded
#: machine (0.5 s was seen to expire at a load of 9, and a module's connect): it only bounds how long a dead device
#: takes to be called dead
CONTROLLER_TIMEOUT_S = 2.0


class PhysicsInterferometer(FakeInterferometer):
    """Answers each ``POS?`` with the emulated stage's position at that moment."""

    def __init__(self, link: Path, emulated: EmulatedCell) -> None:
        self.emulated = emulated  # before the serving thread starts
        super().__init__(link)

    def line(self) -> bytes:
        if self.reply is not None:
            return self.reply
        return f"P {self.emulated.position_um() * 1000.0:.1f} nm".encode() + self.eol


class EmulatedCell:
    def __init__(self, tmp_path: Path, *, speed: float = 1000.0, scenario: str = "train", seed: int = 0) -> None:
        self.clock = ScaledClock(speed)
        self.cell = SimulatedCell(SimulationConfig(scenario=scenario, seed=seed).physics(), self.clock)
        self.lock = threading.Lock()  # the cell is reached from the Modbus, pty and Zenoh threads
        self.amplifier_connected = True
        self.voltages: list[float] = []  # every voltage the amplifier received, in order
        self.device = ModbusTestDevice(1, input_ranges=((0, 8),), holding_ranges=((0, 32),))
        self.device.on_read = self._measure
        self.device.on_write = self._output
        self.modbus = ModbusTestServer([self.device])
        self.interferometer = PhysicsInterferometer(tmp_path / "ttyIFM", self)
        self.controller = FakeGcsController(tmp_path / "ttyPI")
        self.controller.on_voltage = self.apply_voltage
        self.pi_gcs = PiGcsEmulator(axes={"1": EmulatedAxis(servo=True)},
                                    on_sva=lambda _axis, volts: self.apply_voltage(volts))
        self.pi_gcs_port = PiGcsPtyDevice(tmp_path / "ttyPIGCS", self.pi_gcs)
        self._loop: asyncio.AbstractEventLoop | None = None
        self._stop: asyncio.Event | None = None
        self._thread: threading.Thread | None = None
        self._node: zenoh.Session | None = None
        self.node_port: int | None = None

    # -- the physics --------------------------------------------------------------------------------

    def apply_voltage(self, volts: float) -> None:
        """What the amplifier does with the voltage on its input."""
        with self.lock:
            self.voltages.append(volts)
            if self.amplifier_connected:
                self.cell.command("x", volts / VOLTS_PER_UM)

    def position_um(self) -> float:
        with self.lock:
            return self.cell.read(["interferometer"])["interferometer"].value

    def true_position_um(self) -> float:
        with self.lock:
            return self.cell.true_positions()["x"]

    def uncompensated_um(self, target_um: float) -> float:
        """Where the stage would be now had it been commanded ``target_um`` as it is (no model)."""
        with self.lock:
            state = replace(self.cell.states["x"], q=target_um, landing_um=0.0)
            return self.cell.physics.attained_now(self.cell.sim_time(), {"x": state})["x"]

    def _measure(self, function_code: int, start: int, registers: list[int]) -> None:
        if function_code != FC_READ_INPUT:
            return
        with self.lock:
            readings = self.cell.read(THERMOCOUPLES)
        for index, name in enumerate(THERMOCOUPLES):
            registers[index - start] = encode(round(readings[name].value / TC_DEGC_PER_COUNT), "int16")[0]

    def _output(self, address: int, values: list[int]) -> None:
        if address == AO_ADDRESS:
            self.apply_voltage(float(decode(values[:1], "int16")) * AO_VOLTS_PER_COUNT)

    # -- the interfaces -----------------------------------------------------------------------------

    def start(self) -> EmulatedCell:
        ready = threading.Event()

        async def serve() -> None:
            self._loop = asyncio.get_running_loop()
            self._stop = asyncio.Event()
            await self.modbus.start()
            ready.set()
            await self._stop.wait()
            await self.modbus.stop()

        self._thread = threading.Thread(target=asyncio.run, args=(serve(),), name="emulated-modbus", daemon=True)
        self._thread.start()
        assert ready.wait(10), "the emulated Modbus module did not start"
        return self

    def start_output_node(self) -> int:
        """A Zenoh peer listening on 127.0.0.1 that applies every ``nanodrift/<cell>/command``'s voltage_v."""
        self.node_port = free_port()
        conf = zenoh.Config()
        conf.insert_json5("mode", '"peer"')
        conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{self.node_port}"]))
        conf.insert_json5("scouting/multicast/enabled", "false")
        self._node = zenoh.open(conf)

        def on_command(sample: zenoh.Sample) -> None:
            self.apply_voltage(float(json.loads(sample.payload.to_bytes())["voltage_v"]))

        self._node.declare_subscriber("nanodrift/*/command", on_command)
        return self.node_port

    def stop(self) -> None:
        if self._loop is not None and self._stop is not None:
            self._loop.call_soon_threadsafe(self._stop.set)
        if self._thread is not None:
            self._thread.join(timeout=10)
        if self._node is not None:
            self._node.close()
        self.interferometer.close()
        self.controller.close()
        self.pi_gcs_port.close()

    def __enter__(self) -> EmulatedCell:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- a config for it ----------------------------------------------------------------------------

    def config_text(self, *, cell: str = "hil", actuator: str = "modbus", zenoh_port: int | None = None,
                    procedure: str = "", extra_actuator: str = "") -> str:
        zenoh_port = zenoh_port or free_port()
        actuators: dict[str, str] = {
            "modbus": (f'kind = "modbus"\nhub = "module"\naddress = {AO_ADDRESS}\ndata_type = "int16"\n'
                       f"scale = {AO_VOLTS_PER_COUNT}\nverify = true\n"),
            "serial_line": (f'kind = "serial_line"\nport = "{self.controller.port}"\nreadback = "SVA? 1\\n"\n'
                            f'error_query = "ERR?\\n"\ntimeout_s = {CONTROLLER_TIMEOUT_S}\n'),
            "pi_gcs": (f'kind = "pi_gcs"\ntransport = "serial"\nport = "{self.pi_gcs_port.port}"\n'
                       f"timeout_s = {CONTROLLER_TIMEOUT_S}\n"),
            "zenoh": 'kind = "zenoh"\n',
        }
        connect = f'connect = ["tcp/127.0.0.1:{self.node_port}"]\n' if self.node_port else ""
        sensors = "".join(
            f'[[sensors]]\nname = "{name}"\nkind = "modbus"\nhub = "module"\naddress = {index}\n'
            f'input_type = "input"\ndata_type = "int16"\nscale = {TC_DEGC_PER_COUNT}\ninterval_s = 0.05\n'
            for index, name in enumerate(THERMOCOUPLES))
        sensors += (f'[[sensors]]\nname = "interferometer"\nrole = "position"\nkind = "serial_line"\n'
                    f'port = "{self.interferometer.port}"\nbaudrate = 115200\nquery = "POS?\\r"\n'
                    f"pattern = 'P (?P<value>[-+0-9.]+) nm'\nscale = 0.001\ninterval_s = 0.02\n"
                    f"timeout_s = {CONTROLLER_TIMEOUT_S}\n")
        return (f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zenoh_port}"]\n{connect}'
                f"multicast_scouting = false\n"
                f"[actuator]\nvolts_per_um = {VOLTS_PER_UM}\nv_min = -1.0\nv_max = 11.0\n"
                f"{actuators[actuator]}{extra_actuator}"
                f"[procedure]\n{procedure}"
                f'[[hubs]]\nname = "module"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {self.modbus.port}\n'
                f"timeout_s = {CONTROLLER_TIMEOUT_S}\n{sensors}")


def write_config(path: Path, text: str) -> Path:
    path.write_text(text)
    return path


def describe(values: Any) -> str:
    return ", ".join(f"{v:.3f}" for v in values)
