"""A cell built from the instruments labs own, each emulated behind its real transport and tied together by
the simulated cell's physics (for ``tests/drivers/test_instruments_cell.py``):

- a PI controller (``PiGcsEmulator``) over TCP on 127.0.0.1 or on a pty: its axis ``"1"`` (``"2"``) drives
  the stage's x (y); an SVA that takes effect puts ``volts / VOLTS_PER_UM`` on the axis (open loop, the
  amplifier's gain), a MOV puts the position itself (closed loop: the controller's own sensor holds it);
- an attocube IDS (``IdsEmulator``, JSON-RPC on TCP): its axis 0 (1) reports the stage's x (y), as the cell's
  interferometer measures it at the moment of the request, in picometres;
- one DCON module (``DconModule``, 4 or 8 channels) on an RS-485 pty or behind a TCP gateway: T1..T4 of the
  cell at the moment of each ``#AA`` (on an 8-channel module on channels 4..7; channels 0..3 read a spare
  22 degC nobody configured).

The physics runs on a :class:`~nanodrift.drivers.simulated.clock.ScaledClock` (``SPEED`` simulated seconds
per wall second), so a calibration of a few seconds sees hours of the room.
"""

from __future__ import annotations

import asyncio
import threading
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

from nanodrift.drivers.simulated.cell import SimulatedCell, position_channels
from nanodrift.drivers.simulated.clock import ScaledClock
from nanodrift.drivers.simulated.config import SimulationConfig
from nanodrift.drivers.testing import DconBusEmulator, DconModule, DconTcpGateway, IdsEmulator
from nanodrift.drivers.testing.pi_gcs_emulator import EmulatedAxis, PiGcsEmulator, PiGcsPtyDevice, PiGcsTcpServer

#: the emulated PI controller, IDS and DCON module answer from threads of the pytest process, late on a loaded
#: machine (0.5 s was seen to expire beside a serial run): it only bounds how long a dead device takes to be called
#: dead
CONTROLLER_TIMEOUT_S = 2.0
SPEED = 3000.0
VOLTS_PER_UM = 0.02  # the amplifier's gain (open loop) and [actuator] volts_per_um
V_MIN, V_MAX = -1.0, 11.0  # [actuator] limits, inside the emulated piezo channel's VMI?/VMA? (-30, 130)
TRAVEL_UM = (-10.0, 510.0)  # TMN?/TMX? of every emulated axis: closed loop is bounded by it
SLEW_UM_PER_S = 1500.0
DCON_ADDRESS = 5
THERMOCOUPLES = ("T1", "T2", "T3", "T4")
SPARE_DEGC = 22.0
#: a short plan: 0.08 s holds (4 minutes of the room at SPEED), the last 0.04 s averaged (2 IDS and DCON polls)
STEP_TIMING = "rise_s = 0.03\nhold_s = 0.08\naverage_s = 0.04\n"


def calibration_cycles(axes: tuple[str, ...]) -> int:
    """One sweep of the 17 levels for one axis; two for XY: the space-filling plan's first cycle is the diagonal
    x = y (``cell_calibration_plan``), on which no fit can tell x from y."""
    return 1 if len(axes) == 1 else 2


@dataclass(frozen=True)
class Case:
    """One wiring of the cell: which axes, which loop, and over what each instrument is reached."""

    name: str
    axes: tuple[str, ...]
    mode: Literal["open_loop", "closed_loop"]
    pi_transport: Literal["tcp", "serial"]
    dcon_transport: Literal["tcp", "serial"]
    dcon_channels: Literal[4, 8]

    @property
    def pi_axes(self) -> dict[str, str]:
        """Cell axis -> the controller's axis identifier."""
        return {axis: str(index + 1) for index, axis in enumerate(self.axes)}

    @property
    def ids_axes(self) -> dict[str, int]:
        """Cell axis -> the IDS's measurement axis."""
        return {axis: index for index, axis in enumerate(self.axes)}

    @property
    def thermocouple_channels(self) -> dict[str, int]:
        """Thermocouple -> its channel on the DCON module."""
        first = self.dcon_channels - len(THERMOCOUPLES)
        return {name: first + index for index, name in enumerate(THERMOCOUPLES)}

    @property
    def position_sensors(self) -> dict[str, str]:
        """Cell axis -> the name of its position sensor in the config."""
        return {axis: "interferometer" if len(self.axes) == 1 else f"ifm_{axis}" for axis in self.axes}


class InstrumentCell:
    def __init__(self, tmp_path: Path, case: Case) -> None:
        self.case = case
        simulation = SimulationConfig(scenario="train", seed=0, axes="".join(case.axes) if len(case.axes) > 1 else "")
        self.cell = SimulatedCell(simulation.physics(), ScaledClock(SPEED))
        self._channel_of = {axis: channel for channel, axis in position_channels(self.cell.axes).items()}
        self.lock = threading.Lock()  # the cell is reached from the PI, IDS and DCON serving threads
        self._cell_axis = {pi_axis: axis for axis, pi_axis in case.pi_axes.items()}
        self.pi = PiGcsEmulator(
            axes={pi_axis: EmulatedAxis(servo=case.mode == "open_loop", travel_um=TRAVEL_UM)
                  for pi_axis in case.pi_axes.values()},
            on_sva=lambda pi_axis, volts: self._command(pi_axis, volts / VOLTS_PER_UM),
            on_mov=self._command)
        self.ids = IdsEmulator(start=False)
        for axis, ids_axis in case.ids_axes.items():
            self.ids.axes[ids_axis].follow = lambda axis=axis: self.position_um(axis) * 1e6  # type: ignore[misc]
        self.module = DconModule(DCON_ADDRESS, [SPARE_DEGC] * case.dcon_channels, name="4018+" if
                                 case.dcon_channels == 8 else "4018", follow=self._module_channels)
        self._tmp_path = tmp_path
        self.dcon: DconBusEmulator | DconTcpGateway | None = None
        self.pi_pty: PiGcsPtyDevice | None = None
        self.pi_tcp: PiGcsTcpServer | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread: threading.Thread | None = None

    # -- the physics --------------------------------------------------------------------------------

    def _command(self, pi_axis: str, q_um: float) -> None:
        with self.lock:
            self.cell.command(self._cell_axis[pi_axis], q_um)

    def position_um(self, axis: str) -> float:
        """The stage's ``axis`` as the cell's interferometer measures it now."""
        channel = self._channel_of[axis]
        with self.lock:
            return self.cell.read([channel])[channel].value

    def _module_channels(self) -> list[float]:
        with self.lock:
            readings = self.cell.read(THERMOCOUPLES)
        values = [SPARE_DEGC] * self.case.dcon_channels
        for name, channel in self.case.thermocouple_channels.items():
            values[channel] = readings[name].value
        return values

    # -- the transports -----------------------------------------------------------------------------

    def start(self) -> InstrumentCell:
        self.ids.start()
        if self.case.dcon_transport == "serial":
            self.dcon = DconBusEmulator(self._tmp_path / "ttyRS485", [self.module])
        else:
            self.dcon = DconTcpGateway([self.module])
        if self.case.pi_transport == "serial":
            self.pi_pty = PiGcsPtyDevice(self._tmp_path / "ttyPI", self.pi)
        else:
            self.pi_tcp = PiGcsTcpServer(self.pi)
            self._loop = asyncio.new_event_loop()
            self._thread = threading.Thread(target=self._loop.run_forever, name="pi-gcs-tcp", daemon=True)
            self._thread.start()
            asyncio.run_coroutine_threadsafe(self.pi_tcp.start(), self._loop).result(10)
        return self

    def stop(self) -> None:
        if self._loop is not None and self.pi_tcp is not None:
            asyncio.run_coroutine_threadsafe(self.pi_tcp.stop(), self._loop).result(10)
            self._loop.call_soon_threadsafe(self._loop.stop)
        if self._thread is not None:
            self._thread.join(timeout=10)
        if self._loop is not None:
            self._loop.close()
        if self.pi_pty is not None:
            self.pi_pty.close()
        if self.dcon is not None:
            self.dcon.close()
        self.ids.stop()

    def __enter__(self) -> InstrumentCell:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # -- the operator's config ----------------------------------------------------------------------

    def actuator_keys(self, axis: str) -> str:
        c = self.case
        if self.pi_tcp is not None:
            where = f'transport = "tcp"\nhost = "127.0.0.1"\nport = {self.pi_tcp.port}\n'
        else:
            assert self.pi_pty is not None
            where = f'transport = "serial"\nport = "{self.pi_pty.port}"\n'
        return (f'kind = "pi_gcs"\n{where}axis = "{c.pi_axes[axis]}"\nmode = "{c.mode}"\n'
                f"timeout_s = {CONTROLLER_TIMEOUT_S}\n"
                f"volts_per_um = {VOLTS_PER_UM}\nv_min = {V_MIN}\nv_max = {V_MAX}\n"
                f"max_slew_um_per_s = {SLEW_UM_PER_S}\nsafe_voltage_v = 0.0\n")

    def config_text(self, *, cell: str, zenoh_port: int, model: Path) -> str:
        c = self.case
        if len(c.axes) == 1:
            outputs = f"[actuator]\n{self.actuator_keys(c.axes[0])}"
        else:
            outputs = "".join(f'[[axes]]\nname = "{axis}"\nmin_um = 0.0\nmax_um = 480.0\n[axes.actuator]\n'
                              f"{self.actuator_keys(axis)}" for axis in c.axes)
        assert self.dcon is not None
        if isinstance(self.dcon, DconTcpGateway):
            hub = f'[[hubs]]\nname = "rs485"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {self.dcon.port}\n'
        else:
            hub = f'[[hubs]]\nname = "rs485"\ntype = "serial"\nport = "{self.dcon.port}"\n'
        sensors = "".join(f'[[sensors]]\nname = "{name}"\nkind = "dcon"\nhub = "rs485"\naddress = {DCON_ADDRESS}\n'
                          f"channel = {channel}\ninterval_s = 0.02\nmax_age_s = 1.0\n"
                          for name, channel in c.thermocouple_channels.items())
        sensors += "".join(
            f'[[sensors]]\nname = "{c.position_sensors[axis]}"\nrole = "position"\n'
            + (f'axis = "{axis}"\n' if len(c.axes) > 1 else "")
            + f'kind = "attocube_ids"\nhost = "127.0.0.1"\nport = {self.ids.port}\nids_axis = {ids_axis}\n'
              f"interval_s = 0.02\nmax_age_s = 1.0\ntimeout_s = {CONTROLLER_TIMEOUT_S}\n"
            for axis, ids_axis in c.ids_axes.items())
        return (f'cell = "{cell}"\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{zenoh_port}"]\n'
                f'multicast_scouting = false\n[model]\npath = "{model}"\n'
                f"[procedure]\ncycles = {calibration_cycles(c.axes)}\n{STEP_TIMING}"
                f"{outputs}{hub}timeout_s = {CONTROLLER_TIMEOUT_S}\n{sensors}")
