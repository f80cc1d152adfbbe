"""``nanodrift ioc`` over Channel Access on loopback: real daemons (``nanodrift run``), the bridge as its own
process (``nanodrift ioc``), and caproto's threading client as the CA client (searches and monitors over
127.0.0.1 only, each bridge on its own free port).

A put to ``SP`` moves and ``DMOV`` goes 0 -> 1 on ``done``; ``STOP`` ends a ramp (the output holds short);
a refusal shows in ``MSG`` (and ``STATE`` where its cause is the cell's state) and leaves ``DMOV`` 1; an XY
cell serves ``<cell>:x:...`` and ``<cell>:y:...``, a put to one axis holding the other. A cell whose Zenoh
side the test scripts (a daemon that takes queries and never answers, or answers and never says ``done``)
shows that no number of such puts holds up a ``STOP`` or ``STATE``. Every wait is on a CA monitor event or a
connection, bounded.

caproto's threading client drops the CA error a failed put-callback gets (``ECA_PUTFAIL``; libca hands it to
the put's callback) and waits out its timeout instead: :meth:`CellPVs.put` says so, with ``MSG``, when a put
that should move does not complete.
"""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest
from caproto import CaprotoTimeoutError, ChannelType
from caproto.threading.client import PV, Context
from helpers.daemon_harness import REPO, TESTS, Served, free_port, run_cli, wait_until
from helpers.running_cell import VOLTS_PER_UM, RunningCell
from helpers.scripted_cell import ScriptedCell

#: a put returns once the daemon answered: seconds on an idle machine, but a loaded one (two busy cores
#: beside four test workers) once took longer than 5 s; the bound only ends a failing test
PUT_TIMEOUT_S = 20.0

PV_PREFIX = "ndtest:"
SLEW_UM_PER_S = 100.0  # a 0 -> 480 µm move ramps for 4.8 s
MEASURED_TOLERANCE_UM = 0.5  # the simulated interferometer's noise and the model's residual
#: one CA port per bridge, all known to the client's address list before it starts
PORTS = {"one": free_port(), "refuse": free_port(), "xy": free_port(), "scripted": free_port()}
CA_ENV = {
    "EPICS_CA_ADDR_LIST": " ".join(f"127.0.0.1:{port}" for port in PORTS.values()),
    "EPICS_CA_AUTO_ADDR_LIST": "NO",
    "EPICS_CAS_INTF_ADDR_LIST": "127.0.0.1",
    "EPICS_CAS_AUTO_BEACON_ADDR_LIST": "NO",
    "EPICS_CAS_BEACON_ADDR_LIST": "127.0.0.1",
    "EPICS_CA_REPEATER_PORT": str(free_port()),
}


class Bridge:
    """``nanodrift ioc`` serving one cell on its own CA port; stderr in a file."""

    def __init__(self, root: Path, endpoint: str, cell: str, port: int, *extra: str) -> None:
        env = {**os.environ, **CA_ENV, "EPICS_CA_SERVER_PORT": str(port), "EPICS_CAS_BEACON_PORT": str(port + 1),
               "PYTHONPATH": os.pathsep.join([str(TESTS), str(REPO), os.environ.get("PYTHONPATH", "")])}
        self.log_path = root / f"ioc-{cell}.log"
        self._log = open(self.log_path, "wb")
        self.proc = subprocess.Popen([sys.executable, "-m", "nanodrift.cli", "ioc", "-e", endpoint, "--cell", cell,
                                      "--pv-prefix", PV_PREFIX, *extra],
                                     stdout=subprocess.DEVNULL, stderr=self._log, env=env)
        # listening: a CA search sent now is answered at once (one sent before waits for the client's backoff)
        wait_until(self._serving, 20, f"nanodrift ioc serving cell {cell}", interval=0.05)

    def _serving(self) -> bool:
        if self.proc.poll() is not None:
            raise AssertionError(f"nanodrift ioc exited with {self.proc.returncode}:\n{self.log_path.read_text()}")
        return "nanodrift ioc: serving cell" in self.log_path.read_text(errors="replace")

    def stop(self) -> int:
        self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(10)
        finally:
            if self.proc.poll() is None:
                self.proc.kill()
                self.proc.wait(5)
            self._log.close()
        return code


def _value(response: Any) -> Any:
    data = response.data
    if response.data_type == ChannelType.CHAR:
        return bytes(data).decode("utf-8").rstrip("\0")
    if response.data_type == ChannelType.STRING:
        return data[0].decode("utf-8")
    return float(data[0])


class Monitor:
    """Every value a PV's CA monitor delivered, in order (``severity``: its alarm severity instead)."""

    def __init__(self, pv: PV, *, severity: bool = False) -> None:
        self.values: list[Any] = []
        self._cond = threading.Condition()
        self._severity = severity
        self._sub = pv.subscribe(data_type="time" if severity else "native")
        self._sub.add_callback(self._on_value)  # caproto keeps a weak reference: this object holds the method

    def _on_value(self, sub: Any, response: Any) -> None:
        with self._cond:
            self.values.append(int(response.metadata.severity) if self._severity else _value(response))
            self._cond.notify_all()

    def wait(self, predicate: Callable[[list[Any]], bool], what: str, timeout: float = 8.0) -> list[Any]:
        with self._cond:
            if not self._cond.wait_for(lambda: predicate(self.values), timeout):
                raise AssertionError(f"timed out after {timeout:g} s waiting for {what}; values {self.values}")
            return list(self.values)

    def last(self) -> Any:
        return self.wait(bool, "a first value")[-1]

    def close(self) -> None:
        self._sub.clear()


@pytest.fixture(scope="module")
def ca() -> Iterator[Context]:
    saved = {key: os.environ.get(key) for key in CA_ENV}
    os.environ.update(CA_ENV)  # the client reads its address list when its context starts
    context = Context()
    yield context
    context.disconnect()
    for key, value in saved.items():
        if value is None:
            os.environ.pop(key, None)
        else:
            os.environ[key] = value


class CellPVs:
    """One cell, its bridge, and the CA client's PVs of it."""

    def __init__(self, ca: Context, cell: str, port: int, endpoint: str, root: Path, *extra: str) -> None:
        self.bridge = Bridge(root, endpoint, cell, port, *extra)
        self.ca = ca
        self.base = f"{PV_PREFIX}{cell}:"
        self.monitors: list[Monitor] = []

    def pv(self, name: str) -> PV:
        [pv] = self.ca.get_pvs(self.base + name, timeout=10.0)
        pv.wait_for_connection(timeout=15.0)  # the bridge is up once its PVs answer
        return pv

    def put(self, name: str, value: float) -> None:
        """A put that the test expects to complete (a move answered, a stop); when it does not, the failure
        names ``MSG`` (a refused put's CA error is lost on caproto's client: it only times out)."""
        try:
            self.pv(name).write([value], wait=True, timeout=PUT_TIMEOUT_S)
        except CaprotoTimeoutError:
            msg_name = name.rsplit(":", 1)[0] + ":MSG" if ":" in name else "MSG"
            raise AssertionError(f"the put of {value} to {self.base}{name} did not complete within {PUT_TIMEOUT_S:g} s;"
                                 f" {msg_name}: {_value(self.pv(msg_name).read(data_type='native'))!r}") from None

    def monitor(self, name: str, *, severity: bool = False) -> Monitor:
        monitor = Monitor(self.pv(name), severity=severity)
        self.monitors.append(monitor)
        return monitor

    def close(self) -> int:
        for monitor in self.monitors:
            monitor.close()
        return self.bridge.stop()


def near(value_um: float) -> Callable[[list[Any]], bool]:
    return lambda values: bool(values) and abs(values[-1] - value_um) < MEASURED_TOLERANCE_UM


def is_now(value: Any) -> Callable[[list[Any]], bool]:
    return lambda values: bool(values) and values[-1] == value


def says(text: str) -> Callable[[list[Any]], bool]:
    return lambda values: bool(values) and text in values[-1]


def severity(pv: PV) -> int:
    """The PV's alarm severity (0 none, 1 minor, 2 major), read with its time metadata."""
    return int(pv.read(data_type="time").metadata.severity)


def settle_dmov(dmov: Monitor, count_before: int, what: str) -> list[Any]:
    """Wait for a 0 then a 1 after the first ``count_before`` values: one move seen from start to ``done``."""
    return dmov.wait(lambda v: 0.0 in v[count_before:] and v[-1] == 1.0, what)  # (v[-1] exists: 0.0 is in v)


# --- one axis, slewed: put, DMOV, STOP ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def one(ca: Context, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RunningCell, CellPVs]]:
    root = tmp_path_factory.mktemp("ioc-one")
    cell = RunningCell(root, "ca1", slew_um_per_s=SLEW_UM_PER_S)
    served = CellPVs(ca, "ca1", PORTS["one"], cell.endpoint, root)
    yield cell, served
    assert served.close() == 0
    assert cell.close() == 0


def test_a_put_to_sp_moves_and_dmov_goes_0_then_1_on_done(one: tuple[RunningCell, CellPVs]) -> None:
    cell, pvs = one
    dmov, rbv, msg = pvs.monitor("DMOV"), pvs.monitor("RBV"), pvs.monitor("MSG")
    assert dmov.last() == 1.0
    before = len(dmov.values)
    pvs.put("SP", 120.0)  # returns once the daemon answered
    values = settle_dmov(dmov, before, "DMOV 0 then 1 for the move to 120 µm")[before:]
    assert values.index(0.0) < len(values) - 1 and values[-1] == 1.0  # (a monitor may repeat the first 1)
    rbv.wait(near(120.0), "RBV (the interferometer) at 120 µm")
    assert msg.last() == ""
    volt = pvs.pv("VOLT").read().data[0]
    assert volt == pytest.approx(cell.last_voltage_v(), abs=1e-6)  # what the output holds
    assert volt == pytest.approx(120.0 * VOLTS_PER_UM, abs=0.02)
    assert 0.0 < pvs.pv("SIGMA").read().data[0] < 1.0
    assert pvs.pv("STATE").read().data[0].decode() == "ok"


def test_stop_ends_a_ramp_and_the_output_holds_short(one: tuple[RunningCell, CellPVs]) -> None:
    cell, pvs = one
    dmov, msg = pvs.monitor("DMOV"), pvs.monitor("MSG")
    before = len(dmov.wait(bool, "DMOV's first value"))
    pvs.put("SP", 0.0)
    settle_dmov(dmov, before, "the move to 0 µm")
    before = len(dmov.values)
    pvs.put("SP", 480.0)
    dmov.wait(lambda v: 0.0 in v[before:], "DMOV 0: the 4.8 s ramp to 480 µm began")
    pvs.put("STOP", 1)
    settle_dmov(dmov, before, "DMOV 1 after the stop")
    assert "stopped" in msg.wait(says("stopped"), "MSG saying stopped")[-1]
    assert cell.last_voltage_v() < 0.9 * 480.0 * VOLTS_PER_UM  # held on the ramp, short of the target
    assert pvs.pv("STOP").read().data[0] == 0


# --- refusals: MSG and STATE (a cell on the test's file sensors, whose T1 the test faults) ---------------


@pytest.fixture(scope="module")
def refusing(ca: Context, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[Served, CellPVs]]:
    root = tmp_path_factory.mktemp("ioc-refuse")
    cell = Served(root, "carefuse").start()
    served = CellPVs(ca, "carefuse", PORTS["refuse"], f"tcp/127.0.0.1:{cell.port}", root)
    yield cell, served
    assert served.close() == 0
    assert cell.close() == 0


def test_a_refusal_shows_in_msg_and_state_and_leaves_dmov_1(refusing: tuple[Served, CellPVs]) -> None:
    cell, pvs = refusing
    dmov, msg, state, sp = pvs.monitor("DMOV"), pvs.monitor("MSG"), pvs.monitor("STATE"), pvs.monitor("SP")
    state.wait(is_now("ok"), "STATE ok")
    pvs.pv("SP").write([900.0], wait=False)
    msg.wait(says("outside the workspace"), "MSG: the workspace refusal")
    assert "900" in msg.values[-1]
    assert severity(pvs.pv("SP")) == 2  # the refused put left SP in alarm (WRITE, MAJOR) ...
    cell.sensors.write(fault={"T1": "open circuit"})
    state.wait(is_now("degraded"), "STATE degraded: T1 faulted")  # the daemon has read the fault
    pvs.pv("SP").write([100.0], wait=False)
    msg.wait(says("T1"), "MSG naming the faulted channel")
    assert state.values[-1] == "degraded"
    assert 0.0 not in dmov.values and dmov.values[-1] == 1.0  # nothing moved
    assert 900.0 not in sp.values and 100.0 not in sp.values
    assert cell.client.commands == []  # the daemon published no command
    cell.sensors.write(fault={})
    state.wait(is_now("ok"), "STATE ok again")
    before = len(dmov.values)
    pvs.put("SP", 100.0)
    settle_dmov(dmov, before, "the move once T1 is back")
    assert msg.wait(is_now(""), "MSG empty after a reached move")[-1] == ""
    assert severity(pvs.pv("SP")) == 0  # ... until a put moved


# --- XY: a set of PVs per axis -----------------------------------------------------------------------------


@pytest.fixture(scope="module")
def xy(ca: Context, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RunningCell, CellPVs]]:
    root = tmp_path_factory.mktemp("ioc-xy")
    cell = RunningCell(root, "caxy", axes="xy")
    served = CellPVs(ca, "caxy", PORTS["xy"], cell.endpoint, root)
    yield cell, served
    assert served.close() == 0
    assert cell.close() == 0


def test_xy_serves_each_axis_and_a_put_moves_one_holding_the_other(xy: tuple[RunningCell, CellPVs]) -> None:
    cell, pvs = xy
    x_dmov, x_rbv, y_rbv = pvs.monitor("x:DMOV"), pvs.monitor("x:RBV"), pvs.monitor("y:RBV")
    y_dmov, y_sp = pvs.monitor("y:DMOV"), pvs.monitor("y:SP")
    before = len(x_dmov.wait(bool, "x:DMOV's first value"))
    # y is held where it is measured (no command yet): the bridge must have seen a y sample, else the put is
    # refused ("no setpoint known"); it serves once it has (CellView.open), or after 2 s without one
    y_rbv.wait(lambda v: any(math.isfinite(value) for value in v), "y:RBV: a first y position at the bridge")
    pvs.put("x:SP", 100.0)
    settle_dmov(x_dmov, before, "x's move to 100 µm")
    x_rbv.wait(near(100.0), "x:RBV at 100 µm")
    y_held = y_sp.wait(lambda v: any(abs(value) < 1.0 for value in v), "y:SP: the held y (about 0 µm)")[-1]
    before = len(y_dmov.values)
    pvs.put("y:SP", 200.0)
    settle_dmov(y_dmov, before, "y's move to 200 µm")
    y_rbv.wait(near(200.0), "y:RBV at 200 µm")
    assert pvs.pv("x:SP").read().data[0] == 100.0  # x kept its setpoint ...
    x_rbv.wait(near(100.0), "x:RBV still at 100 µm")  # ... and its position
    assert abs(y_held) < 1.0
    for axis in "xy":
        assert pvs.pv(f"{axis}:VOLT").read().data[0] == pytest.approx(cell.last_voltage_v(axis), abs=1e-6)


# --- a daemon that does not answer, or never says done: no put holds up STOP or STATE ---------------------

#: how long the scripted cell's bridge waits for an answer to a put (``--answer-timeout``)
ANSWER_TIMEOUT_S = 1.0
#: more puts than asyncio's default executor has threads on two cores (6): each used to hold one until done
PUTS = 8


@pytest.fixture(scope="module")
def scripted(ca: Context, tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[ScriptedCell, CellPVs]]:
    root = tmp_path_factory.mktemp("ioc-scripted")
    cell = ScriptedCell("cascript")
    served = CellPVs(ca, cell.cell, PORTS["scripted"], cell.endpoint, root, "--answer-timeout", str(ANSWER_TIMEOUT_S))
    yield cell, served
    assert served.close() == 0
    cell.close()


def test_puts_a_daemon_never_answers_fail_in_alarm_and_stop_and_state_still_work(
        scripted: tuple[ScriptedCell, CellPVs]) -> None:
    cell, pvs = scripted
    cell.answering.clear()
    msg, dmov, state = pvs.monitor("MSG"), pvs.monitor("DMOV"), pvs.monitor("STATE")
    sp_severity = pvs.monitor("SP", severity=True)
    state.wait(is_now("ok"), "STATE ok")
    for i in range(PUTS):
        pvs.pv("SP").write([10.0 + i], wait=False)  # (a failed put's CA error is lost on this client: watch MSG)
    for _ in range(PUTS):
        assert cell.asked.acquire(timeout=PUT_TIMEOUT_S), "the bridge sent every put's query"
    pvs.put("STOP", 1)  # answered while every put's query waits on the daemon
    assert cell.stops == ["{}"]
    msg.wait(says("gave no command"), "MSG: the daemon took the query and did not answer", timeout=PUT_TIMEOUT_S)
    sp_severity.wait(is_now(2), "SP in alarm (WRITE, MAJOR): the puts failed")
    before = len(state.values)
    state.wait(lambda v: len(v) > before + 1, "STATE refreshed twice more while the puts waited")  # not starved
    assert state.values[-1] == "ok"
    msg.wait(lambda v: sum("gave no command" in text for text in v) >= PUTS, "every put failed, one MSG each",
             timeout=PUT_TIMEOUT_S)  # (none left to be answered by the next test's cell)
    assert 0.0 not in dmov.values  # nothing moved


def test_moves_whose_done_never_comes_hold_no_thread_and_stop_ends_the_last(
        scripted: tuple[ScriptedCell, CellPVs]) -> None:
    cell, pvs = scripted
    cell.answering.set()
    dmov, msg = pvs.monitor("DMOV"), pvs.monitor("MSG")
    before = len(dmov.wait(bool, "DMOV's first value"))
    for i in range(PUTS):
        pvs.put("SP", 100.0 + i)  # answered at once; its done never comes
    dmov.wait(lambda v: 0.0 in v[before:], "DMOV 0: the moves are in flight")
    assert pvs.pv("SP").read().data[0] == 100.0 + PUTS - 1
    assert severity(pvs.pv("SP")) == 0  # a put that moved cleared the alarm
    stops_before = len(cell.stops)
    pvs.put("STOP", 1)
    assert len(cell.stops) == stops_before + 1
    settle_dmov(dmov, before, "DMOV 1 on the last move's done (stopped)")
    assert "stopped" in msg.wait(says("stopped"), "MSG saying stopped")[-1]


def test_ioc_refuses_an_answer_timeout_that_is_not_positive() -> None:
    result = run_ioc("-e", "tcp/127.0.0.1:1", "--answer-timeout", "0")
    assert result.returncode == 2, result.stderr
    assert "--answer-timeout must be a positive number of seconds, got 0" in result.stderr


# --- the command line's refusals: a clear sentence, exit 2, nothing served ----------------------------------


def run_ioc(*args: str) -> subprocess.CompletedProcess[str]:
    """``nanodrift ioc`` refusing its arguments or its endpoint: in this process (it exits before serving any PV)."""
    return run_cli("ioc", *args)


def test_ioc_says_when_nobody_listens_at_the_endpoint() -> None:
    port = free_port()
    result = run_ioc("-e", f"tcp/127.0.0.1:{port}")
    assert result.returncode == 2, result.stderr
    assert f"tcp/127.0.0.1:{port}" in result.stderr and "nobody is listening" in result.stderr


def test_ioc_names_a_cell_that_does_not_answer_and_the_cells_that_do(one: tuple[RunningCell, CellPVs]) -> None:
    cell, _ = one
    result = run_ioc("-e", cell.endpoint, "--cell", "nosuchcell", "--timeout", "1")
    assert result.returncode == 2, result.stderr
    assert "nosuchcell did not answer status" in result.stderr and f"the cells answering: {cell.cell}" in result.stderr
