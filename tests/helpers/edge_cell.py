"""The hardware edge's output module and daemon (issues 16 and 26): what the device receives, not what the daemon says.

``OutputModule``: pymodbus' own TCP server on 127.0.0.1 (on an asyncio loop in a thread of this process, stamping
every write as it lands, optionally answering each write late or refusing one). ``Cell``: ``nanodrift run`` as a
process on the harness' ``file`` sensor plugin with an ``[actuator]`` of the test's, and a Zenoh client.
"""

from __future__ import annotations

import asyncio
import itertools
import subprocess
import threading
import time
from collections.abc import Callable, Coroutine, Sequence
from pathlib import Path
from typing import Any

from helpers.daemon_harness import (
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    run_cli,
)
from helpers.modbus_helpers import ModbusTestDevice, ModbusTestServer
from helpers.wall_clock import WallShift
from nanodrift.model.model import FittedTerm, Model, Training, save_model
from nanodrift.model.terms import parse_term

SCALE = 0.001  # volts per count of the output register
ADDRESS = 10
VOLTS_PER_UM = 0.02
UM_PER_COUNT = SCALE / VOLTS_PER_UM
#: the output module answers from a thread of the pytest process, late on a loaded machine: the hub's timeout only
#: bounds how long a dead module takes to be called dead, which no test here times
MODULE_TIMEOUT_S = 2.0


# --- the output module ---------------------------------------------------------------------------


class OutputModule:
    """pymodbus' TCP server on its own loop thread; ``stamps`` is every write of a register as it landed."""

    def __init__(self) -> None:
        self.device = ModbusTestDevice(1, holding_ranges=((0, 32),))
        self.server = ModbusTestServer([self.device])
        self.stamps: list[tuple[float, int, int]] = []  # (time.monotonic(), address, raw)
        self.on_output: Callable[[int], None] | None = None  # told each raw value landing in ADDRESS
        self.device.on_write = self._landed
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="modbus-output", daemon=True)
        self._thread.start()
        self.call(self.server.start())

    def _landed(self, address: int, values: list[int]) -> None:
        now = time.monotonic()
        self.stamps.extend((now, address + i, _signed(v)) for i, v in enumerate(values))
        if self.on_output is not None and address == ADDRESS:
            self.on_output(_signed(values[0]))

    def call(self, coro: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def register(self) -> int:
        return _signed(self.call(self.server.get_registers(1, ADDRESS, 1))[0])

    def hold(self, raw: int) -> None:
        """Put ``raw`` in the register (what an earlier run, or someone else, left there); not a stamp."""
        self.call(self.server.set_registers(1, ADDRESS, [raw & 0xFFFF], input_type="holding"))
        self.stamps.clear()
        self.device.writes.clear()

    def written(self, since: int = 0) -> list[tuple[float, int]]:
        """(time, raw) of every write of the output register, from stamp ``since`` on."""
        return [(t, raw) for t, address, raw in self.stamps[since:] if address == ADDRESS]

    def close(self) -> None:
        self.call(self.server.stop())
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join(5)


def _signed(raw: int) -> int:
    return raw - 65536 if raw >= 32768 else raw


def raw_for(voltage_v: float) -> int:
    return round(voltage_v / SCALE)


# --- a daemon --------------------------------------------------------------------------------------


def confirm_output(config: Path, pythonpath: Sequence[Path], *args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift confirm-output --config <config> <args>``: an operator says where an output is (in this process,
    with the config's driver plugins in ``pythonpath``; it writes a state file and opens no device)."""
    return run_cli("confirm-output", "--config", str(config), *args, pythonpath=pythonpath)


def state_dir_keys(root: Path) -> str:
    """A ``[daemon]`` table keeping the daemon's state in ``root/state``."""
    return f'\n[daemon]\nstate_dir = "{root / "state"}"\n'


def write_model(path: Path, terms: dict[str, float]) -> None:
    parsed = [FittedTerm(parse_term(name), coef) for name, coef in terms.items()]
    channels = sorted({ch for ft in parsed for ch in ft.term.channels})
    ranges = {ch: (TEMPS.get(ch, 21.8) - 1.0, TEMPS.get(ch, 21.8) + 1.0) for ch in channels}
    save_model(Model(terms=parsed, training=Training(x_range=(0.0, 480.0), channel_ranges=ranges, rows=100,
                                                     t_span_s=3600.0),
                     provenance={"source": "tests/service/test_hardware_edge.py"}), path)


class Cell:
    """``nanodrift run`` on the ``file`` sensor plugin with an ``[actuator]`` of the test's, and a client."""

    def __init__(self, root: Path, *, terms: dict[str, float], actuator: str, hub_port: int | None = None,
                 channels: Sequence[str] = ("T1", "T2"), position: bool = False, extra: str = "",
                 shift: WallShift | None = None, confirmed_v: float | None = None,
                 sensor_values: dict[str, float] | None = None, sensor_age: dict[str, float] | None = None,
                 ready: Sequence[str] | None = None, start: bool = True) -> None:
        """``confirmed_v``: an operator confirmed the output holds it before the daemon starts (issue 26.5: a
        read-back other than the power-up value is believed only so). ``sensor_values``, ``sensor_age``: what
        the sensor file says at the start beyond the temperatures (values; each channel's age in seconds);
        ``ready``: the channels to wait for (default: every channel the cell reads); ``start`` False: the config
        and files only, no daemon (``daemon`` and ``client`` None)."""
        self.root = root
        self.cell = f"edge{free_port()}"
        self.port = free_port()
        self.hub_port = hub_port
        self.channels = tuple(channels)
        self.position = position
        self.extra = extra + (state_dir_keys(root) if confirmed_v is not None else "")
        plugins = install_file_plugin(root / "plugins")
        self.model_path = root / "model.json"
        write_model(self.model_path, terms)
        self.sensors = SensorFile(root / "sensors.json",
                                  {**TEMPS, **({"P": 0.0} if position else {}), **(sensor_values or {})})
        if sensor_age:
            self.sensors.write(age=dict(sensor_age))
        self.config_path = root / "nanodrift.toml"
        self.write_config(actuator)
        pythonpath = [plugins, *([WallShift.SITE_DIR] if shift is not None else [])]
        self._pythonpath = pythonpath
        if confirmed_v is not None:
            confirmed = confirm_output(self.config_path, pythonpath, "--voltage", repr(confirmed_v))
            assert confirmed.returncode == 0, confirmed.stderr
        self._ids = itertools.count(1)
        self.client: Client | None = None
        if not start:
            self.daemon = None  # type: ignore[assignment]  # (a config-only cell: no test of it reads one)
            return
        self.daemon = Daemon(["--config", str(self.config_path)], root / "daemon.log", pythonpath,
                             env=shift.env() if shift is not None else None)
        self.daemon.wait_log("serving", timeout=30)
        self.client = Client(self.port, self.cell)
        self.client.wait_alive()
        self.client.wait_ready(self.channels + (("P",) if position else ()) if ready is None else ready)

    def write_config(self, actuator: str) -> None:
        keys = f"volts_per_um = {VOLTS_PER_UM}\n{actuator}"
        if self.hub_port is not None:
            keys = f'kind = "modbus"\nhub = "out"\ndevice_id = 1\naddress = {ADDRESS}\nscale = {SCALE}\n{keys}'
        extra = self.extra
        if self.hub_port is not None:
            extra += (f'\n[[hubs]]\nname = "out"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {self.hub_port}\n'
                      f"timeout_s = {MODULE_TIMEOUT_S}\n")
        if self.position:
            extra += (f'\n[[sensors]]\nname = "P"\nrole = "position"\nkind = "file"\npath = "{self.sensors.path}"\n'
                      "interval_s = 0.05\nmax_age_s = 2.0\ntimeout_s = 0.5\n")
        self.config_path.write_text(file_sensor_config(
            self.root, cell=self.cell, port=self.port, model_path=self.model_path, sensor_file=self.sensors.path,
            channels=self.channels, actuator=keys, extra=extra))

    def restart_after_kill(self, *, ready: Sequence[str] | None = None) -> None:
        """``kill -9`` the daemon (no safe stop, nothing flushed) and start it again on the same config and cell;
        ``ready``: the channels to wait for (default: every channel the cell reads)."""
        if self.client is not None:
            self.client.close()
            self.client = None
        self.daemon.proc.kill()
        self.daemon.proc.wait(10)
        self.daemon.stop()
        self.daemon = Daemon(["--config", str(self.config_path)], self.root / "daemon-restarted.log",
                             self._pythonpath)
        self.daemon.wait_log("serving", timeout=30)
        self.client = Client(self.port, self.cell)
        self.client.wait_alive()
        self.client.wait_ready(self.channels + (("P",) if self.position else ()) if ready is None else ready)

    @property
    def bus(self) -> Client:
        assert self.client is not None
        return self.client

    def target(self, x_um: float) -> dict[str, Any]:
        """A served target's command (the test fails on a refusal)."""
        ok, answer = self.bus.query({"x_um": x_um, "id": next(self._ids)})
        assert ok, answer
        return answer

    def close(self) -> int:
        if self.client is not None:
            self.client.close()
            self.client = None
        return 0 if self.daemon is None else self.daemon.stop()
