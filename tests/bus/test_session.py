"""The daemon's Zenoh session config: the operator's [zenoh] section, a zenoh json5 file, command-line overrides."""

from __future__ import annotations

import json
import threading
from pathlib import Path

import zenoh

from nanodrift.bus.session import Bus, session_config
from nanodrift.config import ZenohSettings
from nanodrift.drivers.local_port import free_port


def test_session_config_from_a_zenoh_json5_file(tmp_path: Path) -> None:
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] }, // comments are fine\n }')
    conf = session_config(ZenohSettings(config_file=path))
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7999"]
    conf = session_config(ZenohSettings(config_file=path, mode="peer"), listen=["tcp/127.0.0.1:7998"])
    assert json.loads(conf.get_json("mode")) == "peer"  # an explicit key in the TOML wins over the file
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7998"]



def test_session_config_command_line_overrides_the_file() -> None:
    settings = ZenohSettings(mode="peer", listen=["tcp/127.0.0.1:7447"], multicast_scouting=False)
    conf = session_config(settings, mode="client", connect=["tcp/127.0.0.1:7450"])
    assert json.loads(conf.get_json("mode")) == "client"
    assert json.loads(conf.get_json("connect/endpoints")) == ["tcp/127.0.0.1:7450"]
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7447"]
    assert json.loads(conf.get_json("scouting/multicast/enabled")) is False
    conf = session_config(settings, listen=["tcp/127.0.0.1:7460"])
    assert json.loads(conf.get_json("listen/endpoints")) == ["tcp/127.0.0.1:7460"]


def _answer_stream(bus: Bus, putting: threading.Event, stop: threading.Event, outcomes: list[str]) -> None:
    """What Zenoh's callback thread does while targets keep coming: publish answers until told to stop."""
    while not stop.is_set():
        try:
            bus.publish_error(b'{"id":1,"error":"shutting_down"}')
            putting.set()
        except zenoh.ZError:
            outcomes.append("ZError")
            return
        except Exception as error:  # what the target path would not handle
            outcomes.append(f"{type(error).__name__}: {error}")
            return


def test_closing_the_bus_while_another_thread_publishes_answers_raises_nothing() -> None:
    """A daemon stopping under a stream of targets: an answer still being published on Zenoh's thread while
    the loop closes the bus. Undeclaring that publisher during its put raised ``RuntimeError: Already
    borrowed`` (a daemon's SIGTERM ended with exit code 1 in a loaded CI run); the put after the close
    raises ``ZError``, which the target path reports as ``answer_not_sent``."""
    for attempt in range(20):
        session = zenoh.open(session_config(ZenohSettings(mode="peer", listen=[f"tcp/127.0.0.1:{free_port()}"],
                                                          multicast_scouting=False)))
        bus = Bus(session, "closing")
        putting, stop = threading.Event(), threading.Event()
        outcomes: list[str] = []
        publisher = threading.Thread(target=_answer_stream, args=(bus, putting, stop, outcomes))
        publisher.start()
        try:
            assert putting.wait(5), "the answer stream never published"
            bus.close()  # raised RuntimeError: Already borrowed before the fix
        finally:
            stop.set()
            publisher.join(5)
        assert session.is_closed()
        assert outcomes in ([], ["ZError"]), (attempt, outcomes)
