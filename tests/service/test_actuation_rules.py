""":class:`Actuation`'s rules in process, on recording outputs, for a one-axis cell (its one axis, ``x``)
and for an XY cell (the same rules per axis, every axis of a command written before the next command's):
latest command wins, ramps start from where each axis is, the goal survives a reload, a fault on any
axis is the cell's, what a device would receive is checked against its axis' limits, the safe stop.

Every assertion is on what the recording devices received. The one-axis cell's log lines and fault texts
keep their shape (``device``, no axis named); a cell of several names the axis.
"""

from __future__ import annotations

import asyncio
import io
import itertools
import math
import time
from collections.abc import Callable, Mapping
from pathlib import Path
from typing import Any, Literal

import pytest
from helpers.log_capture import captured_logging, json_lines

from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator, DeviceError
from nanodrift.logs import get_logger
from nanodrift.motion import RAMP_PERIOD_S
from nanodrift.output_record import OutputRecords
from nanodrift.service import actuation as actuation_module
from nanodrift.service.actuation import Actuation

#: the cells every rule runs on: a one-axis cell and an XY cell
CELLS = {"one-axis": ("x",), "xy": ("x", "y")}
#: the y axis' share of each command in an XY cell (its own values, so a mix-up of axes shows)
Y_SHARE = 0.5


class RecordingActuator(Actuator):
    """Records every write (and when it started); ``holds`` is what ``read_back`` answers before the first
    write, then the last voltage written (None: the device cannot say); ``broken`` fails ``open``,
    ``unreadable`` fails ``read_back``, ``fail_writes`` the next N writes. ``journal``, shared by the axes
    of a cell, is every write of every axis in order."""

    def __init__(self, write_s: float = 0.0, description: str = "recording actuator",
                 holds: tuple[Literal["voltage_v", "q_um"], float] | None = None,
                 journal: list[tuple[str, float]] | None = None) -> None:
        self.written: list[tuple[float, float, float | None]] = []
        self.started: list[float] = []  # time.monotonic() as each write began
        self.write_s = write_s
        self.description = description
        self.holds = holds
        self.broken = self.unreadable = False
        self.fail_writes = 0
        self.opens = 0
        self.journal = journal if journal is not None else []

    async def open(self) -> None:
        self.opens += 1
        if self.broken:
            raise DeviceError(f"{self.description}: port gone")

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        if self.unreadable:
            raise DeviceError(f"{self.description}: no answer to the readback")
        if self.holds is not None and self.written:  # a readable device reads back what it was last sent
            return ("voltage_v", self.written[-1][1])
        return self.holds

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        if self.fail_writes > 0:
            self.fail_writes -= 1
            raise DeviceError(f"{self.description}: no answer")
        self.started.append(time.monotonic())
        await asyncio.sleep(self.write_s)
        self.written.append((q_um, voltage_v, x_um))
        self.journal.append((self.description, voltage_v))

    async def close(self) -> None:
        return None


class Events:
    """A logger keeping every line as (level, event, fields)."""

    def __init__(self) -> None:
        self.lines: list[tuple[str, str, dict[str, Any]]] = []

    def __getattr__(self, level: str) -> Callable[..., None]:
        return lambda event, **fields: self.lines.append((level, event, fields))

    def named(self, event: str) -> list[dict[str, Any]]:
        return [fields for _, name, fields in self.lines if name == event]


async def until(condition: Callable[[], Any], timeout: float, what: str) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > deadline:
            raise AssertionError(f"not within {timeout:g} s: {what}")
        await asyncio.sleep(0.005)


def share(axis: str) -> float:
    return 1.0 if axis == "x" else Y_SHARE


def command(actuation: Actuation, configs: Mapping[str, ActuatorConfig], q_um: float,
            x_um: float | None = None) -> None:
    """What the target path does for a served target: axis x at ``q_um``, y at its share of it."""
    qs = {a: q_um * share(a) for a in configs}
    positions = {a: x_um * share(a) for a in configs} if x_um is not None else None
    if actuation.offer(qs, {a: configs[a].voltage(q) for a, q in qs.items()}, positions):
        actuation.wake()


def devices(axes: tuple[str, ...], journal: list[tuple[str, float]] | None = None, **keys: Any
            ) -> dict[str, RecordingActuator]:
    name = keys.pop("description", "recording actuator")
    return {a: RecordingActuator(description=name if len(axes) == 1 else f"{name} {a}", journal=journal, **keys)
            for a in axes}


def on_record(directory: Path, outputs: Mapping[str, RecordingActuator], voltage_v: float) -> OutputRecords:
    """The state an earlier run left: it wrote ``voltage_v`` to every output (the proof a read-back needs)."""
    records = OutputRecords(directory, "cell")
    for axis, device in outputs.items():
        records.save(axis, device.description, voltage_v, voltage_v)
    return records


def per_axis(fields: Mapping[str, Any], name: str, axes: tuple[str, ...]) -> dict[str, Any]:
    """A line's per-axis value: a one-axis cell's is the number, a cell of several's ``{axis: value}``."""
    value = fields[name]
    if len(axes) == 1:
        assert not isinstance(value, dict), fields
        return {"x": value}
    assert isinstance(value, dict), fields
    return value


@pytest.fixture(params=list(CELLS), ids=list(CELLS))
def axes(request: pytest.FixtureRequest) -> tuple[str, ...]:
    return CELLS[request.param]


@pytest.fixture
def quick_backoff(monkeypatch: pytest.MonkeyPatch) -> None:
    """Reopens after a fault 10x sooner: the rules are about how many attempts and what they write, not how long
    the daemon waits between them (each wait was most of these tests' time)."""
    monkeypatch.setattr(actuation_module, "INITIAL_BACKOFF_S", 0.02)


def test_the_device_gets_served_commands_in_order_and_the_latest_always(axes: tuple[str, ...]) -> None:
    journal: list[tuple[str, float]] = []
    outputs = devices(axes, journal, write_s=0.005)
    configs = {a: ActuatorConfig() for a in axes}

    async def main() -> None:
        actuation = Actuation(Events())
        await actuation.start(outputs, configs)
        for i in range(200):
            command(actuation, configs, float(i), x_um=float(i) + 0.5)
            await asyncio.sleep(0.001 if i % 20 else 0.08)  # bursts, and pauses the stage catches up in
        await until(lambda: all(d.written and d.written[-1][0] == 199.0 * share(a) for a, d in outputs.items()),
                    5, "the last command on every axis")
        await actuation.stop()

    asyncio.run(main())
    for axis, device in outputs.items():
        qs = [q for q, _, _ in device.written]
        assert qs == sorted(set(qs)), "written out of order or twice"
        assert len(qs) < 200, "nothing was coalesced"
        assert all(x == q + 0.5 * share(axis) and v == configs[axis].voltage(q) for q, v, x in device.written)
    # every axis of one command goes out before any axis of the next
    names = [outputs[a].description for a in axes]
    assert [name for name, _ in journal] == names * (len(journal) // len(axes))
    for group in (journal[i:i + len(axes)] for i in range(0, len(journal), len(axes))):
        assert len({round(v / share(a), 9) for (_, v), a in zip(group, axes, strict=True)}) == 1, group


SLEW = 2000.0  # um/s: a ramp step of 40 um every RAMP_PERIOD_S, so the in-process ramps take a fraction of a second


def ramp_of(device: RecordingActuator) -> list[float]:
    return [q for q, _, _ in device.written]


def assert_never_faster(device: RecordingActuator, rate: float) -> None:
    """Each write is no further from the previous one than the rate allows for the time between them."""
    slack_s = 0.002  # the daemon times a step just before it calls the device, the device a moment later
    for (t0, (q0, _, _)), (t1, (q1, _, _)) in itertools.pairwise(zip(device.started, device.written, strict=True)):
        assert abs(q1 - q0) <= rate * (t1 - t0 + slack_s) + 1e-9, f"{q1 - q0:.3f} um in {t1 - t0:.4f} s"


@pytest.mark.parametrize(("holds", "safe_v", "start_q", "known_from"), [
    (("voltage_v", 1.0), math.nan, 50.0, "read back"),  # the output register holds 1 V: 50 um
    (("q_um", 70.0), math.nan, 70.0, "read back"),  # a closed-loop controller answers the command
    (None, 2.0, 100.0, "safe_voltage_v"),  # cannot say; a clean stop left it at safe_voltage_v
    (None, math.nan, None, "unknown"),
])
def test_the_first_move_after_start_ramps_from_where_the_stage_is(
        axes: tuple[str, ...], holds: tuple[Literal["voltage_v", "q_um"], float] | None, safe_v: float,
        start_q: float | None, known_from: str, tmp_path: Path) -> None:
    log = Events()
    configs = {a: ActuatorConfig(max_slew_um_per_s=SLEW, safe_voltage_v=safe_v) for a in axes}
    outputs = devices(axes, holds=holds)
    goal_q = 480.0  # x; y goes to its share, 240 um
    # an earlier run wrote what the device reads back: the state file proves it
    records = on_record(tmp_path, outputs, configs["x"].voltage(start_q)) if holds is not None else None

    async def main() -> None:
        actuation = Actuation(log, records=records)
        await actuation.start(outputs, configs)
        command(actuation, configs, goal_q)
        await until(lambda: all(d.written and d.written[-1][0] == goal_q * share(a) for a, d in outputs.items()),
                    10, "the target written")
        await actuation.stop()

    asyncio.run(main())
    config = configs["x"]
    voltage = None if start_q is None else config.voltage(start_q)
    [opened] = log.named("actuator_open")
    if len(axes) == 1:
        assert opened == {"device": "recording actuator", "voltage_v": voltage, "known_from": known_from}
    else:
        assert opened == {"axes": {a: d.description for a, d in outputs.items()},
                          "voltage_v": {a: voltage for a in axes}, "known_from": {a: known_from for a in axes}}
    for axis, device in outputs.items():
        assert device.limits_v == (config.v_min, config.v_max)  # the device knows the operator's limits
        target = goal_q * share(axis)
        if start_q is None:  # nothing known: the one move is written as is, and the log says so once per axis
            assert ramp_of(device) == [target]
            continue
        qs = ramp_of(device)
        assert qs[0] == pytest.approx(start_q + SLEW * RAMP_PERIOD_S)  # one ramp step from where the stage was
        assert all(0 < b - a for a, b in itertools.pairwise(qs))  # towards the target, never back
        assert len(qs) <= math.ceil((target - start_q) / (SLEW * RAMP_PERIOD_S))  # steps cover the time they took
        assert_never_faster(device, SLEW)
    told = log.named("actuator_unramped")
    if start_q is None:
        assert len(told) == len(axes)
        for line, (axis, device) in zip(told, outputs.items(), strict=True):
            assert line["voltage_v"] == config.voltage(goal_q * share(axis))
            assert "this move is not ramped" in line["reason"] and line["device"] == device.description
            assert ("axis" not in line) if len(axes) == 1 else line["axis"] == axis
    else:
        assert not told


def test_an_edit_to_another_device_forgets_the_old_devices_voltage_and_the_same_device_remembers_it(
        axes: tuple[str, ...], tmp_path: Path) -> None:
    log = Events()
    configs = {a: ActuatorConfig(max_slew_um_per_s=SLEW) for a in axes}

    async def main() -> tuple[dict[str, RecordingActuator], ...]:
        first = devices(axes, description="output A", holds=("voltage_v", 8.0))  # 400 um
        actuation = Actuation(log, records=on_record(tmp_path, first, 8.0))
        await actuation.start(first, configs)
        command(actuation, configs, 400.0)  # y: 200 um, ramped down from 400
        await until(lambda: all(d.written and d.written[-1][0] == 400.0 * share(a) for a, d in first.items()), 5,
                    "written to A")
        await actuation.stop()  # an [actuator] edit: the daemon restarts the actuation ...
        other = devices(axes, description="output B")  # ... on other outputs that cannot be read back
        await actuation.start(other, configs)
        assert actuation.axis_doc("x")["last_voltage_v"] is None  # A's voltage is not B's
        assert all(each["last_voltage_v"] is None for each in actuation.doc()["axes"].values())
        command(actuation, configs, 10.0)
        await until(lambda: all(d.written for d in other.values()), 5, "written to B")
        await actuation.stop()
        again = devices(axes, description="output B")  # a reload that keeps B: its last voltage is known
        await actuation.start(again, configs)
        command(actuation, configs, 130.0)
        await until(lambda: all(d.written and d.written[-1][0] == 130.0 * share(a) for a, d in again.items()), 5,
                    "written to B again")
        await actuation.stop()
        return first, other, again

    first, other, again = asyncio.run(main())
    assert ramp_of(first["x"]) == [400.0]  # read back at 8 V: already there
    for axis in axes:
        assert ramp_of(other[axis]) == [10.0 * share(axis)]  # not ramped from A's value: where B is is unknown
        qs = ramp_of(again[axis])  # ramped from what was last written to B
        start = 10.0 * share(axis)
        # B's first step covers no more time than passed since B's last write (not one ramp period: on a
        # loaded machine the daemon's pause grows with the write's latency, LATENCY_PAUSES)
        since_s = again[axis].started[0] - other[axis].started[-1]
        assert qs[-1] == 130.0 * share(axis) and start < qs[0] <= start + SLEW * since_s + 1e-9, (qs[0], since_s)
        assert all(0 < b - a for a, b in itertools.pairwise(qs))
        assert_never_faster(again[axis], SLEW)
    assert len(log.named("actuator_unramped")) == len(axes)
    opened = [per_axis(line, "known_from", axes) for line in log.named("actuator_open")]
    assert opened == [{a: k for a in axes} for k in ("read back", "unknown", "last written")]


def test_a_fault_at_start_ends_only_when_the_device_opens_and_reads_back_again(
        axes: tuple[str, ...], tmp_path: Path, quick_backoff: None) -> None:
    log = Events()
    configs = {a: ActuatorConfig() for a in axes}
    outputs = devices(axes, holds=("voltage_v", 1.0))
    sick = outputs[axes[-1]]  # x in a one-axis cell, y in an XY cell
    sick.broken = True

    async def main() -> None:
        actuation = Actuation(log, records=on_record(tmp_path, outputs, 1.0))
        await actuation.start(outputs, configs)
        named = "" if len(axes) == 1 else f"axis {axes[-1]}: "
        assert actuation.fault_reason == f"open failed: {named}{sick.description}: port gone"
        sick.broken, sick.unreadable = False, True  # it opens, but does not answer
        await until(lambda: "reopen failed" in (actuation.fault_reason or ""), 5, "a reopen attempt")
        await until(lambda: actuation.write_failures >= 3, 10, "more reopen attempts")
        assert "no answer to the readback" in (actuation.fault_reason or "")  # still in fault: nothing proved it works
        sick.unreadable = False
        await until(lambda: actuation.fault_reason is None, 10, "the fault ends")
        await actuation.stop()

    asyncio.run(main())
    assert all(d.written == [] for d in outputs.values())  # nothing was commanded: nothing written to end the fault
    [failed] = log.named("actuator_failed")
    [recovered] = log.named("actuator_recovered")
    assert recovered["failures"] >= 3
    if len(axes) == 1:
        assert failed["device"] == "recording actuator" and recovered["device"] == "recording actuator"
    else:
        assert "device" not in failed and failed["error"].startswith(f"open failed: axis {axes[-1]}: ")


def test_a_failure_on_one_axis_is_the_cells_fault_and_the_goal_is_written_whole_after(
        axes: tuple[str, ...]) -> None:
    journal: list[tuple[str, float]] = []
    outputs = devices(axes, journal)
    configs = {a: ActuatorConfig(v_min=-2.0, v_max=12.0) for a in axes}
    sick = axes[-1]

    async def scenario() -> None:
        actuation = Actuation(get_logger("test"))
        await actuation.start(outputs, configs)
        outputs[sick].fail_writes = 1
        command(actuation, configs, 150.0)  # 3 V on x, 1.5 V on y
        await until(lambda: actuation.fault_reason is not None, 5, "the fault")
        reason = actuation.fault_reason or ""
        if len(axes) == 1:
            assert reason == "recording actuator: no answer", reason  # a one-axis cell's text, as always
        else:
            assert reason.startswith(f"axis {sick}:"), reason
        want = [(outputs[a].description, configs[a].voltage(150.0 * share(a))) for a in axes]
        await until(lambda: journal[-len(axes):] == want, 5, "the goal written again to every axis")
        await until(lambda: actuation.fault_reason is None, 5, "recovered")
        assert all(d.opens >= 2 for d in outputs.values())  # every axis closed and reopened
        await actuation.stop()

    asyncio.run(scenario())


def test_the_goal_is_carried_over_a_reload_to_the_new_outputs(axes: tuple[str, ...]) -> None:
    journal: list[tuple[str, float]] = []
    first = devices(axes, journal, description="old")
    second = devices(axes, journal, description="new")
    configs = {a: ActuatorConfig() for a in axes}

    async def scenario() -> None:
        actuation = Actuation(get_logger("test"))
        await actuation.start(first, configs)
        command(actuation, configs, 50.0)
        await until(lambda: len(journal) == len(axes), 5, "the first goal")
        await actuation.stop()  # a reload: the drivers are stopped ...
        command(actuation, configs, 250.0)  # ... a target is served meanwhile ...
        await actuation.start(second, configs)  # ... and the new outputs get it
        want = [(second[a].description, configs[a].voltage(250.0 * share(a))) for a in axes]
        await until(lambda: journal[-len(axes):] == want, 5, "the goal on the new outputs")
        await actuation.stop()

    asyncio.run(scenario())
    assert all(not d.written or d.written[-1][0] == 50.0 * share(a) for a, d in first.items())


def test_a_goal_whose_command_a_gain_change_puts_outside_the_limits_is_dropped_not_retried(
        axes: tuple[str, ...]) -> None:
    """The serial chaos machine's finding: a goal carried over a reload that raised the gain kept its voltage
    inside the new limits, but its command (what a controller sent positions receives) meant a voltage outside
    them; the template refused it at every retry and the axis stayed in fault for good. Now it is dropped whole,
    as a goal whose voltage the new limits forbid: nothing written, the stage holds, no fault."""
    journal: list[tuple[str, float]] = []
    first = devices(axes, journal, description="old")
    second = devices(axes, journal, description="new")
    before = {a: ActuatorConfig(volts_per_um=0.01, v_min=-1.0, v_max=10.0) for a in axes}
    after = {a: ActuatorConfig(volts_per_um=0.025, v_min=-0.25, v_max=5.0) for a in axes}
    q_um = -20.0  # -0.2 V at 0.01 V/um (inside both), but -0.5 V at 0.025 V/um (outside the new limits)

    async def scenario(stream: io.StringIO) -> None:
        actuation = Actuation(get_logger("test"))
        await actuation.start(first, before)
        await actuation.stop()  # a reload: the drivers are stopped ...
        command(actuation, before, q_um)  # ... a target is served under the old gain ...
        await actuation.start(second, after)  # ... and the new outputs, at the new gain, get the goal
        await until(lambda: "actuator_goal_dropped" in stream.getvalue(), 5, "the carried goal dropped")
        assert actuation.fault_reason is None and not journal
        command(actuation, after, 40.0)  # the next target: served at once (1 V)
        want = [(second[a].description, after[a].voltage(40.0 * share(a))) for a in axes]
        await until(lambda: journal[-len(axes):] == want, 5, "the next goal on the new outputs")
        await actuation.stop()

    with captured_logging() as stream:
        asyncio.run(scenario(stream))
    dropped = [e for e in json_lines(stream) if e["event"] == "actuator_goal_dropped"]
    assert len(dropped) == 1, stream.getvalue()
    assert all(volts > -0.25 for _, volts in journal), journal  # the carried goal never reached a device
    assert [v for d, v in journal if d.startswith("new")] == [after[a].voltage(40.0 * share(a)) for a in axes]


class TakesPositionsUpTo(RecordingActuator):
    """A device whose command carries the target position and refuses one beyond ``bound_um`` (a template's
    ``x_um`` field kept within the command range): ValueError, nothing written."""

    bound_um = 300.0

    def check_command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        if x_um is not None and x_um > self.bound_um:
            raise ValueError(f"{self.description}: x_um = {x_um} um is outside the command range")

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        self.check_command(q_um, voltage_v, x_um=x_um)
        await super().command(q_um, voltage_v, x_um=x_um)


def test_a_goal_a_field_of_the_devices_command_cannot_carry_is_dropped_before_anything_is_written(
        axes: tuple[str, ...]) -> None:
    """The serial chaos machine's second finding: a target position beyond what the template's ``x_um`` field may
    carry made every write raise ValueError (after the state record had been written): the axis stayed in fault,
    its read-back never matching the record again. Now the goal is dropped whole before anything is recorded."""
    journal: list[tuple[str, float]] = []
    outputs = {a: TakesPositionsUpTo(description=f"bounded {a}", journal=journal) for a in axes}
    configs = {a: ActuatorConfig() for a in axes}

    async def scenario(stream: io.StringIO) -> None:
        actuation = Actuation(get_logger("test"))
        await actuation.start(outputs, configs)
        command(actuation, configs, 310.0, x_um=320.0)  # x beyond 300 um on x (y's share, 0.5, is inside)
        await until(lambda: "actuator_goal_dropped" in stream.getvalue(), 5, "the goal dropped")
        assert actuation.fault_reason is None and not journal, journal
        command(actuation, configs, 100.0, x_um=110.0)
        want = [(outputs[a].description, configs[a].voltage(100.0 * share(a))) for a in axes]
        await until(lambda: journal[-len(axes):] == want, 5, "the next goal written")
        await actuation.stop()

    with captured_logging() as stream:
        asyncio.run(scenario(stream))


class RoundsOutward(RecordingActuator):
    """A device whose representation of a voltage lands 0.05 V above it (a template that rounds up)."""

    def sent_voltage(self, voltage_v: float) -> float:
        return voltage_v + 0.05


def test_what_the_device_would_receive_is_checked_against_the_limits_not_what_was_asked(
        axes: tuple[str, ...]) -> None:
    """Issue 16.8: the value after the device's own rounding must lie inside [v_min, v_max], or nothing is sent
    (on no axis)."""
    log = Events()
    configs = {a: ActuatorConfig(v_max=10.0) for a in axes}
    outputs = {a: (RoundsOutward if a == "x" else RecordingActuator)(
        description="recording actuator" if len(axes) == 1 else f"recording actuator {a}") for a in axes}

    async def main() -> None:
        actuation = Actuation(log)
        await actuation.start(outputs, configs)
        command(actuation, configs, 100.0)  # 2.0 V, sent as 2.05 V: inside
        await until(lambda: all(len(d.written) == 1 for d in outputs.values()), 5, "the first command written")
        command(actuation, configs, 499.0)  # 9.98 V would be sent as 10.03 V on x: outside
        await until(lambda: actuation.fault_reason is not None, 5, "the refusal")
        await actuation.stop()

    asyncio.run(main())
    assert [v for _, v, _ in outputs["x"].written] == [2.0]  # nothing sent for 9.98 V
    assert all(len(d.written) == 1 for d in outputs.values())  # nothing of that command, on any axis
    [failed] = log.named("actuator_failed")
    assert "would be sent as 10.030000 V, outside [-2, 10] V: nothing written" in failed["error"]
    assert failed["error"].startswith("ValueError: " if len(axes) == 1 else "axis x: ")


def test_a_value_a_device_would_receive_outside_its_axis_limits_is_never_sent() -> None:
    """Each axis against its own limits: 9.8 V is inside x's and, sent as 10.3 V, outside y's."""
    journal: list[tuple[str, float]] = []
    outputs = devices(("x", "y"), journal)
    outputs["y"].sent_voltage = lambda v: v + 0.5  # type: ignore[method-assign]
    configs = {"x": ActuatorConfig(v_min=-2.0, v_max=12.0), "y": ActuatorConfig(v_min=0.0, v_max=10.0)}

    async def scenario() -> None:
        actuation = Actuation(get_logger("test"))
        await actuation.start(outputs, configs)
        if actuation.offer({"x": 490.0, "y": 490.0}, {"x": 9.8, "y": 9.8}):
            actuation.wake()
        await until(lambda: actuation.fault_reason is not None, 5, "the fault")
        assert "axis y" in (actuation.fault_reason or "") and "10.3" in (actuation.fault_reason or "")
        assert not journal  # nothing of that command, on any axis
        await actuation.stop()

    asyncio.run(scenario())


def test_a_reload_onto_an_output_that_opens_ends_the_fault_and_says_so(axes: tuple[str, ...]) -> None:
    """Issue 16.11: a reload that cleared an actuator fault logged no ``actuator_recovered``."""
    log = Events()
    configs = {a: ActuatorConfig() for a in axes}

    async def main() -> None:
        actuation = Actuation(log)
        dead = devices(axes, description="output A")
        dead[axes[-1]].broken = True
        await actuation.start(dead, configs)
        assert actuation.fault_reason is not None and len(log.named("actuator_failed")) == 1
        await actuation.stop()  # an [actuator] edit: the daemon restarts the actuation ...
        fixed = devices(axes, description="output B")  # ... on outputs that open
        await actuation.start(fixed, configs)
        assert actuation.fault_reason is None
        await actuation.stop()

    asyncio.run(main())
    [recovered] = log.named("actuator_recovered")
    assert recovered["via"] == "reload" and recovered["failures"] >= 1
    if len(axes) == 1:
        assert recovered["device"] == "output B"


def test_the_stop_ramps_every_axis_to_its_safe_voltage(axes: tuple[str, ...]) -> None:
    log = Events()
    journal: list[tuple[str, float]] = []
    outputs = devices(axes, journal)
    safe = {"x": ActuatorConfig(v_min=-2.0, v_max=12.0, safe_voltage_v=0.0, max_slew_um_per_s=200.0),
            "y": ActuatorConfig(v_min=0.0, v_max=10.0, safe_voltage_v=1.0, max_slew_um_per_s=200.0)}
    configs = {a: safe[a] for a in axes}

    async def scenario() -> None:
        actuation = Actuation(log, safe_budget_s=5.0)
        await actuation.start(outputs, configs)
        if actuation.offer({a: 100.0 for a in axes}, {a: 2.0 + (a == "y") for a in axes}):
            actuation.wake()
        await until(lambda: all(d.written and d.written[-1][1] == 2.0 + (a == "y") for a, d in outputs.items()),
                    5, "the goal")
        for device in outputs.values():
            device.written.clear()
        await actuation.stop(final=True)

    asyncio.run(scenario())
    for axis, device in outputs.items():
        steps = [v for _, v, _ in device.written]
        assert steps[-1] == configs[axis].safe_voltage_v
        assert len(steps) >= 3 and all(b < a for a, b in itertools.pairwise(steps))  # ramped down
    [done] = log.named("actuator_safe")
    assert per_axis(done, "voltage_v", axes) == {a: configs[a].safe_voltage_v for a in axes}


def test_an_output_nothing_confirms_is_never_written_and_refuses_until_confirmed(
        axes: tuple[str, ...], tmp_path: Path, quick_backoff: None) -> None:
    """Issue 26.5: a claim the state file contradicts, or a state file that cannot be read, moves nothing; a
    confirmation (the record rewritten) ends the fault at the next retry."""
    log = Events()
    configs = {a: ActuatorConfig(max_slew_um_per_s=SLEW, safe_voltage_v=0.0) for a in axes}
    outputs = devices(axes, holds=("voltage_v", 10.0))  # every output claims 10 V
    records = on_record(tmp_path, outputs, 0.0)  # the daemon wrote 0 V last
    sick = axes[-1]
    unreadable = records.path(sick)
    assert unreadable is not None
    unreadable.write_text("{not json")  # and one state file cannot be read

    async def main() -> None:
        actuation = Actuation(log, records=records, safe_budget_s=0.5)
        await actuation.start(outputs, configs)
        reason = actuation.fault_reason or ""
        assert "read back 10.0000 V, but 0.0000 V was the last value written (state file)" in reason \
            or "the state file cannot be read" in reason, reason
        assert "nanodrift confirm-output" in reason and str(tmp_path) in reason
        command(actuation, configs, 100.0)  # (the target path refuses it; the goal must not move anything either)
        await until(lambda: actuation.write_failures >= 2, 10, "a retry that still cannot prove it")
        assert all(not d.written for d in outputs.values())
        for axis, device in outputs.items():  # an operator confirms what each output holds
            records.save(axis, device.description, 10.0, 10.0)
        await until(lambda: actuation.fault_reason is None, 15, "the confirmed outputs believed")
        await actuation.stop(final=True)

    asyncio.run(main())
    for axis, device in outputs.items():  # then the goal and the safe stop ramp from the confirmed 10 V
        steps = [v for _, v, _ in device.written]
        assert steps and abs(steps[0] - 10.0) <= SLEW * 0.02 * RAMP_PERIOD_S + 1e-9, (axis, steps)
        assert_never_faster(device, SLEW)


def test_the_stop_takes_each_axis_to_its_safe_voltage_on_its_own_and_says_which_failed() -> None:
    """Issue 26.8: y's module dead at the stop never holds x energised; the log names what was reached and what not."""
    log = Events()
    outputs = devices(("x", "y"))
    configs = {a: ActuatorConfig(safe_voltage_v=0.0, max_slew_um_per_s=200.0) for a in ("x", "y")}

    async def scenario() -> None:
        actuation = Actuation(log, safe_budget_s=1.0)
        await actuation.start(outputs, configs)
        if actuation.offer({"x": 100.0, "y": 100.0}, {"x": 2.0, "y": 2.0}):
            actuation.wake()
        await until(lambda: all(d.written and d.written[-1][1] == 2.0 for d in outputs.values()), 5, "the goal")
        outputs["y"].fail_writes, outputs["y"].broken = 1000, True  # y's module is gone
        await actuation.stop(final=True)

    asyncio.run(scenario())
    x_steps = [v for _, v, _ in outputs["x"].written]
    assert x_steps[-1] == 0.0 and outputs["y"].written[-1][1] == 2.0
    [reached] = log.named("actuator_safe")
    assert reached["voltage_v"] == {"x": 0.0}, reached
    [failed] = log.named("actuator_safe_failed")
    assert failed["voltage_v"] == {"y": 0.0} and failed["last_voltage_v"] == {"y": 2.0}, failed
    assert "axis y" in failed["error"] and "port gone" in failed["error"], failed


# --- how each served command ends: exactly one done each ---------------------------------------


class Dones:
    """Every ``done`` the actuation tells, as (id, state, held voltages, error)."""

    def __init__(self, actuation: Actuation) -> None:
        self.told: list[tuple[Any, str, dict[str, float | None], str | None]] = []
        actuation.done_listeners.append(lambda goal, state, held, error: self.told.append((goal.id, state, held,
                                                                                          error)))

    def of(self, target_id: Any) -> list[tuple[Any, str, dict[str, float | None], str | None]]:
        return [d for d in self.told if d[0] == target_id]

    def state(self, target_id: Any) -> str | None:
        mine = self.of(target_id)
        assert len(mine) <= 1, f"more than one done for {target_id}: {mine}"
        return mine[0][1] if mine else None

    def ids(self) -> list[Any]:
        return [d[0] for d in self.told]


def serve(actuation: Actuation, configs: Mapping[str, ActuatorConfig], q_um: float, target_id: Any) -> None:
    """A served target with its id: x at ``q_um``, y at its share."""
    qs = {a: q_um * share(a) for a in configs}
    if actuation.offer(qs, {a: configs[a].voltage(q) for a, q in qs.items()}, None, target_id):
        actuation.wake()


def volts(configs: Mapping[str, ActuatorConfig], q_um: float) -> dict[str, float]:
    return {a: configs[a].voltage(q_um * share(a)) for a in configs}


def test_a_flood_during_a_slow_ramp_ends_every_command_once_superseded_and_the_last_reached(
        axes: tuple[str, ...]) -> None:
    configs = {a: ActuatorConfig(max_slew_um_per_s=500.0) for a in axes}  # 0 -> 400 um: 0.8 s
    outputs = devices(axes, holds=("voltage_v", 0.0))

    async def main() -> Dones:
        actuation = Actuation(Events())
        dones = Dones(actuation)
        await actuation.start(outputs, configs)
        serve(actuation, configs, 400.0, 1)
        await until(lambda: all(len(d.written) >= 3 for d in outputs.values()), 5, "the ramp under way")
        for i in range(2, 31):
            serve(actuation, configs, 400.0 + i, i)
            await asyncio.sleep(0.001 if i % 10 else 0.03)
        await until(lambda: dones.state(30) is not None, 10, "the last command's done")
        await actuation.stop()
        return dones

    dones = asyncio.run(main())
    assert sorted(dones.ids()) == list(range(1, 31))  # exactly one done per served command
    assert all(dones.state(i) == "superseded" for i in range(1, 30))
    [(_, state, held, error)] = dones.of(30)
    assert state == "reached" and error is None
    for axis, device in outputs.items():  # what the outputs hold: the last command, as the devices received it
        assert device.written[-1][1] == volts(configs, 430.0)[axis] == held[axis]
        assert all(v < volts(configs, 431.0)[axis] for _, v, _ in device.written)


def test_a_stop_mid_ramp_holds_every_output_ends_the_command_stopped_and_the_next_moves_again(
        axes: tuple[str, ...]) -> None:
    configs = {a: ActuatorConfig(max_slew_um_per_s=200.0) for a in axes}  # 0 -> 400 um: 2 s
    outputs = devices(axes, holds=("voltage_v", 0.0))
    old_goal = volts(configs, 400.0)

    async def main() -> tuple[Dones, dict[str, float | None], dict[str, int]]:
        log = Events()
        actuation = Actuation(log)
        dones = Dones(actuation)
        await actuation.start(outputs, configs)
        serve(actuation, configs, 400.0, "far")
        await until(lambda: all(len(d.written) >= 5 for d in outputs.values()), 5, "the ramp under way")
        held = await actuation.halt()
        assert dones.state("far") == "stopped"
        counts = {a: len(d.written) for a, d in outputs.items()}
        again = await actuation.halt()  # nothing moves: a no-op that still answers
        assert again == held and len(dones.told) == 1
        await actuation.stop()  # a reload after the stop: the old goal is not carried over ...
        await actuation.start(outputs, configs)
        await actuation.halt()  # (the drive loop has run: a halt is answered from it)
        assert {a: len(d.written) for a, d in outputs.items()} == counts  # ... nothing was written
        assert len(log.named("actuator_stopped")) == 1
        serve(actuation, configs, 50.0, "next")  # the next target moves again
        await until(lambda: dones.state("next") is not None, 10, "the next command's done")
        await actuation.stop()
        return dones, held, counts

    dones, held, counts = asyncio.run(main())
    [(_, _, stopped_held, error)] = dones.of("far")
    assert error is None and stopped_held == held
    assert dones.state("next") == "reached"
    for axis, device in outputs.items():
        sent = [v for _, v, _ in device.written]
        at_stop = sent[counts[axis] - 1]
        assert held[axis] == at_stop and 0.0 < at_stop < old_goal[axis]  # held where the ramp was
        assert old_goal[axis] not in sent  # the old goal was never reached
        after = sent[counts[axis]:]
        assert after and after[-1] == volts(configs, 50.0)[axis]
        if at_stop > after[-1]:  # from where it was held towards the next goal, by ramp steps, never back up
            assert all(b < a for a, b in itertools.pairwise([at_stop, *after]))
            assert at_stop - after[0] <= 200.0 * 0.02 * 5 * RAMP_PERIOD_S + 1e-9
        assert_never_faster(device, 200.0)


def test_a_fault_ends_the_command_failed_once_and_the_goal_is_still_written_after(axes: tuple[str, ...]) -> None:
    journal: list[tuple[str, float]] = []
    outputs = devices(axes, journal)
    configs = {a: ActuatorConfig() for a in axes}
    sick = axes[-1]

    async def main() -> Dones:
        actuation = Actuation(Events())
        dones = Dones(actuation)
        await actuation.start(outputs, configs)
        outputs[sick].fail_writes = 1
        serve(actuation, configs, 150.0, 5)
        await until(lambda: dones.state(5) is not None, 5, "the command's done")
        want = [(outputs[a].description, v) for a, v in volts(configs, 150.0).items()]
        await until(lambda: journal[-len(axes):] == want and actuation.fault_reason is None, 10,
                    "the goal written after the recovery")
        await actuation.halt()
        await actuation.stop()
        return dones

    dones = asyncio.run(main())
    [(_, state, _, error)] = dones.of(5)  # one done, even though the goal was written later
    assert state == "failed" and error is not None and "no answer" in error
    assert error.startswith("recording actuator: " if len(axes) == 1 else f"axis {sick}: ")


def test_the_daemon_stop_ends_a_command_in_flight_stopped_or_failed_when_the_outputs_are_in_fault(
        axes: tuple[str, ...]) -> None:
    configs = {a: ActuatorConfig(max_slew_um_per_s=200.0, safe_voltage_v=0.0) for a in axes}

    async def main() -> tuple[Dones, Dones]:
        moving = devices(axes, holds=("voltage_v", 0.0))
        actuation = Actuation(Events(), safe_budget_s=5.0)
        mid_ramp = Dones(actuation)
        await actuation.start(moving, configs)
        serve(actuation, configs, 400.0, "moving")
        await until(lambda: all(len(d.written) >= 3 for d in moving.values()), 5, "the ramp under way")
        await actuation.stop(final=True)

        broken = devices(axes)
        broken[axes[-1]].broken = True
        faulted = Actuation(Events(), safe_budget_s=0.5)
        in_fault = Dones(faulted)
        await faulted.start(broken, configs)
        serve(faulted, configs, 100.0, "never")  # served before the fault was noticed, never written
        await faulted.stop(final=True)
        return mid_ramp, in_fault

    mid_ramp, in_fault = asyncio.run(main())
    [(_, state, _, error)] = mid_ramp.of("moving")
    assert state == "stopped" and error is None
    [(_, state, _, error)] = in_fault.of("never")
    assert state == "failed" and error is not None and "port gone" in error


def test_a_reload_mid_ramp_carries_the_command_over_and_it_ends_once(axes: tuple[str, ...]) -> None:
    configs = {a: ActuatorConfig(max_slew_um_per_s=500.0) for a in axes}
    outputs = devices(axes, holds=("voltage_v", 0.0))

    async def main() -> Dones:
        actuation = Actuation(Events())
        dones = Dones(actuation)
        await actuation.start(outputs, configs)
        serve(actuation, configs, 400.0, 9)
        await until(lambda: all(len(d.written) >= 3 for d in outputs.values()), 5, "the ramp under way")
        await actuation.stop()  # a reload mid-ramp
        assert dones.told == []
        await actuation.start(outputs, configs)  # the same outputs: they read back where the ramp left them
        await until(lambda: dones.state(9) is not None, 10, "the command's done")
        await actuation.stop()
        return dones

    dones = asyncio.run(main())
    [(_, state, held, _)] = dones.of(9)
    assert state == "reached" and held == volts(configs, 400.0)
    for device in outputs.values():
        assert_never_faster(device, 500.0)
        assert all(b > a for a, b in itertools.pairwise([v for _, v, _ in device.written]))


def test_with_no_outputs_each_command_is_reached_as_it_is_published(axes: tuple[str, ...]) -> None:
    """Every axis ``kind = "zenoh"`` (or no actuator): no device to verify, the published command is the actuation."""
    configs = {a: ActuatorConfig() for a in axes}

    async def main() -> tuple[Dones, dict[str, float | None]]:
        actuation = Actuation(Events())
        dones = Dones(actuation)
        await actuation.start({}, configs)
        for i in range(1, 21):
            serve(actuation, configs, 10.0 * i, i)
            await until(lambda i=i: dones.state(i) is not None, 5, f"command {i}'s done")
        held = await actuation.halt()
        await actuation.stop(final=True)
        return dones, held

    dones, held = asyncio.run(main())
    assert [(i, s) for i, s, _, _ in dones.told] == [(i, "reached") for i in range(1, 21)]
    assert all(h == volts(configs, 10.0 * i) for i, _, h, _ in dones.told)
    assert held == volts(configs, 200.0)


def test_a_stop_during_a_fault_is_answered_at_once_and_the_recovered_outputs_move_nothing(
        axes: tuple[str, ...], tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    configs = {a: ActuatorConfig() for a in axes}
    outputs = devices(axes, holds=("voltage_v", 1.0))
    sick = outputs[axes[-1]]
    # a backoff already past a second at the first reopen (as after a few failed ones, without waiting for them)
    monkeypatch.setattr(actuation_module, "INITIAL_BACKOFF_S", 2.0)

    async def main() -> tuple[Dones, float]:
        actuation = Actuation(Events(), records=on_record(tmp_path, outputs, 1.0))
        dones = Dones(actuation)
        await actuation.start(outputs, configs)
        sick.fail_writes, sick.broken = 1, True  # its next write fails, and it does not open again
        serve(actuation, configs, 200.0, "lost")  # failed, and the goal waits for the device
        await until(lambda: dones.state("lost") == "failed", 15, "the fault seen, the backoff begun")
        serve(actuation, configs, 300.0, "waiting")  # served just before the fault was seen: pending
        # the backoff after this stop is short: the recovery below need not wait out a doubled one
        monkeypatch.setattr(actuation_module, "MAX_BACKOFF_S", 0.02)
        asked = time.monotonic()
        held = await asyncio.wait_for(actuation.halt(), 10)
        answered_s = time.monotonic() - asked
        assert dones.state("waiting") == "stopped"
        assert held[axes[-1]] is None and all(held[a] is not None for a in axes[:-1])  # a failed write: unknown
        counts = [len(d.written) for d in outputs.values()]
        sick.broken = False
        await until(lambda: actuation.fault_reason is None, 20, "recovered")
        await actuation.halt()  # (the drive loop has run since)
        assert [len(d.written) for d in outputs.values()] == counts  # the stopped goal is not written
        await actuation.stop()
        return dones, answered_s

    dones, answered_s = asyncio.run(main())
    assert answered_s < 1.0, f"the stop waited {answered_s:.2f} s for the backoff"
    assert [d[0] for d in dones.told] == ["lost", "waiting"]


def test_a_stop_ends_the_commands_served_before_it_never_one_served_after_it(axes: tuple[str, ...]) -> None:
    configs = {a: ActuatorConfig(max_slew_um_per_s=500.0) for a in axes}
    outputs = devices(axes, holds=("voltage_v", 0.0))

    async def main() -> tuple[Dones, dict[str, float | None]]:
        actuation = Actuation(Events())
        dones = Dones(actuation)
        await actuation.start(outputs, configs)
        serve(actuation, configs, 400.0, "before")
        await until(lambda: all(len(d.written) >= 3 for d in outputs.values()), 5, "the ramp under way")
        mark = actuation.stop_mark()  # the stop arrives (on Zenoh's thread) ...
        serve(actuation, configs, 100.0, "after")  # ... then a target, answered before the loop runs the stop
        held = await actuation.halt(mark)
        await until(lambda: dones.state("after") is not None, 10, "the later command's done")
        await actuation.stop()
        return dones, held

    dones, held = asyncio.run(main())
    assert [(i, s) for i, s, _, _ in dones.told] == [("before", "stopped"), ("after", "reached")]
    for axis, device in outputs.items():
        assert device.written[-1][1] == volts(configs, 100.0)[axis]
        assert held[axis] is not None and held[axis] < volts(configs, 400.0)[axis]


def test_a_flood_while_the_drivers_are_swapped_ends_each_replaced_command_before_the_outputs_are_back(
        axes: tuple[str, ...]) -> None:
    """Nothing piles up during a reload: the commands a newer one replaced end ``superseded`` from the loop
    while no drive loop runs; the newest is written once the outputs are back, and ends ``reached``."""
    configs = {a: ActuatorConfig() for a in axes}
    outputs = devices(axes, holds=("voltage_v", 0.0))

    async def main() -> tuple[Dones, int]:
        actuation = Actuation(Events())
        dones = Dones(actuation)
        await actuation.start(outputs, configs)
        await actuation.stop()  # a reload: the drivers are swapped
        wakes = 0
        for i in range(1, 501):
            if actuation.offer({a: 1.0 * share(a) for a in axes}, volts(configs, 1.0), None, i):
                wakes += 1
                asyncio.get_running_loop().call_soon(actuation.wake)  # as the target path does
            if i % 50 == 0:
                await asyncio.sleep(0)  # the loop runs between bursts
        await until(lambda: len(dones.told) == 499, 5, "every replaced command told")
        assert all(d.written == [] for d in outputs.values())  # nothing written while the drivers are away
        await actuation.start(outputs, configs)
        await until(lambda: dones.state(500) is not None, 5, "the newest command's done")
        await actuation.stop()
        return dones, wakes

    dones, wakes = asyncio.run(main())
    assert [(i, s) for i, s, _, _ in dones.told] == [*((i, "superseded") for i in range(1, 500)), (500, "reached")]
    assert wakes <= 10  # one wake per burst, not per target
    assert all(d.written[-1][1] == volts(configs, 1.0)[a] for a, d in outputs.items())


def test_a_position_sensor_proves_a_read_back_only_with_a_stated_tolerance_and_never_an_unreadable_record(
        axes: tuple[str, ...], tmp_path: Path) -> None:
    """No state file, every output claims 8 V (400 µm), every axis' sensor reads 401 µm: nothing is proved
    without ``position_proof_tolerance_um`` (the sensor is not even asked), each axis is proved by its own sensor
    with 5 µm, and a state file that cannot be read is never overruled by a sensor."""
    asked: list[str] = []

    async def witness(axis: str) -> tuple[str, float]:
        asked.append(axis)
        return f"P{axis}", 401.0

    def configs(tolerance_um: float) -> dict[str, ActuatorConfig]:
        return {a: ActuatorConfig(max_slew_um_per_s=SLEW, position_proof_tolerance_um=tolerance_um) for a in axes}

    async def started(tolerance_um: float, records: OutputRecords) -> tuple[Actuation, Events,
                                                                             dict[str, RecordingActuator]]:
        log, outputs = Events(), devices(axes, holds=("voltage_v", 8.0))
        actuation = Actuation(log, records=records, position_witness=witness)
        await actuation.start(outputs, configs(tolerance_um))
        return actuation, log, outputs

    async def main() -> None:
        unstated, _, outputs = await started(math.nan, OutputRecords(tmp_path / "a", "cell"))
        assert "on a first start" in (unstated.fault_reason or "") and asked == []
        await unstated.stop()
        assert all(not d.written for d in outputs.values())

        proved, log, outputs = await started(5.0, OutputRecords(tmp_path / "b", "cell"))
        assert proved.fault_reason is None and asked == list(axes), proved.fault_reason
        lines = {line["axis"]: line for line in log.named("output_proved")}
        assert {a: (lines[a]["by"], lines[a]["sensor"]) for a in axes} == {a: ("position_sensor", f"P{a}")
                                                                           for a in axes}
        assert all(lines[a]["measured_um"] == 401.0 and lines[a]["tolerance_um"] == 5.0 for a in axes), lines
        await proved.stop()
        assert all(not d.written for d in outputs.values())  # believing moves nothing

        asked.clear()
        records = OutputRecords(tmp_path / "c", "cell")
        (tmp_path / "c").mkdir()
        unreadable = records.path(axes[-1])
        assert unreadable is not None
        unreadable.write_text("{not json")
        refused, _, _ = await started(5.0, records)
        assert "the state file cannot be read" in (refused.fault_reason or "") and axes[-1] not in asked
        await refused.stop()

    asyncio.run(main())
