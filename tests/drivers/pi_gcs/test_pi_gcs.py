"""The ``pi_gcs`` plugin against the GCS emulator (``nanodrift.drivers.testing.pi_gcs_emulator``) over real TCP on
127.0.0.1 and a real pty: what the controller was told (its own log of lines), never the plugin's account.

- the servo: on at power-up with an open-loop config -> switched off before any SVA, and logged; off with a
  closed-loop config -> switched on before any MOV; the controller's own drift compensation is warned about;
- errors: a controller error is reported as ``PI error N: <text>`` naming the command that caused it, and the next
  command is not blamed; an error raised by something else between two commands is reported as pending before
  the command, never as the command's; a controller that accepts a command without applying it is a fault;
- limits: a config beyond what the controller reports (VMI?/VMA?, TMN?/TMX?) is refused at open naming the axis
  and both ranges, with nothing moved; a controller without voltage limits opens;
- GCS framing: a multi-line answer (``" \\n"`` between lines) is read whole;
- bad config: a clear error naming the key; ``config/pi_gcs.toml`` passes ``nanodrift check-config``.
"""

from __future__ import annotations

import asyncio
import math
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from fractions import Fraction
from pathlib import Path
from typing import Any

import pytest
import structlog
from helpers.budget import examples
from helpers.daemon_harness import write_test_model
from hypothesis import example, given, settings
from hypothesis import strategies as st
from pydantic import ValidationError

from nanodrift.config import ConfigError, parse_config
from nanodrift.drivers.base import DeviceError, DriverContext
from nanodrift.drivers.pi_gcs.actuator import PiGcsActuator, PiGcsLimitsError, rounded_inside
from nanodrift.drivers.pi_gcs.config import PiGcsActuatorConfig
from nanodrift.drivers.registry import load_plugin
from nanodrift.drivers.testing.pi_gcs_emulator import (
    EmulatedAxis,
    PiGcsEmulator,
    PiGcsPtyDevice,
    PiGcsTcpServer,
)

REPO = Path(__file__).resolve().parents[3]
WORKED_CONFIG = REPO / "config" / "pi_gcs.toml"
BOUND_S = 10.0


def actuator_for(options: dict[str, Any]) -> PiGcsActuator:
    """Built the daemon's way: the plugin by its entry point, the options through its model."""
    plugin = load_plugin("pi_gcs")
    assert plugin.actuator_model is not None
    actuator = plugin.create_actuator(plugin.actuator_model.model_validate({"kind": "pi_gcs", **options}),
                                      DriverContext())
    assert isinstance(actuator, PiGcsActuator)
    return actuator


@asynccontextmanager
async def over_tcp(emulator: PiGcsEmulator, **options: Any) -> AsyncIterator[PiGcsActuator]:
    server = PiGcsTcpServer(emulator)
    await server.start()
    try:
        yield actuator_for({"host": "127.0.0.1", "port": server.port, "timeout_s": 2.0, **options})
    finally:
        await server.stop()


def run(body: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(body(), BOUND_S))


# --- the servo ----------------------------------------------------------------------------------


@pytest.mark.parametrize("transport", ["tcp", "pty"])
def test_servo_on_with_an_open_loop_config_is_switched_off_before_any_sva_and_logged(
        tmp_path: Path, transport: str) -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(servo=True)})

    async def drive(actuator: PiGcsActuator) -> None:
        actuator.limits_v = (-2.0, 12.0)
        with structlog.testing.capture_logs() as logs:
            await actuator.open()
        await actuator.command(125.0, 2.5)
        await actuator.close()
        [switched] = [e for e in logs if e["event"] == "pi_gcs_servo_switched"]
        assert switched["servo"] == "off" and "SVA" in switched["reason"]

    async def body() -> None:
        if transport == "tcp":
            async with over_tcp(emulator) as actuator:
                await drive(actuator)
        else:
            device = PiGcsPtyDevice(tmp_path / "ttyPI", emulator)
            try:
                await drive(actuator_for({"transport": "serial", "port": device.port, "timeout_s": 2.0}))
            finally:
                device.close()

    run(body)
    lines = emulator.received()
    assert lines.index("SVO 1 0") < lines.index("SVA 1 2.500000")
    assert emulator.sva("1") == 2.5 and not emulator.axes["1"].servo
    assert emulator.received("SVA") == ["SVA 1 2.500000"]  # the only motion command it got


def test_closed_loop_switches_the_servo_on_moves_reads_back_the_target_and_reports_on_target() -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(travel_um=(0.0, 480.0))}, settle_s=0.05)

    async def body() -> None:
        async with over_tcp(emulator, mode="closed_loop", q_max_um=450.0) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            with structlog.testing.capture_logs() as logs:
                await actuator.open()
            assert [e["servo"] for e in logs if e["event"] == "pi_gcs_servo_switched"] == ["on"]
            await actuator.command(240.1234567, 4.8)
            assert await actuator.read_back() == ("q_um", pytest.approx(240.123457, abs=1e-12))
            assert await actuator.on_target() is False  # settle_s has not passed
            deadline = time.monotonic() + 2.0
            while not await actuator.on_target():
                assert time.monotonic() < deadline, "ONT? never said on target"
            with pytest.raises(ValueError, match=r"q_um = 460.0 is outside \[q_min_um, q_max_um\] = \[0.0, 450.0\]"):
                await actuator.command(460.0, 9.2)
            await actuator.close()

    run(body)
    lines = emulator.received()
    assert lines.index("SVO 1 1") < lines.index("MOV 1 240.123457")
    assert emulator.received("MOV") == ["MOV 1 240.123457"]  # 460 um was never sent
    assert emulator.target_um("1") == pytest.approx(240.123457, abs=1e-12)


def test_the_controllers_own_drift_compensation_is_warned_about() -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(drift_compensation=True)})

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            with structlog.testing.capture_logs() as logs:
                await actuator.open()
            await actuator.close()
        [warning] = [e for e in logs if e["event"] == "pi_gcs_drift_compensation_on"]
        assert warning["log_level"] == "warning" and "DCO" in warning["note"]
        assert "E-727" in warning["identity"]

    run(body)


# --- errors -------------------------------------------------------------------------------------


def test_a_controller_error_is_reported_with_number_and_text_and_the_next_command_is_not_blamed() -> None:
    emulator = PiGcsEmulator()

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            await actuator.open()
            emulator.fail_next["SVA"] = 302  # the controller refuses this SVA
            with pytest.raises(DeviceError) as refused:
                await actuator.command(150.0, 3.0)
            assert "PI error 302: Voltage out of limits (after 'SVA 1 3.000000')" in str(refused.value)
            await actuator.command(200.0, 4.0)  # not blamed for the earlier error
            assert emulator.sva("1") == 4.0
            await actuator.close()

    run(body)
    assert emulator.received("SVA") == ["SVA 1 3.000000", "SVA 1 4.000000"]


def test_an_error_raised_between_two_commands_is_pending_before_the_next_never_blamed_on_it() -> None:
    emulator = PiGcsEmulator()

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            await actuator.open()
            await actuator.command(100.0, 2.0)
            emulator.raise_error(10)  # someone's STP on another connection
            with pytest.raises(DeviceError) as pending:
                await actuator.command(150.0, 3.0)
            message = str(pending.value)
            assert "PI error 10: Controller was stopped by command was pending before 'SVA 1 3.000000'" in message
            assert "not by this command" in message and "(after 'SVA" not in message
            await actuator.command(150.0, 3.0)  # the register is clear again
            await actuator.close()

    run(body)
    assert emulator.sva("1") == 3.0


def test_an_error_left_from_before_the_connection_is_cleared_at_open_and_blamed_on_nothing() -> None:
    emulator = PiGcsEmulator()
    emulator.raise_error(79)

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            with structlog.testing.capture_logs() as logs:
                await actuator.open()
            await actuator.command(100.0, 2.0)
            await actuator.close()
        [cleared] = [e for e in logs if e["event"] == "pi_gcs_error_cleared"]
        assert cleared["error"] == "PI error 79: Open-loop commands are not allowed when servo is on"

    run(body)
    assert emulator.received()[0] == "ERR?" and emulator.sva("1") == 2.0


def test_a_command_accepted_without_moving_the_stage_is_a_fault_never_accepted() -> None:
    emulator = PiGcsEmulator()

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            await actuator.open()
            await actuator.command(100.0, 2.0)
            emulator.frozen = True  # the controller takes SVA without an error, and nothing changes
            with pytest.raises(DeviceError, match=r"wrote 'SVA 1 5.000000', 'SVA\? 1' reads back 2.0"):
                await actuator.command(250.0, 5.0)
            await actuator.close()

    run(body)
    assert emulator.sva("1") == 2.0


def test_a_stray_line_resets_the_connection_and_is_never_taken_for_an_answer() -> None:
    emulator = PiGcsEmulator()

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            await actuator.open()
            await actuator.command(100.0, 2.0)
            emulator.stray = "1=42.000000"  # before the next answer: the answers are out of step by one
            with pytest.raises(DeviceError, match=r"unexpected answer '1=42.000000' to 'ERR\?'.*connection is reset"):
                await actuator.command(150.0, 3.0)
            await actuator.command(200.0, 4.0)  # a new connection, the axis prepared again
            assert await actuator.read_back() == ("voltage_v", 4.0)
            await actuator.close()

    run(body)
    assert [c for c, line in emulator.lines if line == "*IDN?"] == ["tcp1", "tcp2"]  # opened twice
    assert emulator.sva("1") == 4.0


def test_servo_switched_on_from_outside_makes_sva_fail_with_error_79_named() -> None:
    emulator = PiGcsEmulator()

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            await actuator.open()
            emulator.set_servo("1", True)
            with pytest.raises(DeviceError, match="PI error 79: Open-loop commands are not allowed when servo is on"):
                await actuator.command(100.0, 2.0)
            await actuator.close()

    run(body)
    assert emulator.sva("1") == 0.0


# --- limits -------------------------------------------------------------------------------------


def test_voltage_limits_beyond_the_controllers_are_refused_at_open_naming_axis_and_ranges() -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(servo=True, voltage_v=(-20.0, 120.0))})

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-30.0, 100.0)
            with pytest.raises(PiGcsLimitsError) as refused:
                await actuator.open()
            await actuator.close()
        assert ("axis 1 (SVA, open loop): [v_min, v_max] = [-30, 100] V exceeds the voltage range the controller "
                "reports for axis 1 (piezo channel 1), [-20, 120] V (VMI?/VMA?)") in str(refused.value)

    run(body)
    assert emulator.received("SVA") == [] and emulator.received("SVO") == []  # nothing moved, servo untouched


def test_a_position_range_beyond_the_travel_is_refused_at_open() -> None:
    emulator = PiGcsEmulator(axes={"A": EmulatedAxis(travel_um=(0.0, 480.0))})

    async def body() -> None:
        async with over_tcp(emulator, axis="A", piezo_channel=1, mode="closed_loop", q_max_um=500.0) as actuator:
            with pytest.raises(PiGcsLimitsError, match=r"\[q_min_um, q_max_um\] = \[0, 500\] um exceeds the travel "
                                                       r"range the controller reports for axis A, \[0, 480\] um"):
                await actuator.open()
            await actuator.close()

    run(body)
    assert emulator.received("MOV") == [] and emulator.received("SVO") == []


def test_an_axis_the_controller_does_not_have_is_refused_listing_its_axes() -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(), "2": EmulatedAxis(), "3": EmulatedAxis()})

    async def body() -> None:
        async with over_tcp(emulator, axis="4") as actuator:
            with pytest.raises(PiGcsLimitsError, match=r"no axis '4' \(SVO\? lists 1, 2, 3\)"):
                await actuator.open()
            await actuator.close()

    run(body)


def test_a_controller_without_voltage_limits_opens_and_serves() -> None:
    emulator = PiGcsEmulator(has_voltage_limits=False)

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            actuator.limits_v = (-2.0, 12.0)
            await actuator.open()
            assert actuator.voltage_range_v is None and actuator.travel_um == (0.0, 500.0)
            await actuator.command(100.0, 2.0)
            await actuator.close()

    run(body)
    assert emulator.sva("1") == 2.0


# --- GCS framing --------------------------------------------------------------------------------


def test_a_multi_line_answer_has_a_space_before_each_lf_but_the_last_and_is_read_whole() -> None:
    emulator = PiGcsEmulator(axes={"1": EmulatedAxis(travel_um=(0.0, 100.0)), "2": EmulatedAxis(travel_um=(0.0, 200.0)),
                                   "3": EmulatedAxis(travel_um=(-5.0, 300.0))})

    async def body() -> None:
        async with over_tcp(emulator) as actuator:
            host, port = "127.0.0.1", actuator.config.tcp_port
            reader, writer = await asyncio.open_connection(host, port)
            writer.write(b"TMX?\n")
            raw = b"".join([await reader.readline() for _ in range(3)])
            writer.close()
            assert raw == b"1=100.000000 \n2=200.000000 \n3=300.000000\n"
            [answer, err] = await actuator.link.ask(["TMX?", "ERR?"], 2)
            assert answer == "1=100.000000\n2=200.000000\n3=300.000000" and err == "0"
            actuator.link.drop()

    run(body)


@given(st.floats(min_value=-2.0, max_value=12.0, allow_nan=False), st.floats(min_value=-2.0, max_value=12.0))
@example(1e-06, 3e-97)  # a CI run drew 3.25e-97: no 6-decimal number in [3e-97, 1e-06] (binary 1e-06 < 1e-6)
@settings(max_examples=examples(200), deadline=None)
def test_a_written_number_never_leaves_the_limits(value: float, other: float) -> None:
    low, high = min(value, other), max(value, other)
    try:
        written = rounded_inside(value, low, high, "v")
    except ValueError:  # right only when no 6-decimal number lies inside, judged exactly: a float subtraction
        # rounds (1e-06 - 3.3e-97 == 1e-06, yet the binary 1e-06 is below 0.000001 and no step fits)
        assert math.ceil(Fraction(low) * 10**6) > Fraction(high) * 10**6, (value, low, high)
        return
    assert low <= written <= high and abs(written - value) <= 1e-6 + 1e-12
    assert f"{written:.6f}" == f"{float(f'{written:.6f}'):.6f}"


# --- config -------------------------------------------------------------------------------------


@pytest.mark.parametrize(("options", "message"), [
    ({}, r"host: transport = \"tcp\" needs the controller's address"),
    ({"host": "10.0.0.2", "port": "/dev/ttyUSB0"}, r"port: transport = \"tcp\" takes a TCP port number"),
    ({"transport": "serial"}, r"port: transport = \"serial\" needs the serial device"),
    ({"transport": "serial", "port": 50000}, r"port: transport = \"serial\" needs the serial device"),
    ({"host": "10.0.0.2", "axis": "A"}, r"piezo_channel: axis 'A' is not a number"),
    ({"host": "10.0.0.2", "q_max_um": 400.0}, r"q_min_um: only mode = \"closed_loop\""),
    ({"host": "10.0.0.2", "mode": "closed_loop", "q_min_um": 5.0, "q_max_um": 1.0}, r"q_max_um: 1 is not above"),
    ({"host": "10.0.0.2", "mod": "open_loop"}, r"mod\n  Extra inputs are not permitted"),
])
def test_a_bad_config_is_refused_naming_the_key(options: dict[str, Any], message: str) -> None:
    with pytest.raises(ValidationError, match=message):
        PiGcsActuatorConfig.model_validate({"kind": "pi_gcs", **options})


def test_a_pi_gcs_sensor_is_refused_as_an_output_only_kind() -> None:
    data = {"cell": "c", "actuator": {"kind": "zenoh"},
            "sensors": [{"name": "P", "role": "position", "kind": "pi_gcs"}]}
    with pytest.raises(ConfigError, match=r"sensors\[0\] \(P\).*pi_gcs is an output"):
        parse_config(data, source="t.toml")


def test_the_worked_config_passes_check_config(tmp_path: Path) -> None:
    write_test_model(tmp_path / "model.json")
    config = tmp_path / "pi_gcs.toml"
    model = f'"{tmp_path / "model.json"}"'
    config.write_text(WORKED_CONFIG.read_text().replace('"/var/lib/nanodrift/model.json"', model))
    result = subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(config)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    broken = tmp_path / "broken.toml"
    broken.write_text(config.read_text().replace('transport = "tcp"', 'transport = "usb"'))
    result = subprocess.run([sys.executable, "-m", "nanodrift.cli", "check-config", str(broken)],
                            capture_output=True, text=True, timeout=60)
    assert result.returncode != 0 and "actuator.transport" in result.stderr, result.stderr


def test_nothing_listens_means_a_device_error_naming_the_controller() -> None:
    with socket.socket() as probe:  # a port nobody listens on: bound, never listening
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
        actuator = actuator_for({"host": "127.0.0.1", "port": port, "timeout_s": 1.0})

        async def body() -> None:
            with pytest.raises(DeviceError, match=rf"PI controller at 127.0.0.1:{port}.*cannot connect"):
                await actuator.open()
            await actuator.close()

        run(body)


def test_two_cell_axes_on_one_controller_axis_are_refused() -> None:
    axes = [{"name": name, "actuator": {"kind": "pi_gcs", "host": "10.0.0.2", "axis": axis}}
            for name, axis in (("x", "1"), ("y", "2"), ("z", "1"))]
    with pytest.raises(ConfigError, match=r"axes\[2\] \(z\).actuator: axis '1' of the PI controller at "
                                          r"10.0.0.2:50000 is already the output of axes\[0\] \(x\)"):
        parse_config({"cell": "c", "axes": axes}, source="t.toml")
