"""Calibrating real hardware: with no plugin that moves the stage, steps go out on the command key."""

import asyncio
import json
import queue
import time

import pytest
import zenoh
from helpers.daemon_harness import free_port

from nanodrift.assembly import procedure_drivers
from nanodrift.bus.actuator import ZenohActuator
from nanodrift.config import parse_config


def hardware_config(port: int):
    return parse_config(
        {
            "cell": "lab1",
            "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{port}"], "multicast_scouting": False},
            "hubs": [{"name": "adam", "type": "tcp", "host": "127.0.0.1", "port": 1}],
            "sensors": [
                {"name": "T1", "kind": "modbus", "hub": "adam", "address": 0, "input_type": "input"},
                {"name": "interferometer", "role": "position", "kind": "serial_line", "port": "loop://",
                 "pattern": r"P (?P<value>[-+0-9.]+) nm", "scale": 0.001},
            ],
        },
        source="test",
    )


def test_hardware_calibration_publishes_each_step_as_a_command(tmp_path):
    port = free_port()
    config = hardware_config(port)
    backend = procedure_drivers(config)
    assert isinstance(backend.actuators["x"], ZenohActuator)
    assert "nanodrift/lab1/command" in backend.description
    with pytest.raises(ValueError, match="outside"):
        config.actuator.checked_voltage(700.0)  # 14 V: refused before anything is published

    received: queue.Queue = queue.Queue()
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    conf.insert_json5("scouting/multicast/enabled", "false")

    async def scenario() -> list[dict]:
        await backend.actuators["x"].open()
        listener = zenoh.open(conf)
        try:
            listener.declare_subscriber("nanodrift/lab1/command", lambda s: received.put(s.payload.to_bytes()))
            deadline = time.monotonic() + 10.0
            while received.empty():  # the first puts may precede the link; bounded
                assert time.monotonic() < deadline, "no command reached the subscriber in 10 s"
                await backend.actuators["x"].command(240.0, config.actuator.checked_voltage(240.0))
                await asyncio.sleep(0.05)
            await backend.actuators["x"].command(270.0, config.actuator.checked_voltage(270.0))
            samples = [json.loads(received.get(timeout=5.0))]
            while samples[-1]["q_um"] != 270.0:
                samples.append(json.loads(received.get(timeout=5.0)))
            return samples
        finally:
            listener.close()
            await backend.actuators["x"].close()

    samples = asyncio.run(scenario())
    first, last = samples[0], samples[-1]
    assert set(first) >= {"id", "x_um", "q_um", "voltage_v", "temperatures_c", "model", "t"}
    assert first["q_um"] == 240.0 and first["voltage_v"] == pytest.approx(4.8) and first["model"] is None
    assert last["voltage_v"] == pytest.approx(5.4) and last["id"].startswith("calibration-")
    assert int(last["id"].split("-")[1]) > int(first["id"].split("-")[1])
