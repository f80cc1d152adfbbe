"""``nanodrift.drivers.testing.protocol``: the scripted device a lab tests its plugin's exact conversation with,
here driving the serial_line actuator; and its verdict on a conversation that differs."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest

from nanodrift.drivers.base import DriverContext
from nanodrift.drivers.registry import load_plugin
from nanodrift.drivers.testing import expected_protocol


def gcs_actuator(port: str) -> object:
    plugin = load_plugin("serial_line")
    assert plugin.actuator_model is not None
    options = plugin.actuator_model.model_validate({"kind": "serial_line", "port": port, "readback": "SVA? 1\n",
                                                    "error_query": "ERR?\n", "timeout_s": 0.5})
    return plugin.create_actuator(options, DriverContext())


def drive(port: str, *volts: float) -> None:
    actuator = gcs_actuator(port)

    async def body() -> None:
        await actuator.open()  # type: ignore[attr-defined]
        for v in volts:
            await actuator.command(v / 0.02, v)  # type: ignore[attr-defined]
        await actuator.close()  # type: ignore[attr-defined]

    asyncio.run(asyncio.wait_for(body(), 10))


def test_the_exact_conversation_passes(tmp_path: Path) -> None:
    with expected_protocol(tmp_path / "ttyPI", [(b"SVA 1 4.9990\n", None), (b"SVA? 1\n", b"1=4.9990\n"),
                                                (b"ERR?\n", b"0\n")]) as device:
        drive(device.port, 4.999)
    assert device.done == 3 and device.problems() == []


def test_a_different_request_or_a_missing_one_fails_naming_it(tmp_path: Path) -> None:
    with pytest.raises(AssertionError) as error, expected_protocol(
            tmp_path / "ttyPI", [(b"SVA 1 5.0000\n", None), (b"SVA? 1\n", b"1=5.0000\n")]):
        with pytest.raises(Exception, match="no answer"):  # the script waits for 5.0000: nothing answers
            drive(str(tmp_path / "ttyPI"), 4.999)
    assert "unexpected bytes b'SVA 1 4.9990\\n" in str(error.value)
    assert "2 exchange(s) never took place, first b'SVA 1 5.0000\\n'" in str(error.value)
