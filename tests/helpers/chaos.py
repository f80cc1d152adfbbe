"""The chaos suites' machine (``tests/service/test_chaos*.py``): one real ``nanodrift run`` per hypothesis
example, driven by random interleavings of targets, reloads, wall-clock steps, device and sensor faults,
SIGTERM and restart, with device-side invariants after every step.

:class:`ChaosMachine` drives an emulated Modbus output (``test_chaos.py`` describes its rules and
invariants); a machine with another output overrides the output hooks (``open_output``, ``output_toml``,
``check_left_safe``, ...), ``wait_quiet`` and ``check`` (``test_chaos_serial.py``).
"""

from __future__ import annotations

import asyncio
import csv
import datetime as dt
import itertools
import json
import math
import os
import shutil
import signal
import subprocess
import tempfile
import threading
import time
from collections.abc import Coroutine
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from hypothesis import HealthCheck, Phase, event, note, settings
from hypothesis import strategies as st
from hypothesis.control import currently_in_test_context
from hypothesis.stateful import RuleBasedStateMachine, initialize, invariant, precondition, rule
from pymodbus.constants import ExcCodes

from helpers.budget import LONG_TESTS
from helpers.cell_helpers import write_cell_model
from helpers.daemon_harness import (
    MODEL_CHANNEL_RANGES,
    TEMPS,
    Client,
    Daemon,
    SensorFile,
    file_sensor_config,
    free_port,
    install_file_plugin,
    wait_until,
    write_test_model,
)
from helpers.edge_cell import confirm_output
from helpers.modbus_helpers import FC_READ_HOLDING, ModbusTestDevice, ModbusTestServer
from helpers.wall_clock import WallShift
from nanodrift.service.recorder import TIMESYNC_FLAG, file_name

#: read once: a precondition must not read the host (the file could appear mid-run)
HOST_CLOCK_SYNCHRONISED = TIMESYNC_FLAG.exists()
#: NANODRIFT_CHAOS_SHRINK=0: report the first failing sequence as found (each shrink step starts a daemon)
SHRINK = os.environ.get("NANODRIFT_CHAOS_SHRINK", "1") != "0"


def chaos_settings(examples: int, steps: int) -> settings:
    """Hypothesis settings for a chaos machine: no deadline (a step waits for a daemon), shrinking unless
    ``NANODRIFT_CHAOS_SHRINK=0``. At the CI size the sequences are the same on every run (derandomized): how long
    a machine runs depends on the faults it draws (11 s one run, 20 s the next, same code), and exploring new
    sequences is the release run's job (``NANODRIFT_LONG_TESTS=1``, random)."""
    return settings(
        max_examples=examples,
        stateful_step_count=steps,
        derandomize=not LONG_TESTS,
        deadline=None,
        suppress_health_check=[HealthCheck.too_slow],
        phases=tuple(Phase) if SHRINK else tuple(p for p in Phase if p is not Phase.shrink),
    )


SCALE = 0.001  # volts per count of the output register (int16)
ADDRESS = 10
SAFE_V = 0.0  # safe_voltage_v: where SIGTERM leaves the stage
POWER_UP_V = 0.0  # power_up_voltage_v (the default): what a register holds before anything wrote it
HUB_TIMEOUT_S = 1.0  # the module's latency stays below it (and below the daemon's 3 s write timeout)
LIE_COUNTS = 7  # a lying module reads back this many counts more than it holds
SLACK_V = 1e-9
#: the slew check's tolerance: each of the two values is rounded to a count (half a count each), plus float noise
SLEW_TOLERANCE_V = SCALE + 1e-9
#: how long a check waits for the actuation to go quiet, a healed device's fault to clear, or status to show the
#: device's position. A failing device pushes the daemon's reopen backoff to MAX_BACKOFF_S (5 s, +-20 %), and on
#: a loaded machine a reopen can miss a device timeout more than once: 20 s (10 s for the position) left room for
#: a few tries only and flaked with the cores busy; 60 s allows about ten. A green check waits only as long as
#: the daemon takes.
QUIET_WAIT_S = 60.0


def _signed(raw: int) -> int:
    return raw - 65536 if raw >= 32768 else raw


# --- the output module --------------------------------------------------------------------------


@dataclass(frozen=True)
class Arrival:
    """A write request as it reached the module: when it arrived and when the module answered it (this
    process' monotonic clock), where, what, and whether the module took it."""

    t: float
    address: int
    raw: int
    landed: bool
    returned: float

    @property
    def volts(self) -> float:
        return self.raw * SCALE


class ChaosDevice(ModbusTestDevice):
    """One Modbus device whose output registers (one per axis) are the stage's voltages.

    ``outputs`` is what the module really holds per register (the last write it took); ``failing`` answers every
    write with DEVICE_FAILURE (nothing is stored), ``latency_s`` delays every answer, ``lying`` makes reads of an
    output register answer ``LIE_COUNTS`` more than it holds.
    """

    def __init__(self, addresses: tuple[int, ...] = (ADDRESS,)) -> None:
        super().__init__(1, input_ranges=((0, 16),), holding_ranges=((0, 32),))
        self.lock = threading.Lock()
        self.arrivals: list[Arrival] = []  # in the order the module answered them
        self.outputs = dict.fromkeys(addresses, 0)  # every register starts at 0 counts: 0 V
        self.power_up_at = time.monotonic()  # when the registers took their power-up value
        self.failing = False
        self.lying = False
        self.latency_s = 0.0
        self.lies_left = 0  # reads of an output register still to answer wrong (a transient mismatch)
        self.last_activity = time.monotonic()  # the last request's arrival or answer

    def _touch(self) -> None:
        with self.lock:
            self.last_activity = time.monotonic()

    async def _action(self, function_code: int, start: int, address: int, count: int,
                      registers: list[int], set_values: object) -> ExcCodes | None:
        if self.quiet:
            return None
        self._touch()
        if set_values is None:  # a read: the daemon's read-back (at open, and after each write: verify)
            if self.latency_s:
                await asyncio.sleep(self.latency_s)
            if function_code == FC_READ_HOLDING:
                with self.lock:
                    for register, held in self.outputs.items():
                        if address <= register < address + count:  # what this read answers
                            lie = self.lying or self.lies_left > 0
                            registers[register - start] = (held + (LIE_COUNTS if lie else 0)) & 0xFFFF
                            self.lies_left = max(self.lies_left - 1, 0)
            self._touch()
            return None
        assert isinstance(set_values, list)
        values = [_signed(int(v)) for v in set_values]
        with self.lock:
            landed = not self.failing
        arrived = time.monotonic()
        if self.latency_s:
            await asyncio.sleep(self.latency_s)
        with self.lock:
            if landed:
                for i, value in enumerate(values):
                    if address + i in self.outputs:
                        self.outputs[address + i] = value
            returned = time.monotonic()  # stamped before the answer leaves: never later than the daemon sees it
            self.arrivals.extend(Arrival(arrived, address + i, v, landed, returned) for i, v in enumerate(values))
        self._touch()
        return None if landed else ExcCodes.DEVICE_FAILURE

    def quiet_for(self) -> float:
        with self.lock:
            return time.monotonic() - self.last_activity


class OutputModule:
    """pymodbus' TCP server with a :class:`ChaosDevice`, on its own loop thread."""

    def __init__(self, addresses: tuple[int, ...] = (ADDRESS,)) -> None:
        self.device = ChaosDevice(addresses)
        self.server = ModbusTestServer([self.device])
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="chaos-modbus", daemon=True)
        self._thread.start()
        self.call(self.server.start())

    def call(self, coro: Coroutine[Any, Any, Any]) -> Any:
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(10)

    def close(self) -> None:
        try:
            self.call(self.server.stop())
        finally:
            self.loop.call_soon_threadsafe(self.loop.stop)
            self._thread.join(5)


# --- what the test believes is in force ---------------------------------------------------------


@dataclass(frozen=True)
class Limits:
    v_min: float = -2.0
    v_max: float = 12.0
    max_slew_um_per_s: float = 0.0
    volts_per_um: float = 0.02

    def allows(self, volts: float) -> bool:
        return self.v_min - SLACK_V <= volts <= self.v_max + SLACK_V

    def count_for(self, volts: float) -> int:
        """The count a command of ``volts`` is written as: the nearest, or the neighbour inside a limit."""
        raw = round(volts / SCALE)
        if raw * SCALE > self.v_max + SLACK_V:
            raw -= 1
        elif raw * SCALE < self.v_min - SLACK_V:
            raw += 1
        return raw

    def text(self) -> str:
        return (f"[{self.v_min:g}, {self.v_max:g}] V, slew {self.max_slew_um_per_s:g} um/s, "
                f"{self.volts_per_um:g} V/um")


@dataclass(frozen=True)
class Epoch:
    """Limits in force from ``t`` on; writes arriving in ``[t, window_end]`` may still carry ``previous``'s."""

    t: float
    limits: Limits
    window_end: float
    previous: Limits | None


# slews that make any ramp take at most a second: 14 V at 0.01 V/um is 1400 um
V_MINS = (-2.0, -1.0, -0.25, 0.0)
V_MAXES = (2.5, 5.0, 8.0, 12.0)
SLEWS = (0.0, 1500.0, 3000.0)
GAINS = (0.01, 0.02, 0.025)
limits_strategy = st.builds(Limits, st.sampled_from(V_MINS), st.sampled_from(V_MAXES), st.sampled_from(SLEWS),
                            st.sampled_from(GAINS))

MAX_AXES = 3
valid_x = st.floats(min_value=0.0, max_value=500.0, allow_nan=False).map(lambda x: round(x, 3))
#: a point of up to MAX_AXES axes (a cell takes its first ones); a test may pass one float for every axis
valid_point = st.tuples(*[valid_x] * MAX_AXES)
#: a position outside the workspace on one axis (the others inside); a float: on the first axis
outside_x = st.tuples(st.sampled_from([-50.0, -0.001, 500.5, 1.0e4]), st.integers(0, MAX_AXES - 1))
MALFORMED = {  # with an id the daemon can answer to
    "x_not_a_number": '{{"id": "{id}", "x_um": "abc"}}',
    "x_missing": '{{"id": "{id}"}}',
    "x_null": '{{"id": "{id}", "x_um": null}}',
    "x_infinite": '{{"id": "{id}", "x_um": 1e999}}',
}
ANONYMOUS = {"not_json": "x_um=12", "not_an_object": "[1, 2]", "empty": ""}  # answered with id null
target_strategy = st.one_of(
    st.tuples(st.just("valid"), valid_point),
    st.tuples(st.just("outside"), outside_x),
    st.tuples(st.just("malformed"), st.sampled_from(sorted(MALFORMED))),
    st.tuples(st.just("anonymous"), st.sampled_from(sorted(ANONYMOUS))),
)
BAD_EDITS = ("unknown_key", "bad_toml", "v_min_above_v_max", "safe_voltage_outside")
RECORD_DAYS = 4  # day files there before the first start
RECORD_KEEP_DAYS = 90
RESTART_CLOCK_OFF_DAYS = 30  # (clock_near_true) well inside RECORD_KEEP_DAYS of the day files
SHARED_REGISTER = "# two axes on one register\n"  # (a comment in the edit: the config_registers hook reads it)


class ChaosMachine(RuleBasedStateMachine):
    """One daemon per example; see the module docstring for the rules and the invariants.

    ``AXES`` are the cell's axes: one (``x``, the one-axis config of ``[actuator]``) or several (``[[axes]]``),
    each on its own register of the one module (``ADDRESS`` + its index); every rule and check runs per axis."""

    AXES: tuple[str, ...] = ("x",)
    VERIFY = True  # the outputs' verify: each write read back (transient mismatches are met)

    def __init__(self) -> None:
        super().__init__()
        self.root: Path | None = None
        self.module: OutputModule | None = None
        self.daemon: Daemon | None = None
        self.client: Client | None = None
        self.old_clients: list[Client] = []  # one per earlier daemon process: their answers still count
        self.step_log: list[str] = []

    # --- set-up and tear-down -------------------------------------------------------------------

    @initialize(limits=limits_strategy)
    def start_daemon(self, limits: Limits) -> None:
        self.root = Path(tempfile.mkdtemp(prefix="nanodrift-chaos-"))
        self.open_output()
        self.plugins = install_file_plugin(self.root / "plugins")
        self.model_path = self.root / "model.json"
        if len(self.AXES) == 1:
            write_test_model(self.model_path)
        else:
            write_cell_model(self.model_path, self.AXES, max_um=500.0)
        self.temps = dict(TEMPS)
        self.positions = {f"ifm_{axis}": 0.0 for axis in self.AXES}  # each axis' interferometer reads its target
        self.faulted: set[str] = set()
        self.sensors = SensorFile(self.root / "sensors.json", {**self.temps, **self.positions})
        self.records = self.root / "records"
        self.records.mkdir()
        today = dt.datetime.now(dt.UTC).date()
        for days_ago in range(RECORD_DAYS):  # day files of earlier days, within record_keep_days of the real today
            (self.records / file_name(today - dt.timedelta(days=days_ago))).write_text(self.record_header())
        self.record_files = set(self.records.glob("records-*.csv"))
        self.shift = WallShift(self.root / "wall_shift")
        self.cell = f"chaos{free_port()}"
        self.port = free_port()
        self.config_path = self.root / "nanodrift.toml"
        self.state_dir = self.root / "state"
        now = time.monotonic()
        self.epochs = [Epoch(now, limits, now, None)]
        self.write_config(limits)
        self.ids = itertools.count(1)
        self.sent: dict[str, tuple[str, Any, set[str]]] = {}  # id -> (what, detail, kinds of error allowed)
        self.anonymous_sent = 0
        self.checked_arrivals = 0
        self.previous_write: dict[int, Arrival] = {}  # per register: the last write it took, as checked
        self.checked_answers: set[Any] = set()
        self.sent_at: dict[str, float] = {}
        self.commands_seen = 0
        self.last_command: dict[str, Any] | None = None
        self.expect = "safe"  # "safe" | "command" | "dropped" | "held": what the registers hold once quiet
        self.held: dict[str, int] = {}  # "held": the counts each axis' register held when the daemon stopped
        self.dropped_at: float | None = None
        self.mode = "ok"  # the module: "ok" | "failing" | "lying"
        self.misreads_pending = False  # module_misreads_a_few_times: wrong answers not yet all given
        self.restarts = 0
        self.say(f"start: {limits.text()}")
        self.launch()

    def launch(self) -> None:
        assert self.root is not None
        self.daemon = Daemon(["--config", str(self.config_path)], self.root / f"daemon{self.restarts}.log",
                             [WallShift.SITE_DIR, self.plugins], env=self.shift.env())
        self.daemon.wait_log("serving", timeout=30)
        self.client = self.make_client()
        self.client.wait_alive()
        self.wait_channels()

    def wait_channels(self) -> None:
        """Until status shows each channel as the sensor file makes it: ``fault`` or ``ok``."""

        def as_written() -> bool:
            try:
                sensors = self.client.status(1.0)["sensors"]  # type: ignore[union-attr]
            except AssertionError:
                return False
            return all(sensors.get(c, {}).get("state") == ("fault" if c in self.faulted else "ok")
                       for c in ("T1", "T2"))

        wait_until(as_written, 15, f"channels in status ({sorted(self.faulted)} in fault, the others ok)",
                   interval=0.05)

    # --- the output device: hooks a machine with another output overrides ------------------------

    @property
    def registers(self) -> dict[str, int]:
        """Each axis' output register on the module."""
        return {axis: ADDRESS + i for i, axis in enumerate(self.AXES)}

    def config_registers(self, tail: str) -> dict[str, int]:
        """The registers the config gives the axes: with ``SHARED_REGISTER`` in ``tail`` (a bad edit), the last
        axis on the first's."""
        registers = self.registers
        if SHARED_REGISTER in tail:
            registers[self.AXES[-1]] = registers[self.AXES[0]]
        return registers

    def open_output(self) -> None:
        self.module = OutputModule(tuple(self.registers.values()))

    def heal_output(self) -> None:
        """The device works properly again (before the daemon stops, so it can leave the stage safe)."""
        if self.module is not None:
            self.module.device.failing = self.module.device.lying = False
            self.module.device.latency_s = 0.0
            self.module.device.lies_left = 0

    def close_output(self) -> None:
        if self.module is not None:
            self.module.close()

    def make_client(self) -> Client:
        return Client(self.port, self.cell)

    def output_toml(self, limits: Limits, v_min: float, v_max: float, safe: float,
                    tail: str) -> tuple[str | None, str]:
        """The ``[actuator]`` keys (None: ``[[axes]]`` instead) and what follows them (axes, hubs, more sensors)."""
        assert self.module is not None
        keys = {axis: (f'kind = "modbus"\nhub = "out"\ndevice_id = 1\naddress = {address}\nscale = {SCALE}\n'
                       f"volts_per_um = {limits.volts_per_um!r}\nv_min = {v_min!r}\nv_max = {v_max!r}\n"
                       f"verify = {str(self.VERIFY).lower()}\n"
                       f"max_slew_um_per_s = {limits.max_slew_um_per_s!r}\nsafe_voltage_v = {safe!r}\n{tail}")
                for axis, address in self.config_registers(tail).items()}
        hub = (f'[[hubs]]\nname = "out"\ntype = "tcp"\nhost = "127.0.0.1"\nport = {self.module.server.port}\n'
               f"timeout_s = {HUB_TIMEOUT_S}\n")
        if len(self.AXES) == 1:
            return keys[self.AXES[0]], hub
        axes = "".join(f'\n[[axes]]\nname = "{axis}"\nmin_um = 0.0\nmax_um = 500.0\n[axes.actuator]\n{text}'
                       for axis, text in keys.items())
        return None, axes + "\n" + hub

    def check_left_safe(self) -> str:
        """After a SIGTERM (exit 0): the output holds ``safe_voltage_v``; what it holds, for the step log."""
        assert self.module is not None
        with self.module.device.lock:
            outputs = dict(self.module.device.outputs)
        for axis, address in self.registers.items():
            assert outputs[address] == self.limits.count_for(SAFE_V), (
                f"after SIGTERM axis {axis}'s register {address} holds {outputs[address]} counts "
                f"({outputs[address] * SCALE:.4f} V), not safe_voltage_v {SAFE_V} V:\n{self.daemon_log_tail()}")
        return f"registers {outputs} counts"

    def teardown(self) -> None:
        try:
            self.heal_output()
            for client in [*self.old_clients, *([self.client] if self.client else [])]:
                client.close()
            if self.daemon is not None:
                self.daemon.stop(timeout=25)
        finally:
            self.close_output()
            if self.root is not None:
                shutil.rmtree(self.root, ignore_errors=True)

    # --- helpers --------------------------------------------------------------------------------

    @property
    def limits(self) -> Limits:
        return self.epochs[-1].limits

    def say(self, line: str) -> None:
        self.step_log.append(line)
        if currently_in_test_context():
            note(line)

    def write_config(self, limits: Limits, bad: str | None = None) -> None:
        assert self.root is not None
        v_min, v_max, safe, tail = limits.v_min, limits.v_max, SAFE_V, ""
        if bad == "unknown_key":
            tail = "v_maximum = 3.0\n"
        elif bad == "bad_toml":
            tail = "v_max = = 3.0\n"
        elif bad == "v_min_above_v_max":
            v_min, v_max = limits.v_max, limits.v_min
        elif bad == "safe_voltage_outside":
            safe = limits.v_max + 1.0
        elif bad == "shared_register":
            tail = SHARED_REGISTER
        actuator, hub = self.output_toml(limits, v_min, v_max, safe, tail)
        self.config_path.write_text(file_sensor_config(
            self.root, cell=self.cell, port=self.port, model_path=self.model_path, sensor_file=self.sensors.path,
            actuator=actuator, extra=hub + self.daemon_toml()))

    def record_header(self) -> str:
        """A record file's header for this cell (the CSV contract: one-axis names, or per axis)."""
        if len(self.AXES) == 1:
            return "t_s,x_um,q_um,target_um,residual_um,valid,T1,T2\n"
        per_axis = [[f"{kind}{axis}_um" for axis in self.AXES] for kind in ("", "q_", "target_", "residual_")]
        return ",".join(["t_s", *[f"{a}_um" for a in self.AXES], *per_axis[1], *per_axis[2], *per_axis[3],
                         "valid", "T1", "T2"]) + "\n"

    def daemon_toml(self) -> str:
        """The ``[daemon]`` table (the state directory the daemon proves its outputs by), recording (``[health]``)
        and each axis' interferometer (the ``file`` plugin, reading the last target sent)."""
        positions = "".join(
            f'\n[[sensors]]\nname = "ifm_{axis}"\nrole = "position"\nkind = "file"\npath = "{self.sensors.path}"\n'
            f"interval_s = 0.05\nmax_age_s = 1.0\n" + (f'axis = "{axis}"\n' if len(self.AXES) > 1 else "")
            for axis in self.AXES)
        return (f'\n[daemon]\nstate_dir = "{self.state_dir}"\n'
                f'[health]\nsettle_s = 0.1\nwindow_s = 0.2\nrecord_dir = "{self.records}"\n'
                f"record_keep_days = {RECORD_KEEP_DAYS}\n{positions}")


    def put_target(self, what: str, detail: Any) -> str | None:
        assert self.client is not None
        target_id = f"t{next(self.ids)}"
        device_trouble = {"actuator_fault"} if self.mode != "ok" or self.misreads_pending else set()
        if what == "valid":
            payload = json.dumps({**self.position(detail), "id": target_id})
            allowed = {"voltage_limit", *device_trouble, *({"fault"} if self.faulted else set())}
        elif what == "outside":
            value, index = detail if isinstance(detail, tuple) else (detail, 0)
            point = {**self.position(250.0), f"{self.AXES[index % len(self.AXES)]}_um": value}
            payload = json.dumps({**point, "id": target_id})
            allowed = {"out_of_workspace", *device_trouble}
        elif what == "malformed":
            payload = MALFORMED[detail].format(id=target_id)
            allowed = {"bad_payload"}
        else:
            self.client.put(ANONYMOUS[detail])
            self.anonymous_sent += 1
            return None
        self.sent[target_id] = (what, detail, allowed)
        self.sent_at[target_id] = time.monotonic()
        if what == "valid":  # the stage gets there: the interferometers read the target
            self.positions = {f"ifm_{key.removesuffix('_um')}": v for key, v in self.position(detail).items()}
            self.sensors.set(**self.positions)
        self.client.put(payload)
        return target_id

    def position(self, detail: float | tuple[float, ...]) -> dict[str, float]:
        """A target's ``<axis>_um`` keys: one float for every axis, or a tuple's first values."""
        values = detail if isinstance(detail, tuple) else (detail,) * len(self.AXES)
        return {f"{axis}_um": value for axis, value in zip(self.AXES, values, strict=False)}

    def volts_of(self, doc: dict[str, Any]) -> dict[str, float]:
        """A command's (or log line's) ``voltage_v`` per axis: a number in a one-axis cell, an object otherwise."""
        volts = doc["voltage_v"]
        return dict(volts) if isinstance(volts, dict) else {self.AXES[0]: volts}

    def q_of(self, doc: dict[str, Any]) -> dict[str, float]:
        """A command's ``q_um`` per axis, as :meth:`volts_of`."""
        q = doc["q_um"]
        return dict(q) if isinstance(q, dict) else {self.AXES[0]: q}

    def actuators(self, timeout: float) -> dict[str, dict[str, Any]]:
        """Each axis' ``actuator`` in ``status`` (one-axis: the top-level one)."""
        assert self.client is not None
        doc = self.client.status(timeout)
        if len(self.AXES) == 1:
            return {self.AXES[0]: doc["actuator"]}
        return {axis: doc["axes"][axis]["actuator"] for axis in self.AXES}

    def answers(self) -> dict[Any, list[tuple[str, dict[str, Any]]]]:
        out: dict[Any, list[tuple[str, dict[str, Any]]]] = {}
        for client in [*self.old_clients, *([self.client] if self.client else [])]:
            with client._cond:
                docs = [("command", c) for c in client.commands] + [("error", e) for e in client.errors]
            for kind, doc in docs:
                out.setdefault(doc.get("id"), []).append((kind, doc))
        return out

    def commands(self) -> list[dict[str, Any]]:
        return [c for client in [*self.old_clients, *([self.client] if self.client else [])] for c in client.commands]

    def log_events(self, event: str) -> list[dict[str, Any]]:
        assert self.daemon is not None
        return self.daemon.log_events(event)

    def daemon_log_tail(self, events: int = 25) -> str:
        assert self.daemon is not None
        lines = [json.dumps(d) for d in self.daemon.logs() if d.get("event") not in ("target_refused",)]
        return "\n".join(lines[-events:])

    def track_commands(self) -> None:
        """Take the newest command as what the register must hold (a new command ends "dropped"/"safe")."""
        commands = self.commands()
        if len(commands) > self.commands_seen:
            self.commands_seen = len(commands)
            self.last_command = commands[-1]
            self.expect, self.dropped_at = "command", None
            if not self.command_allowed(self.limits, self.last_command):  # served, but a field the device's
                # command carries is outside the limits (a template's x_um): dropped whole, nothing written
                self.expect, self.dropped_at = "dropped", time.monotonic()

    def wait_answered(self) -> None:
        """Invariant 3: every target sent so far has exactly one answer, of a kind its step allows."""

        def all_answered() -> bool:
            answers = self.answers()
            anonymous = len(answers.get(None, []))
            return all(i in answers for i in self.sent) and anonymous >= self.anonymous_sent

        wait_until(all_answered, 10, "an answer to every target sent")
        answers = self.answers()
        for target_id, got in answers.items():
            if target_id is None:
                continue
            assert target_id in self.sent, f"an answer to a target never sent: {got}"
            assert len(got) == 1, f"target {target_id} answered {len(got)} times: {got}"
            if target_id in self.checked_answers:
                continue
            self.checked_answers.add(target_id)  # checked once, against the limits of the step that sent it
            what, detail, allowed = self.sent[target_id]
            kind, doc = got[0]
            if kind == "error":
                assert doc["kind"] in allowed, (f"target {target_id} ({what} {detail!r}) refused with "
                                                f"{doc['kind']!r}, expected a command or one of {sorted(allowed)}: "
                                                f"{doc}")
            else:
                assert what == "valid", f"target {target_id} ({what} {detail!r}) was served: {doc}"
                assert all(self.limits_at_answer_allow(v) for v in self.volts_of(doc).values()), (
                    f"command {target_id} at {doc['voltage_v']} V is outside every limit in force: {doc}")
        assert len(answers.get(None, [])) == self.anonymous_sent, (
            f"{self.anonymous_sent} anonymous payloads, {len(answers.get(None, []))} answers with id null")
        self.track_commands()

    def limits_at_answer_allow(self, volts: float) -> bool:
        # the command was answered by the limits of the current epoch, or the previous one within a reload
        last = self.epochs[-1]
        return last.limits.allows(volts) or (last.previous is not None and last.previous.allows(volts))

    def wait_quiet(self) -> None:
        """No request reached the module for a moment and, unless the module is failing, the daemon says its
        actuator is ok (a fault it has recovered from): the actuation is idle."""
        assert self.module is not None and self.client is not None and self.daemon is not None
        device = self.module.device
        window = 0.3 + 2 * device.latency_s
        self.track_commands()
        deadline = time.monotonic() + QUIET_WAIT_S
        state = None
        while True:
            self.daemon.check_alive()
            if device.quiet_for() >= window:
                if self.mode != "ok":
                    return
                state = {axis: a["state"] for axis, a in self.actuators(3.0).items()}
                if set(state.values()) == {"ok"} and device.quiet_for() >= window and (
                        self.holds_last_command() or time.monotonic() > deadline - 5.0):
                    return  # (a register that never gets there: the check says what it holds)
            assert time.monotonic() < deadline, (
                f"the actuation never went quiet (module quiet for {device.quiet_for():.2f} s, actuator "
                f"{state}):\n{self.daemon_log_tail()}")
            time.sleep(0.05)

    def holds_last_command(self) -> bool:
        """Unless a command is to be held, True; else whether every register holds it: a command answered a
        moment ago may not have reached the module yet (the module was quiet before it)."""
        if self.expect != "command" or self.last_command is None or self.module is None:
            return True
        want = {axis: self.limits.count_for(v) for axis, v in self.volts_of(self.last_command).items()}
        with self.module.device.lock:
            return all(self.module.device.outputs[self.registers[axis]] == raw for axis, raw in want.items())

    def allowed_limits(self, t: float) -> list[Limits]:
        epoch = None
        for candidate in self.epochs:
            if candidate.t <= t:
                epoch = candidate
        if epoch is None:
            return [self.epochs[0].limits]
        allowed = [epoch.limits]
        if epoch.previous is not None and t <= epoch.window_end:
            allowed.append(epoch.previous)
        return allowed

    # --- rules ----------------------------------------------------------------------------------

    @rule(batch=st.lists(target_strategy, min_size=1, max_size=4))
    def send_targets(self, batch: list[tuple[str, Any]]) -> None:
        ids = [self.put_target(what, detail) for what, detail in batch]
        self.say(f"send targets {list(zip(ids, batch, strict=True))}")

    @rule(limits=limits_strategy, mid_motion=st.none() | valid_point)
    def reload_valid_limits(self, limits: Limits, mid_motion: float | tuple[float, ...] | None) -> None:
        assert self.daemon is not None
        before = len(self.log_events("reload_applied")), len(self.log_events("reload_refused"))
        self.write_config(limits)
        if mid_motion is not None:
            self.put_target("valid", mid_motion)
        t0 = time.monotonic()
        self.daemon.signal(signal.SIGHUP)
        outcome = self.wait_reload(before)
        t1 = time.monotonic()
        assert outcome == "reload_applied", f"a valid edit was refused:\n{self.daemon_log_tail()}"
        previous = self.limits
        self.epochs.append(Epoch(t0, limits, t1, previous))
        self.say(f"reload {previous.text()} -> {limits.text()} (target of {mid_motion} um just before SIGHUP), "
                 f"applied after {t1 - t0:.3f} s")
        self.wait_answered()  # the target sent just before it: answered under the old limits or the new
        if self.last_command is None:
            return
        allowed = self.command_allowed(limits, self.last_command)
        if self.expect == "command" and not allowed:
            self.expect, self.dropped_at = "dropped", t1
            self.say(f"  the last command ({self.volts_of(self.last_command)} V, {self.q_of(self.last_command)} um) "
                     "is outside the new limits (or its command is, at the new gain): the daemon must drop it whole "
                     "and hold")
        elif self.expect == "dropped" and allowed and not self.drop_logged():
            # the daemon had not taken the goal up under the narrower limits (its output was in fault): the limits
            # in force now allow it, so it is carried over and written once the output works
            self.expect, self.dropped_at = "command", None
            self.say("  the goal a narrower reload forbade was never dropped (the output was down) and the new limits "
                     "allow it: the daemon carries it over")

    def command_allowed(self, limits: Limits, command: dict[str, Any]) -> bool:
        """Whether the daemon may still send ``command`` under ``limits``: its voltages, and its commands at the
        gain in force (what a controller sent positions would get)."""
        return all(limits.allows(v) and limits.allows(q * limits.volts_per_um)
                   for v, q in zip(self.volts_of(command).values(), self.q_of(command).values(), strict=True))

    def drop_logged(self) -> bool:
        """Whether an ``actuator_goal_dropped`` line names the last command's voltages."""
        assert self.last_command is not None
        volts = self.volts_of(self.last_command)
        return any(all(math.isclose(self.volts_of(e)[a], v) for a, v in volts.items() if a in self.volts_of(e))
                   for e in self.log_events("actuator_goal_dropped"))

    @rule(bad=st.sampled_from(BAD_EDITS))
    def reload_invalid_edit(self, bad: str) -> None:
        assert self.daemon is not None
        before = len(self.log_events("reload_applied")), len(self.log_events("reload_refused"))
        self.write_config(self.limits, bad=bad)
        self.daemon.signal(signal.SIGHUP)
        outcome = self.wait_reload(before)
        self.write_config(self.limits)  # the file is good again (a later restart reads it); no SIGHUP
        assert outcome == "reload_refused", f"the edit {bad!r} was applied:\n{self.daemon_log_tail()}"
        self.say(f"invalid reload ({bad}): refused")

    @precondition(lambda self: len(self.AXES) > 1)
    @rule()
    def reload_two_axes_on_one_register(self) -> None:
        """An edit putting the last axis on the first's register: refused naming both axes, nothing written."""
        assert self.daemon is not None and self.module is not None
        before = len(self.log_events("reload_applied")), len(self.log_events("reload_refused"))
        self.write_config(self.limits, bad="shared_register")
        with self.module.device.lock:
            writes_before = len(self.module.device.arrivals)
        self.daemon.signal(signal.SIGHUP)
        outcome = self.wait_reload(before)
        with self.module.device.lock:
            written = self.module.device.arrivals[writes_before:]
        self.write_config(self.limits)
        assert outcome == "reload_refused", f"two axes on one register were applied:\n{self.daemon_log_tail()}"
        problems = " ".join(self.log_events("reload_refused")[-1].get("problems", []))
        first, last = self.AXES[0], self.AXES[-1]
        assert f"({last})" in problems and f"({first})" in problems and "one output drives one axis" in problems, (
            f"the refusal does not name both axes {first} and {last}: {problems}")
        assert not written, f"the refused reload wrote {written}:\n{self.daemon_log_tail()}"
        self.say(f"reload with {last} on {first}'s register: refused ({problems[:100]}...), nothing written")

    def wait_reload(self, before: tuple[int, int]) -> str:
        try:
            outcome: str = wait_until(lambda: self.reload_outcome(before), 15, "the reload's outcome", interval=0.02)
        except AssertionError as error:
            raise AssertionError(f"{error}:\n{self.daemon_log_tail()}") from None
        return outcome

    def reload_outcome(self, before: tuple[int, int]) -> str | None:
        assert self.daemon is not None
        self.daemon.check_alive()
        if len(self.log_events("reload_applied")) > before[0]:
            return "reload_applied"
        if len(self.log_events("reload_refused")) > before[1]:
            return "reload_refused"
        return None

    @rule(seconds=st.sampled_from([600.0, -600.0, 86400.0, -86400.0]))
    def step_wall_clock(self, seconds: float) -> None:
        self.shift.step(seconds)
        self.say(f"wall clock stepped by {seconds:+g} s (now {self.shift.offset_s:+g} s)")

    @precondition(lambda self: self.mode == "ok")
    @rule()
    def module_starts_failing_writes(self) -> None:
        assert self.module is not None
        self.module.device.failing = True
        self.mode = "failing"
        self.say("module: every write fails from now on (DEVICE_FAILURE)")

    @precondition(lambda self: self.mode == "ok")
    @rule()
    def module_starts_lying_on_read_back(self) -> None:
        assert self.module is not None
        self.module.device.lying = True
        self.mode = "lying"
        self.say(f"module: reads of the output answer {LIE_COUNTS} counts more than it holds")

    @precondition(lambda self: self.mode == "ok")
    @rule(reads=st.integers(1, 3))
    def module_misreads_a_few_times(self, reads: int) -> None:
        """A transient read-back mismatch: the next ``reads`` reads of an output answer wrong, then it is right
        again. The daemon (``verify = true``) retries; the recovery ramps from what the register is known to hold
        (the slew invariant), and once quiet the register holds the command (the module counts as healthy)."""
        assert self.module is not None
        with self.module.device.lock:
            self.module.device.lies_left = reads
        self.misreads_pending = True  # until a quiet check finds them all answered: a target may meet the fault
        self.say(f"module: the next {reads} read(s) of an output answer {LIE_COUNTS} counts more than it holds")

    @precondition(lambda self: self.mode != "ok")
    @rule()
    def module_works_again(self) -> None:
        assert self.module is not None
        self.module.device.failing = self.module.device.lying = False
        self.say(f"module: works again (was {self.mode})")
        self.mode = "ok"

    @rule(latency_s=st.sampled_from([0.0, 0.05, 0.2, 0.4]))
    def module_latency(self, latency_s: float) -> None:
        assert self.module is not None
        self.module.device.latency_s = latency_s
        self.say(f"module: answers {latency_s:g} s late")

    @rule(t1=st.floats(*MODEL_CHANNEL_RANGES["T1"]).map(lambda t: round(t, 3)),
          t2=st.floats(*MODEL_CHANNEL_RANGES["T2"]).map(lambda t: round(t, 3)))
    def temperatures_change(self, t1: float, t2: float) -> None:
        assert self.client is not None
        self.temps = {"T1": t1, "T2": t2}
        self.sensors.write(values={**self.temps, **self.positions}, fault={})
        self.faulted.clear()
        self.wait_channels()
        self.say(f"temperatures T1 = {t1} degC, T2 = {t2} degC (channels ok)")

    @rule(channel=st.sampled_from(["T1", "T2"]))
    def temperature_channel_faults(self, channel: str) -> None:
        assert self.client is not None
        self.faulted.add(channel)
        self.sensors.write(fault={c: "thermocouple open" for c in self.faulted})
        self.wait_channels()
        self.say(f"temperature channel {channel} faults")

    @precondition(lambda self: self.mode == "ok" and self.clock_near_true())
    @rule(how=st.sampled_from(["SIGTERM", "kill -9"]), forget_state=st.booleans())
    def stop_and_restart(self, how: str, forget_state: bool) -> None:
        """Stop the daemon (SIGTERM: it leaves every output safe; kill -9: they hold), optionally delete its state
        directory, and start it again: it believes a register only as its state file (or the power-up 0 V)
        proves; a register nothing proves is refused, nothing written, until ``nanodrift confirm-output``."""
        assert self.module is not None
        if self.restart_skipped(f"{how} and restart"):
            return
        held = self.stop_daemon(how)
        with self.module.device.lock:
            self.held = {axis: self.module.device.outputs[address] for axis, address in self.registers.items()}
        unproven = {axis: raw for axis, raw in self.held.items() if abs(raw * SCALE - POWER_UP_V) > SLACK_V}
        if forget_state:
            shutil.rmtree(self.state_dir, ignore_errors=True)
        self.say(f"{held}: {self.held} counts{', state directory deleted' if forget_state else ''}")
        self.relaunch()
        self.expect, self.dropped_at = "held", None
        if forget_state and unproven:
            self.confirm_unproven(unproven)

    def registers_within_limits(self) -> bool:
        """Every register holds a value inside the limits in force. A start that reads a register outside them
        (a goal a reload dropped) is a fault by design (the daemon never moves an output from there; no operator
        can confirm it): the restart rules do not exercise that case."""
        assert self.module is not None
        with self.module.device.lock:
            return all(self.limits.allows(self.module.device.outputs[a] * SCALE) for a in self.registers.values())

    def restart_skipped(self, what: str) -> bool:
        """Whether a restart rule must do nothing: a register holds a value outside the limits in force.

        Read on the device, so here in the rule's body and never in a precondition: whether a reload's cut ramp
        left a register outside the new limits depends on timing, and a precondition that reads it makes
        hypothesis draw differently when it replays the same steps (``FlakyStrategyDefinition``, "a flaky
        precondition", met by the XY release run). Preconditions read only what the test did."""
        if self.registers_within_limits():
            return False
        self.say(f"{what}: skipped, a register holds a value outside {self.limits.text()} (a goal a reload dropped)")
        if currently_in_test_context():
            event("restart skipped: a register outside the limits")
        return True

    def clock_near_true(self) -> bool:
        """The daemon's clock is less than :data:`RESTART_CLOCK_OFF_DAYS` off. A restart on a clock still that far
        ahead after rows were written on it deletes records (an open recorder bug, see
        ``test_chaos.py::test_a_second_start_on_the_same_wrong_clock_deletes_no_record``): restarts wait until
        NTP set the clock right (``ntp_corrects_the_clock``) while it is open."""
        return abs(self.shift.offset_s) < RESTART_CLOCK_OFF_DAYS * 86400.0

    @precondition(lambda self: self.shift.offset_s != 0.0)
    @rule()
    def ntp_corrects_the_clock(self) -> None:
        self.shift.step(-self.shift.offset_s)
        self.say("wall clock set right (NTP synchronised)")

    @precondition(lambda self: self.mode == "ok" and not HOST_CLOCK_SYNCHRONISED and self.clock_near_true())
    @rule(days=st.sampled_from([2, 120, 400]))
    def restart_on_a_wrong_clock(self, days: int) -> None:
        """The lab PC starts the daemon with its clock ``days`` ahead (a bad RTC, NTP not yet synchronised):
        no record file may be deleted (checked after every step). (A host whose clock says it is synchronised is
        believed: the daemon rightly deletes what that clock says has expired, so the rule is off there.)"""
        if self.restart_skipped(f"restart {days} days ahead"):
            return
        self.say(self.stop_daemon("SIGTERM"))
        self.shift.step(days * 86400.0)
        self.say(f"wall clock +{days} days before the start (now {self.shift.offset_s / 86400:+g} days)")
        self.relaunch()
        self.expect, self.dropped_at = "safe", None

    def stop_daemon(self, how: str) -> str:
        """SIGTERM (exit 0, every output left at ``safe_voltage_v``) or kill -9; what happened, for the log."""
        assert self.daemon is not None
        t0 = time.monotonic()
        if how == "SIGTERM":
            self.daemon.signal(signal.SIGTERM)
        else:
            self.daemon.proc.kill()
        try:
            code = self.daemon.proc.wait(25)
        except subprocess.TimeoutExpired:
            raise AssertionError(f"the daemon did not stop within 25 s:\n{self.daemon_log_tail()}") from None
        if how != "SIGTERM":
            return f"kill -9 after {time.monotonic() - t0:.2f} s"
        assert code == 0, f"the daemon exited with {code}:\n{self.daemon_log_tail()}"
        held = self.check_left_safe()
        safe = self.log_events("actuator_safe")
        assert safe and self.volts_of(safe[-1]) == dict.fromkeys(self.AXES, SAFE_V), (
            f"no actuator_safe line for every axis:\n{self.daemon_log_tail()}")
        return f"SIGTERM: exit 0 after {time.monotonic() - t0:.2f} s, {held}"

    def relaunch(self) -> None:
        """A new daemon process on the same config (the old one's client keeps its answers)."""
        assert self.client is not None
        self.old_clients.append(self.client)
        self.client.close()
        self.client = None
        self.restarts += 1
        if self.module is not None:  # a transient mismatch is over (a lie at the start read is another rule's)
            with self.module.device.lock:
                self.module.device.lies_left = 0
        self.launch()
        self.say("restarted")

    def confirm_unproven(self, unproven: dict[str, int]) -> None:
        """Nothing proves what ``unproven`` axes' registers hold: a target is refused saying how to confirm, the
        actuator is in fault, nothing is written; ``nanodrift confirm-output`` per axis makes the daemon believe
        them, still writing nothing (the check that follows sees the registers unchanged)."""
        assert self.client is not None and self.module is not None
        with self.module.device.lock:
            writes_before = len(self.module.device.arrivals)
        target_id = self.put_target("valid", 100.0)
        assert target_id is not None
        self.sent[target_id] = ("valid", 100.0, {"actuator_fault"})  # refused: nothing proves where the stage is
        self.wait_answered()
        kind, doc = self.answers()[target_id][0]
        assert kind == "error" and "nanodrift confirm-output" in doc["error"], (
            f"a target while {sorted(unproven)} are unproven was answered {kind} {doc}:\n{self.daemon_log_tail()}")
        states = {axis: a["state"] for axis, a in self.actuators(3.0).items()}
        assert "fault" in states.values(), f"status shows {states} while {sorted(unproven)} are unproven"
        for axis, raw in unproven.items():
            confirmed = confirm_output(self.config_path, [self.plugins], "--axis", axis, "--voltage",
                                       f"{raw * SCALE:.4f}")
            assert confirmed.returncode == 0, f"confirm-output --axis {axis}: {confirmed.stderr}"
        wait_until(lambda: set(a["state"] for a in self.actuators(3.0).values()) == {"ok"}, QUIET_WAIT_S,
                   "the daemon believing the confirmed outputs")
        with self.module.device.lock:
            late = self.module.device.arrivals[writes_before:]
        assert not late, f"unproven outputs were written: {late}:\n{self.daemon_log_tail()}"
        self.say(f"  unproven {unproven} counts: a target refused ({doc['error'][:80]}...), nothing written; "
                 "confirmed with nanodrift confirm-output")

    # --- the invariants -------------------------------------------------------------------------

    @invariant()
    def the_device_and_the_answers_hold(self) -> None:
        if self.daemon is None:  # before initialize
            return
        try:
            self.check()
        except AssertionError:
            note("steps and what happened:\n  " + "\n  ".join(self.step_log))
            raise

    def check(self) -> None:
        assert self.module is not None and self.client is not None and self.daemon is not None
        self.track_commands()
        device = self.module.device
        # 3. every target answered exactly once
        self.wait_answered()
        # quiet: the registers stop changing and the actuation is idle
        self.wait_quiet()
        with device.lock:
            arrivals = device.arrivals[self.checked_arrivals:]
            outputs = dict(device.outputs)
            self.misreads_pending = device.lies_left > 0
        self.checked_arrivals += len(arrivals)
        by_register = {address: axis for axis, address in self.registers.items()}
        for arrival in arrivals:
            assert arrival.address in by_register, f"a write to register {arrival.address}, no axis': {arrival}"
            # 1. every write that reached the module was inside the limits in force when it arrived
            allowed = self.allowed_limits(arrival.t)
            assert any(lim.allows(arrival.volts) for lim in allowed), (
                f"axis {by_register[arrival.address]}'s register received {arrival.raw} counts "
                f"({arrival.volts:.4f} V), outside the limits in force "
                f"({' or '.join(lim.text() for lim in allowed)}):\n{self.daemon_log_tail()}")
            # 5. ... and no faster than the slew from the value before it
            self.check_slew(by_register[arrival.address], arrival)
        # 2. once quiet, each register holds the last served command (or safe_voltage_v after a SIGTERM)
        if currently_in_test_context():
            event(f"register checked: {self.expect if self.mode == 'ok' else 'module ' + self.mode}")
        if self.mode == "ok":
            limits = self.limits
            if self.expect == "safe":
                want = dict.fromkeys(self.AXES, limits.count_for(SAFE_V))
                held = {axis: outputs[address] for axis, address in self.registers.items()}
                assert held == want, (f"no command served since start: the registers hold {held} counts, "
                                      f"not {want}:\n{self.daemon_log_tail()}")
            elif self.expect == "held":  # restarted, no command since: nothing moved
                held = {axis: outputs[address] for axis, address in self.registers.items()}
                assert held == self.held, (f"restarted with no command since: the registers hold {held} counts, "
                                           f"not the {self.held} they held:\n{self.daemon_log_tail()}")
            elif self.expect == "command":
                assert self.last_command is not None
                volts = self.volts_of(self.last_command)
                want = {axis: limits.count_for(v) for axis, v in volts.items()}
                held = {axis: outputs[address] for axis, address in self.registers.items()}
                assert held == want, (
                    f"quiet: the registers hold {held} counts, but the last command {self.last_command['id']} is "
                    f"{volts} V ({want} counts) within {limits.text()}:\n{self.daemon_log_tail()}")
            else:  # dropped: the daemon says so, and nothing was written after it
                assert self.last_command is not None and self.dropped_at is not None
                volts = self.volts_of(self.last_command)
                assert self.drop_logged(), (f"the last command ({volts} V) is outside {limits.text()} but no "
                                 f"actuator_goal_dropped line names it:\n{self.daemon_log_tail()}")
                with device.lock:
                    late = [a for a in device.arrivals if a.t > self.dropped_at]
                assert not late, f"the goal was dropped, yet the module received {late}:\n{self.daemon_log_tail()}"
        self.check_records()
        self.check_alive_and_limits()

    def check_records(self) -> None:
        """Invariant 6: no record file was deleted, and every row's targets (every axis) are those of one command
        the daemon answered the test with: a row never pairs one command's x with another's y."""
        files = set(self.records.glob("records-*.csv"))  # (not the recorder's temporary files)
        gone = sorted(p.name for p in self.record_files - files)
        assert not gone, f"record files deleted: {gone}:\n{self.daemon_log_tail()}"
        self.record_files |= files
        failed = self.log_events("record_failed")
        assert not failed, f"recording failed: {failed}"
        columns = ["target_um"] if len(self.AXES) == 1 else [f"target_{axis}_um" for axis in self.AXES]
        served = {tuple(round(c[f"{axis}_um"], 6) for axis in self.AXES) for c in self.commands()}
        for path in sorted(files):
            text = path.read_text()
            complete = text[:text.rfind("\n") + 1]  # a row being appended right now is checked next time
            for number, row in enumerate(csv.DictReader(complete.splitlines()), start=2):
                targets = tuple(round(float(row[column]), 6) for column in columns)
                named = dict(zip(columns, targets, strict=True))
                assert targets in served, (f"{path.name} row {number}: targets {named} are no command's the "
                                           f"daemon served (served: {sorted(served)})")

    def check_slew(self, axis: str, arrival: Arrival) -> None:
        """Invariant 5: every write (a failed one too: a real module may take it) is within the slew of the value
        the register last took: |dV| <= slew x (time from that write's answer to this write's arrival, as the
        module stamps them) + SLEW_TOLERANCE_V, under the fastest slew in force at either end (none when one is
        off). A write the module failed is not taken: the daemon ramps on from the value the register holds.
        Before its first write a register holds its power-up 0 V, from when the module started."""
        assert self.module is not None
        previous = self.previous_write.get(arrival.address)
        if previous is None:
            previous = Arrival(self.module.device.power_up_at, arrival.address, 0, True,
                               self.module.device.power_up_at)
        if arrival.landed:
            self.previous_write[arrival.address] = arrival
        rates = [lim.max_slew_um_per_s * lim.volts_per_um
                 for lim in (*self.allowed_limits(previous.returned), *self.allowed_limits(arrival.t))]
        if min(rates) <= 0:
            return  # the slew was off at one end: any step is allowed
        elapsed_s = arrival.t - previous.returned
        step_v = abs(arrival.volts - previous.volts)
        assert step_v <= max(rates) * elapsed_s + SLEW_TOLERANCE_V, (
            f"axis {axis}'s register was sent {arrival.volts:.4f} V ({'taken' if arrival.landed else 'failed'}) "
            f"{elapsed_s:.4f} s after it took {previous.volts:.4f} V ({step_v:.4f} V); the slew allows "
            f"{max(rates):g} V/s (+{SLEW_TOLERANCE_V} V):\n{self.daemon_log_tail()}")

    def check_alive_and_limits(self) -> None:
        """Invariant 4: alive, answering status, with the limits the test believes are in force on every axis."""
        assert self.client is not None and self.daemon is not None
        self.daemon.check_alive()
        for axis, actuator in self.actuators(5.0).items():
            shown = Limits(actuator["v_min"], actuator["v_max"], actuator["max_slew_um_per_s"],
                           actuator["volts_per_um"])
            assert shown == self.limits, f"status shows {shown.text()} on {axis}, the test applied {self.limits.text()}"
