"""The checks and rigs of the plugin contract kit (imported through :mod:`nanodrift.drivers.testing.contract`,
which has pytest rewrite this module's asserts first, so a failed check shows the values it compared).

The actuator contract (``nanodrift.drivers.base.Actuator``): ``open``/``command``/``close`` (close safe
twice and after a failed open; open again retries); ``sent_voltage(v)`` is what the device then holds
(within float tolerance), no farther from ``v`` than the device's resolution; with ``limits_v`` set,
nothing outside them reaches the device (a voltage at a limit that the device's rounding would put
outside is written as the value on the inside); ``ValueError`` and nothing written for a value the
device cannot represent; :class:`DeviceError` (no other exception) for a write the device refuses and
for a device that is gone, and the actuator works again once the device does; ``read_back`` after a
command returns what was sent, or None for a device that cannot say. Several outputs of one plugin
(``DriverPlugin.create_actuators``): each writes only its own channel, two written concurrently never
overlap an exchange on the device, closing one leaves the others working (on the same connection,
where the device can tell), and none is left once all are closed.

The sensor contract (``nanodrift.drivers.base.SensorGroup``): ``open``/``read``/``close``; ``read``
returns a reading for every name in ``names`` and no other, stamped on ``context.clock`` during the
read (an :class:`OffsetClock`, a time base no plugin could stamp by accident); ``ok`` readings carry the
device's value; a channel-level problem on a working device is a ``fault`` reading (NaN, with a
reason) while the others stay ``ok``; a device that is gone raises :class:`DeviceError` (never another
exception) from ``read``, and from ``open`` while it stays gone; ``close`` is safe twice and after a
failed ``open``; close then open again recovers once the device is back.
"""

from __future__ import annotations

import asyncio
import math
import time
from collections.abc import Awaitable, Callable, Sequence
from operator import attrgetter
from pathlib import Path
from typing import Any, ClassVar, Literal

import pytest

from nanodrift.drivers.base import Actuator, DeviceError, DriverContext, MonotonicClock, Reading, SensorGroup, State
from nanodrift.drivers.registry import load_plugin

#: a whole check's wall-clock bound: a hung device fails the check instead of the suite
CHECK_BOUND_S = 30.0
#: a single command's bound
COMMAND_BOUND_S = 10.0
#: volts per um: every command passes ``q_um = voltage_v / GAIN_V_PER_UM``
GAIN_V_PER_UM = 0.02
#: the operator's ``[v_min, v_max]`` the checks set, unless a check is about other limits
LIMITS_V = (0.0, 10.0)
#: float tolerance on voltages compared across the device's side and the actuator's
TOLERANCE_V = 1e-9


#: a check's body, ``async def test_...(self, rig)``, and the test pytest runs, ``test_...(self, tmp_path)``
CheckBody = Callable[[Any, Any], Awaitable[None]]
CheckTest = Callable[[Any, Path], None]


def check(unless: Callable[[Any], str | None] | None = None) -> Callable[[CheckBody], CheckTest]:
    """A contract check written as ``async def test_...(self, rig)``: pytest runs it as ``test_...(self, tmp_path)``,
    its body on the contract's ``rig`` built for ``tmp_path``, on a fresh event loop, with the rig's emulator
    started before it and stopped after it, whatever happened, all bounded by :data:`CHECK_BOUND_S`; skipped
    with the reason ``unless(rig)`` gives (None: the rig takes part)."""

    def test_on_a_rig(body: CheckBody) -> CheckTest:
        def test(self: Any, tmp_path: Path) -> None:
            rig = self.rig(tmp_path)
            if unless is not None and (reason := unless(rig)) is not None:
                pytest.skip(f"{rig.kind}: {reason}")

            async def with_emulator() -> None:
                await rig.start()
                try:
                    await body(self, rig)
                finally:
                    await rig.stop()

            asyncio.run(asyncio.wait_for(with_emulator(), CHECK_BOUND_S))

        test.__name__, test.__qualname__, test.__doc__ = body.__name__, body.__qualname__, body.__doc__
        return test

    return test_on_a_rig


# --- actuators ------------------------------------------------------------------------------------


class _Rig:
    """What both rigs share: built afresh for each check with the check's ``tmp_path``; ``start`` runs
    before anything is built and ``stop`` after the check, whatever happened."""

    #: the plugin's name in the ``nanodrift.drivers`` entry points (found there, as the daemon finds it)
    kind: ClassVar[str]

    def __init__(self, tmp_path: Path) -> None:
        self.tmp_path = tmp_path

    async def start(self) -> None:
        """Start the emulator (a server to listen, a pty to open): before anything is built."""

    async def stop(self) -> None:
        """Stop the emulator: after each check, also a failed one."""

    async def gone(self) -> None:
        """The device vanishes (server down, cable out): an actuator's ``open`` and ``command``, a group's
        ``read`` (and ``open``, when ``can_fail_open``) raise :class:`DeviceError`."""
        raise NotImplementedError

    async def back(self) -> None:
        """Working again after :meth:`gone` (or :meth:`ActuatorRig.refuse_writes`): the actuator must recover,
        a sensor group once closed and opened again."""
        raise NotImplementedError


class ActuatorRig(_Rig):
    """One output plugin behind a real interface: how to build its device's emulator and its actuator,
    how to read what the device received, and how to make the device misbehave."""

    #: the finest step of the device's voltage (0: takes the float as it is): ``sent_voltage`` may round
    #: this far and no farther
    resolution_v: ClassVar[float] = 0.0
    #: what ``read_back`` answers after a command: "voltage_v", "q_um" (a closed loop) or None (cannot say)
    reads_back: ClassVar[Literal["voltage_v", "q_um"] | None] = "voltage_v"
    #: (limits_v, a voltage at a limit, what the device must then hold): the rounding goes inward
    limit_case: ClassVar[tuple[tuple[float, float], float, float]]
    #: (limits_v, a voltage the device cannot represent), or None: it takes any finite value
    unrepresentable: ClassVar[tuple[tuple[float, float], float] | None] = None
    #: whether the device can refuse a write, fail to open or vanish (a simulated cell cannot); when
    #: True, implement :meth:`refuse_writes`, :meth:`gone` and :meth:`back`
    can_fail: ClassVar[bool] = True
    #: why the plugin cannot drive several outputs of one device (the multi-output checks are skipped
    #: with this reason); None: it can, and :meth:`output_options` and :meth:`output_written_v` say how
    multi_output_unsupported: ClassVar[str | None] = "the rig declares no multi-output device"

    # -- building ---------------------------------------------------------------------------------

    def options(self) -> dict[str, Any]:
        """The ``[actuator]`` table (``kind`` included), as an operator writes it: the plugin's own
        ``actuator_model`` validates it."""
        raise NotImplementedError

    def context(self) -> DriverContext:
        """The context the plugin builds with: its hubs, sections and clock (a fresh one per build, so
        nothing is shared with an earlier build by accident)."""
        return DriverContext()

    def actuator(self) -> Actuator:
        """The actuator, built the daemon's way: plugin by entry point, options through its model."""
        self.built_context = self.context()
        plugin = load_plugin(self.kind)
        assert plugin.actuator_model is not None, f"{self.kind} cannot move the stage"
        return plugin.create_actuator(plugin.actuator_model.model_validate(self.options()), self.built_context)

    # -- the device's side ------------------------------------------------------------------------

    async def held_v(self) -> float:
        """The voltage the device holds now, read on the emulator (never from the actuator)."""
        raise NotImplementedError

    def written_v(self) -> list[float]:
        """Every voltage the device was sent, in order, read on the emulator: the checks compare it
        with what ``sent_voltage`` promised."""
        raise NotImplementedError

    # -- misbehaviour (``can_fail``; also :meth:`gone` and :meth:`back`) -----------------------------

    async def refuse_writes(self) -> None:
        """The device still answers, but the next writes do not take (an exception code, an amplifier
        off, a full share): the actuator must say so with :class:`DeviceError`."""
        raise NotImplementedError

    # -- several outputs of one device (``multi_output_unsupported`` is None) ---------------------

    def output_options(self) -> list[dict[str, Any]]:
        """The ``[axes.actuator]`` tables of two or more outputs on ONE device (one hub, one port), in
        axis order: the checks see whether they share it without stepping on each other."""
        raise NotImplementedError

    def outputs_context(self) -> DriverContext:
        """The context the outputs are built with (default: :meth:`context`); the kit sets its ``axes``
        to one name per output (x, y, z), as a multi-axis cell's config does."""
        return self.context()

    def actuators(self) -> list[Actuator]:
        """The outputs, built the daemon's way for a multi-axis cell (``DriverPlugin.create_actuators``
        on every table at once, in the cell's axis order)."""
        tables = self.output_options()
        context = self.outputs_context()
        context.axes = ("x", "y", "z")[:len(tables)] if len(tables) <= 3 else tuple(f"a{i}" for i in range(len(tables)))
        self.built_context = context
        plugin = load_plugin(self.kind)
        assert plugin.actuator_model is not None, f"{self.kind} cannot move the stage"
        return plugin.create_actuators([plugin.actuator_model.model_validate(t) for t in tables], context)

    def output_written_v(self, index: int) -> list[float]:
        """Every voltage output ``index``'s own channel (its register, its axis) received, in order, read
        on the emulator: the checks see that each output writes its own channel only."""
        raise NotImplementedError

    def overlapping_exchanges(self) -> list[str]:
        """What the emulator saw of two exchanges overlapping (a request that is not whole, or that
        arrived before the answer to the one before it left), each described; empty: none. The
        default, for a device that cannot tell, is empty."""
        return []

    def connection_ids(self) -> set[str] | None:
        """The connections the device has open now, each by an id the emulator gives it, when it can tell
        (None: it cannot). Outputs of one device share one connection (a hub's): the checks expect one,
        the same one before and after an output is closed, and none once every output is closed."""
        return None


async def command(actuator: Actuator, voltage_v: float) -> None:
    """``voltage_v`` commanded the daemon's way (``q_um`` and ``x_um`` through :data:`GAIN_V_PER_UM`)."""
    await asyncio.wait_for(actuator.command(voltage_v / GAIN_V_PER_UM, voltage_v, x_um=voltage_v / GAIN_V_PER_UM),
                           COMMAND_BOUND_S)


async def opened_actuator(rig: ActuatorRig, limits_v: tuple[float, float] = LIMITS_V) -> Actuator:
    """The rig's actuator, built the daemon's way, given ``limits_v`` and opened."""
    actuator = rig.actuator()
    actuator.limits_v = limits_v
    await actuator.open()
    return actuator


async def assert_serves(rig: ActuatorRig, actuator: Actuator, voltage_v: float) -> None:
    """``voltage_v`` commanded: the device holds ``sent_voltage(voltage_v)``, and it was the last write."""
    sent = actuator.sent_voltage(voltage_v)
    await command(actuator, voltage_v)
    held = await rig.held_v()
    assert held == pytest.approx(sent, abs=TOLERANCE_V), (
        f"commanded {voltage_v!r} V: the device holds {held!r} V, sent_voltage said {sent!r} V")
    written = rig.written_v()
    assert written[-1] == pytest.approx(sent, abs=TOLERANCE_V), (
        f"commanded {voltage_v!r} V: the device's last write was {written[-1]!r} V, sent_voltage said {sent!r} V")


async def assert_output_serves(rig: ActuatorRig, outputs: Sequence[Actuator], index: int, voltage_v: float) -> None:
    """Output ``index`` commanded ``voltage_v``: its channel's last write is ``sent_voltage``, and no
    other output's channel got anything."""
    others = {i: rig.output_written_v(i) for i in range(len(outputs)) if i != index}
    sent = outputs[index].sent_voltage(voltage_v)
    await command(outputs[index], voltage_v)
    written = rig.output_written_v(index)
    assert written and written[-1] == pytest.approx(sent, abs=TOLERANCE_V), (index, voltage_v, written)
    for other, before in others.items():
        assert rig.output_written_v(other) == before, f"commanding output {index} wrote output {other}'s channel"


def assert_one_connection(rig: ActuatorRig) -> set[str] | None:
    """The outputs share one connection to the device, when it can tell; its id."""
    ids = rig.connection_ids()
    assert ids is None or len(ids) == 1, f"the outputs of one device share one connection; the device sees {ids}"
    return ids


async def assert_no_connection_left(rig: ActuatorRig, within_s: float = 2.0) -> None:
    """Every output closed: the device sees its connection go (the emulator may notice a moment later)."""
    deadline = time.monotonic() + within_s
    while (ids := rig.connection_ids()) and time.monotonic() < deadline:
        await asyncio.sleep(0.01)
    assert not ids, f"every output closed, the device still has connections {ids}"


class ActuatorContract:
    """The checks every output plugin passes. Subclass it as ``Test...`` with ``rig = YourRig``."""

    #: the rig class this subclass runs the checks against
    rig: ClassVar[type[ActuatorRig]]

    @check()
    async def test_the_device_holds_sent_voltage_after_each_command(self, rig: ActuatorRig) -> None:
        actuator = await opened_actuator(rig)
        assert actuator.description  # names the device in messages
        asked = [0.1234567, 2.5, 7.7777777, 0.0, 9.99999]
        for volts in asked:
            sent = actuator.sent_voltage(volts)
            assert abs(sent - volts) <= rig.resolution_v / 2 + TOLERANCE_V, (
                f"sent_voltage({volts!r}) = {sent!r}: farther than half the device's resolution "
                f"({rig.resolution_v!r} V)")
            await assert_serves(rig, actuator, volts)
        assert rig.written_v() == pytest.approx([actuator.sent_voltage(v) for v in asked], abs=TOLERANCE_V)
        await actuator.close()
        await actuator.close()  # safe twice

    @check()
    async def test_read_back_after_a_command_is_what_was_sent(self, rig: ActuatorRig) -> None:
        actuator = await opened_actuator(rig)
        for volts in (3.3333333, 6.25):
            await command(actuator, volts)
            back = await asyncio.wait_for(actuator.read_back(), COMMAND_BOUND_S)
            if rig.reads_back is None:
                assert back is None
            else:  # (Any: mypy takes an approx for no float; the tuples compared show in a failure)
                wanted = actuator.sent_voltage(volts) if rig.reads_back == "voltage_v" else volts / GAIN_V_PER_UM
                near: Any = pytest.approx(wanted, abs=TOLERANCE_V)
                assert back == (rig.reads_back, near)
        await actuator.close()

    @check()
    async def test_nothing_outside_limits_v_reaches_the_device(self, rig: ActuatorRig) -> None:
        (low, high), at_limit, expected = rig.limit_case
        actuator = await opened_actuator(rig, (low, high))
        assert actuator.sent_voltage(at_limit) == pytest.approx(expected, abs=TOLERANCE_V)
        await assert_serves(rig, actuator, at_limit)
        await assert_serves(rig, actuator, low)
        written = rig.written_v()
        assert len(written) == 2 and all(low <= v <= high for v in written), written
        assert written[0] == pytest.approx(expected, abs=TOLERANCE_V)
        await actuator.close()

    @staticmethod
    def _takes_any_value(rig: ActuatorRig) -> str | None:
        return "the device takes any finite voltage (unrepresentable = None)" if rig.unrepresentable is None else None

    @check(_takes_any_value)
    async def test_a_value_the_device_cannot_represent_is_a_value_error_and_nothing_is_written(
            self, rig: ActuatorRig) -> None:
        assert rig.unrepresentable is not None
        limits, volts = rig.unrepresentable
        actuator = await opened_actuator(rig)
        await assert_serves(rig, actuator, 1.5)
        held = await rig.held_v()
        before = rig.written_v()
        actuator.limits_v = limits  # the device cannot put out every voltage of these
        with pytest.raises(ValueError):
            await command(actuator, volts)
        await asyncio.sleep(0.2)  # a write under way would land by now
        assert rig.written_v() == before
        assert await rig.held_v() == held
        actuator.limits_v = LIMITS_V
        await assert_serves(rig, actuator, 2.5)  # the actuator still works
        await actuator.close()

    @staticmethod
    def _cannot_fail(rig: ActuatorRig) -> str | None:
        return None if rig.can_fail else "the device cannot refuse a write, fail to open or vanish (can_fail = False)"

    @check(_cannot_fail)
    async def test_a_write_the_device_refuses_is_a_device_error_and_the_next_one_works(self, rig: ActuatorRig) -> None:
        actuator = await opened_actuator(rig)
        await assert_serves(rig, actuator, 1.5)
        await rig.refuse_writes()
        with pytest.raises(DeviceError):
            await command(actuator, 4.5)
        await rig.back()
        await assert_serves(rig, actuator, 4.5)
        await actuator.close()

    @check(_cannot_fail)
    async def test_a_device_that_is_gone_is_a_device_error_and_a_reopen_recovers(self, rig: ActuatorRig) -> None:
        actuator = await opened_actuator(rig)
        await assert_serves(rig, actuator, 1.5)
        await rig.gone()
        with pytest.raises(DeviceError):
            await command(actuator, 4.5)
        await actuator.close()
        await rig.back()
        await actuator.open()
        await assert_serves(rig, actuator, 4.5)
        await actuator.close()

    @check(_cannot_fail)
    async def test_close_is_safe_after_a_failed_open_and_open_retries(self, rig: ActuatorRig) -> None:
        actuator = rig.actuator()
        actuator.limits_v = LIMITS_V
        await rig.gone()
        with pytest.raises(DeviceError):
            await asyncio.wait_for(actuator.open(), COMMAND_BOUND_S)
        await actuator.close()
        await actuator.close()
        await rig.back()
        await asyncio.wait_for(actuator.open(), COMMAND_BOUND_S)  # calling it again after a failure retries
        await assert_serves(rig, actuator, 3.0)
        await actuator.close()

    # -- several outputs of one plugin (DriverPlugin.create_actuators) -----------------------------

    async def _open_outputs(self, rig: ActuatorRig) -> list[Actuator]:
        outputs = rig.actuators()
        assert len(outputs) == len(rig.output_options()) >= 2, "one actuator per output table, in order"
        for output in outputs:
            output.limits_v = LIMITS_V
            await asyncio.wait_for(output.open(), COMMAND_BOUND_S)
        return outputs

    @check(attrgetter("multi_output_unsupported"))
    async def test_each_output_writes_only_its_own_channel(self, rig: ActuatorRig) -> None:
        outputs = await self._open_outputs(rig)
        for index in range(len(outputs)):
            assert rig.output_written_v(index) == [], f"output {index} was written before any command"
        for index in range(len(outputs)):
            await assert_output_serves(rig, outputs, index, 1.0 + index)
        assert_one_connection(rig)
        for index in reversed(range(len(outputs))):
            await assert_output_serves(rig, outputs, index, 5.25 - index)
        for output in outputs:
            await output.close()

    @check(attrgetter("multi_output_unsupported"))
    async def test_outputs_written_concurrently_never_overlap_an_exchange(self, rig: ActuatorRig) -> None:
        outputs = await self._open_outputs(rig)
        asked = {index: [0.5 + index + step * 0.25 for step in range(8)] for index in range(len(outputs))}

        async def drive(index: int) -> None:
            for volts in asked[index]:
                await command(outputs[index], volts)

        await asyncio.gather(*(drive(index) for index in range(len(outputs))))
        for index, output in enumerate(outputs):
            expected = [output.sent_voltage(v) for v in asked[index]]
            assert rig.output_written_v(index) == pytest.approx(expected, abs=TOLERANCE_V), index
        assert rig.overlapping_exchanges() == [], "two outputs' exchanges overlapped on the device"
        assert_one_connection(rig)
        for output in outputs:
            await output.close()

    @check(attrgetter("multi_output_unsupported"))
    async def test_closing_one_output_leaves_the_others_working(self, rig: ActuatorRig) -> None:
        for closed in range(len(rig.output_options())):  # each in turn: the one owning the port too
            outputs = await self._open_outputs(rig)
            for index in range(len(outputs)):
                await assert_output_serves(rig, outputs, index, 2.0 + index)
            shared = assert_one_connection(rig)
            await outputs[closed].close()
            await outputs[closed].close()  # safe twice, and still leaves the others alone
            for index in range(len(outputs)):
                if index != closed:
                    await assert_output_serves(rig, outputs, index, 3.5 + index)
            assert assert_one_connection(rig) == shared, (
                f"closing output {closed} took the shared connection with it (the others reconnected)")
            for output in outputs:  # all closed, the closed one again: the device is free for the next turn
                await output.close()
            await assert_no_connection_left(rig)


# --- sensors --------------------------------------------------------------------------------------


class OffsetClock(MonotonicClock):
    """Monotonic time 123456789 s ahead: neither the wall clock nor the raw monotonic clock, so a reading
    stamped on anything but ``context.clock`` is caught (it sleeps as the daemon's clock does)."""

    OFFSET_S = 123_456_789.0

    def now(self) -> float:
        return time.monotonic() + self.OFFSET_S


class SensorRig(_Rig):
    """One sensor plugin behind a real interface: what it builds, what its device holds, and how the
    device misbehaves."""

    #: the channel names the group must yield, in order
    names: ClassVar[tuple[str, ...]]
    #: each channel's role ("temperature" | "position"), as the group must report it
    roles: ClassVar[dict[str, str]]
    #: each channel's unit, as its readings must carry it
    units: ClassVar[dict[str, str]]
    #: whether ``open`` can fail (a simulated cell is always there); when True, :meth:`gone` must make it fail
    can_fail_open: ClassVar[bool] = True
    #: the time base readings must be stamped on (an OffsetClock keeps no state: one serves every rig)
    clock = OffsetClock()

    def sensor_configs(self) -> list[dict[str, Any]]:
        """The ``[[sensors]]`` tables of one group (``kind`` included), validated by the plugin's ``config_model``."""
        raise NotImplementedError

    def context(self) -> DriverContext:
        """The context the plugin builds with: keep ``clock=self.clock``, so the stamps can be checked."""
        return DriverContext(clock=self.clock)

    def check_values(self, readings: dict[str, Reading]) -> None:
        """Assert the ok readings carry what the emulator holds (in the channel's unit, scaled)."""
        raise NotImplementedError

    async def fault_channel(self) -> str:
        """Make one channel report a problem while the device keeps answering (a burnout code, an error
        line); return its name: it must read ``fault``, the others ``ok``."""
        raise NotImplementedError

    def group(self) -> SensorGroup:
        """The one group of :meth:`sensor_configs`, built the daemon's way (plugin by entry point)."""
        self.built_context = self.context()
        plugin = load_plugin(self.kind)
        configs = [plugin.config_model.model_validate(raw) for raw in self.sensor_configs()]
        [group] = plugin.create(configs, self.built_context)
        return group


async def read(group: SensorGroup) -> dict[str, Reading]:
    """One poll, bounded as the daemon bounds it (``timeout_s``) plus a margin."""
    return await asyncio.wait_for(group.read(), group.timeout_s + 2.0)


async def read_stamped(rig: SensorRig, group: SensorGroup) -> dict[str, Reading]:
    """A poll whose readings were all stamped on the rig's clock while it ran, one per name, each in its unit."""
    before = rig.clock.now()
    readings = await read(group)
    after = rig.clock.now()
    assert set(readings) == set(group.names), readings  # one per name, nothing else
    for name, reading in readings.items():
        assert before <= reading.t <= after, (name, reading.t, before, after)
        assert reading.unit == rig.units[name], (name, reading)
    return readings


def assert_all_ok(rig: SensorRig, readings: dict[str, Reading]) -> None:
    for name, reading in readings.items():
        assert reading.state is State.OK and reading.reason == "", (name, reading)
        assert math.isfinite(reading.value), (name, reading)
    rig.check_values(readings)


class SensorContract:
    """The checks every sensor plugin passes. Subclass it as ``Test...`` with ``rig = YourRig``."""

    #: the rig class this subclass runs the checks against
    rig: ClassVar[type[SensorRig]]

    @check()
    async def test_open_read_close_a_reading_per_name_on_the_context_clock(self, rig: SensorRig) -> None:
        group = rig.group()
        assert group.names == rig.names
        assert dict(group.roles) == rig.roles
        assert group.interval_s > 0 and group.timeout_s > 0
        await group.open()
        for _ in range(3):
            assert_all_ok(rig, await read_stamped(rig, group))
        await group.close()

    @check()
    async def test_close_is_safe_twice_and_the_group_reopens(self, rig: SensorRig) -> None:
        group = rig.group()
        await group.open()
        await read(group)
        await group.close()
        await group.close()
        await group.open()  # the daemon reopens a closed group
        assert_all_ok(rig, await read_stamped(rig, group))
        await group.close()

    @check()
    async def test_a_channel_problem_is_a_fault_reading_and_the_others_stay_ok(self, rig: SensorRig) -> None:
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

    @check()
    async def test_a_device_that_is_gone_raises_device_error_and_recovers_after_reopening(self, rig: SensorRig) -> None:
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

    @staticmethod
    def _always_there(rig: SensorRig) -> str | None:
        return None if rig.can_fail_open else "the device is always there (can_fail_open = False)"

    @check(_always_there)
    async def test_close_is_safe_after_a_failed_open(self, rig: SensorRig) -> None:
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
