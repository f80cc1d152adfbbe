"""The string a serial command template writes is what is checked against the limits (issue 16, problem 8).

``command = "SVA 1 {voltage_v:.1f}\\n"`` with ``v_max = 9.17`` used to send ``SVA 1 9.2``: the limit was
checked before the template rounded. Now the number the line carries is parsed back and kept inside
``limits_v`` (rounded toward the inside at the template's precision); the readback is compared with it.
Device-side assertions over a real pty, and a property over random templates and limits.
"""

from __future__ import annotations

import asyncio
import re
from collections.abc import Awaitable, Iterator
from decimal import Decimal
from pathlib import Path

import pytest
from helpers.budget import examples
from helpers.serial_helpers import FakeGcsController
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from nanodrift.drivers.base import DriverContext
from nanodrift.drivers.serial_line.actuator import SerialLineActuator
from nanodrift.drivers.serial_line.config import SerialLineActuatorConfig
from nanodrift.drivers.serial_line.plugin import PLUGIN
from nanodrift.drivers.serial_line.template import CommandTemplate

#: the number in a line as the device reads it (independent of the driver's own parsing)
DEVICE_NUMBER = re.compile(r"SVA 1\s+(\S+)$")  # GCS splits its arguments on whitespace


def run(coro: Awaitable[None], timeout: float = 30.0) -> None:
    asyncio.run(asyncio.wait_for(coro, timeout))


@pytest.fixture
def controller(tmp_path: Path) -> Iterator[FakeGcsController]:
    fake = FakeGcsController(tmp_path / "ttyPI")
    yield fake
    fake.close()


def actuator_for(port: str, limits_v: tuple[float, float], **kw: object) -> SerialLineActuator:
    settings_: dict[str, object] = {"port": port, "readback": "SVA? 1\n", "timeout_s": 1.0}
    settings_.update(kw)
    actuator = PLUGIN.create_actuator(SerialLineActuatorConfig.model_validate(settings_), DriverContext())
    assert isinstance(actuator, SerialLineActuator)
    actuator.limits_v = limits_v  # as the daemon sets it before open
    return actuator


def test_a_voltage_the_template_would_round_past_v_max_is_sent_inside(controller: FakeGcsController) -> None:
    async def body() -> None:
        actuator = actuator_for(controller.port, (-9.17, 9.17), command="SVA 1 {voltage_v:.1f}\n")
        await actuator.open()
        await actuator.command(458.5, 9.17)  # the readback (1=9.1000) is checked against what was sent: it passes
        await actuator.command(458.0, 9.16)
        await actuator.command(-458.5, -9.17)
        await actuator.command(457.0, 9.14)  # inside once rounded: as formatted
        await actuator.close()
        sent = [line for line in controller.lines if line.startswith("SVA ")]
        assert sent == ["SVA 1 9.1", "SVA 1 9.1", "SVA 1 -9.1", "SVA 1 9.1"]  # never 9.2
        assert controller.voltage == pytest.approx(9.1)

    run(body())


def test_a_template_that_can_write_nothing_inside_refuses_and_writes_nothing(controller: FakeGcsController) -> None:
    async def body() -> None:
        actuator = actuator_for(controller.port, (0.2, 0.4), command="SVA 1 {voltage_v:.0f}\n")
        await actuator.open()
        with pytest.raises(ValueError, match=r"\{voltage_v:.0f\} cannot write 0.3 within \[0.2, 0.4\]"):
            await actuator.command(15.0, 0.3)
        controller.voltage = 0.25
        assert await actuator.read_back() == ("voltage_v", 0.25)  # asked after the refusal, on the same line:
        assert controller.lines == ["SVA? 1"]  # anything written before would have arrived first
        await actuator.close()

    run(body())


def test_the_readback_is_compared_with_the_number_sent_for_a_closed_loop_field(controller: FakeGcsController) -> None:
    async def body() -> None:
        controller.position_per_volt = 1.0  # the fake's SVA stands in for MOV: POS? answers the number written
        actuator = actuator_for(controller.port, (-2.0, 12.0), command="SVA 1 {q_um:.1f}\n", readback="POS? 1\n",
                                readback_tolerance=0.0005)
        await actuator.open()
        await actuator.command(240.1234, 4.8)  # sends 240.1; comparing 240.1 with 240.1234 would be a fault
        await actuator.close()
        assert controller.lines == ["SVA 1 240.1", "POS? 1"]

    run(body())


def _decimals(text: str) -> int:
    return max(0, -Decimal(text).as_tuple().exponent)  # type: ignore[operator]


#: [v_min, v_max] with v_min < v_max, as the config demands
limits = st.tuples(st.floats(-50.0, 50.0), st.floats(1e-3, 60.0)).map(lambda t: (t[0], t[0] + t[1]))


@settings(max_examples=examples(400), deadline=None)
@given(precision=st.integers(0, 6), kind=st.sampled_from("fFeEg%"), bounds=limits,
       where=st.floats(0.0, 1.0), width=st.sampled_from(["", "+", "010", " >12"]))
def test_the_number_a_template_writes_is_always_within_the_limits(
        precision: int, kind: str, bounds: tuple[float, float], where: float, width: str) -> None:
    low, high = bounds
    voltage = low + where * (high - low)
    assume(low <= voltage <= high)
    spec = f"{width}.{precision}{kind}"  # sign, zero padding, fill and width around the number
    template = CommandTemplate("SVA 1 {voltage_v:" + spec + "}\n")
    config = SerialLineActuatorConfig(port="x", command=template.template)
    try:
        text, sent = template.render({"voltage_v": voltage, "q_um": 0.0, "x_um": 0.0}, (low, high))
    except ValueError:
        # refused only where check-config refuses the limits: no value it writes is inside
        problem = config.voltage_range_problem(low, high, 0.02)
        assert problem is not None and "no value it writes lies within" in problem, (spec, low, high, voltage)
        return
    number = DEVICE_NUMBER.match(text.rstrip("\n"))
    assert number is not None, text
    raw = number.group(1).strip()
    device = float(raw[:-1]) / 100 if raw.endswith("%") else float(raw)  # as a controller would read it
    assert low - 1e-12 * max(1.0, abs(low)) <= device <= high + 1e-12 * max(1.0, abs(high)), (spec, low, high, text)
    assert sent["voltage_v"] == pytest.approx(device, rel=1e-12, abs=1e-12)
    if kind in "fF":  # the nearest representable value inside: at most one step from the voltage asked
        assert abs(device - voltage) <= 10.0 ** -precision * (1 + 1e-9), (spec, voltage, text)


#: the command range [q(v_min), q(v_max)] in um, q(v_min) < q(v_max)
command_ranges = st.tuples(st.floats(-600.0, 600.0), st.floats(1e-2, 1200.0)).map(lambda t: (t[0], t[0] + t[1]))


@settings(max_examples=examples(150), deadline=None)
@given(name=st.sampled_from(["q_um", "x_um"]), precision=st.integers(0, 6), kind=st.sampled_from("fFeEg"),
       bounds=command_ranges, where=st.floats(-0.5, 1.5))
def test_a_position_field_is_written_within_the_command_range_or_refused(
        name: str, precision: int, kind: str, bounds: tuple[float, float], where: float) -> None:
    """``MOV 1 {q_um:.0f}`` with q 459.552 at a 459.8 um edge must not write 460: a position field is held
    to the command range after its rounding; a value outside the range before formatting is refused."""
    low, high = bounds
    value = low + where * (high - low)
    template = CommandTemplate("MOV 1 {" + name + ":." + str(precision) + kind + "}\n")
    values = {"voltage_v": 0.0, "q_um": value, "x_um": value}
    try:
        text, sent = template.render(values, limits_v=None, limits_q_um=(low, high))
    except ValueError as error:
        outside = not low - 1e-9 * max(1.0, abs(low), abs(high)) <= value <= high + 1e-9 * max(1.0, abs(high))
        assert outside or "no value it can write lies within" in str(error), (value, low, high, str(error))
        return
    device = float(text.split()[2])  # as the controller reads it
    assert low - 1e-12 * max(1.0, abs(low)) <= device <= high + 1e-12 * max(1.0, abs(high)), (low, high, text)
    assert sent[name] == pytest.approx(device, rel=1e-12, abs=1e-12)


@settings(max_examples=examples(15), deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(precision=st.integers(0, 6), bounds=limits, where=st.floats(0.0, 1.0))
def test_the_line_the_device_receives_is_within_the_limits(
        controller: FakeGcsController, precision: int, bounds: tuple[float, float], where: float) -> None:
    low, high = bounds
    command = f"SVA 1 {{voltage_v:.{precision}f}}\n"
    assume(SerialLineActuatorConfig(port="x", command=command).voltage_range_problem(low, high, 0.02) is None)
    voltage = min(high, max(low, low + where * (high - low)))

    async def body() -> None:
        controller.lines.clear()
        # the fake answers with 4 decimals
        actuator = actuator_for(controller.port, (low, high), command=command, readback_tolerance=1e-4)
        await actuator.open()
        await actuator.command(0.0, voltage)  # returns once the readback came: the line has arrived
        await actuator.close()
        [line] = [line for line in controller.lines if line.startswith("SVA ")]
        number = DEVICE_NUMBER.match(line)
        assert number is not None and _decimals(number.group(1)) == precision
        assert low <= float(number.group(1)) <= high, (precision, low, high, voltage, line)

    run(body())


@pytest.mark.parametrize(("command", "why"), [
    ("SVA 1 {voltage_v!r}\n", r"a conversion \(!r\) writes a string"),
    ("SVA 1 {voltage_v:.{x_um}f}\n", "a field inside a format spec"),
    ("SVA 1 {voltage_v:1>8.2f}\n", r"cannot be read back \(-123.457 is written '-123.46'|cannot be read back"),
    ("SVA 1 {voltage_v:d}\n", "cannot format a number with it"),
    ("SVA 1 {volts:.3f}\n", r"unknown field\(s\) \{volts\}"),
])
def test_templates_whose_sent_number_cannot_be_known_are_refused_naming_the_command(command: str, why: str) -> None:
    with pytest.raises(ValidationError, match=why) as caught:
        SerialLineActuatorConfig(port="x", command=command)
    assert caught.value.errors()[0]["loc"] == ("command",)


def test_the_impossible_and_the_coarse_template() -> None:
    coarse = SerialLineActuatorConfig(port="x", command="SVA 1 {voltage_v:.0f}\n")
    assert coarse.voltage_range_problem(-0.5, 0.4, 0.02) == (
        "command: {voltage_v:.0f} cannot write the voltages within [v_min, v_max] = [-0.5, 0.4] V: it writes every "
        "one of them as '-0', so the stage could not move; give it more decimals, e.g. {voltage_v:.1f}")
    assert "no value it writes lies within them (0.2 is written '0', 0.4 '0')" in str(
        coarse.voltage_range_problem(0.2, 0.4, 0.02))
    assert coarse.voltage_range_problem(-2.0, 12.0, 0.02) is None  # coarse, but it can move the stage: a warning
    assert coarse.config_warnings(-2.0, 12.0, 0.02, 0.0) == [
        "command: {voltage_v:.0f} writes voltage_v in steps of 1 V, 50000 nm of stage travel at volts_per_um = "
        "0.02, coarser than 10 nm: every command reaches the stage rounded to that; e.g. {voltage_v:.4f}"]
    fine = SerialLineActuatorConfig(port="x")  # the default {voltage_v:.4f}: 0.1 mV, 5 nm at 0.02 V/um
    assert fine.config_warnings(-2.0, 12.0, 0.02, 0.0) == []
    assert fine.voltage_range_problem(-2.0, 12.0, 0.02) is None
    assert len(fine.config_warnings(-2.0, 12.0, 0.002, 0.0)) == 1  # 50 nm at a tenfold smaller gain
    closed_loop = SerialLineActuatorConfig(port="x", command="MOV 1 {q_um:.1f}\n")
    assert closed_loop.config_warnings(-2.0, 12.0, 0.02, 0.0)[0].startswith(
        "command: {q_um:.1f} writes q_um in steps of 0.1 um, coarser than 10 nm")
