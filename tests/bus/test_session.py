"""The daemon's Zenoh session config: the operator's [zenoh] section, a zenoh json5 file, command-line overrides."""

from __future__ import annotations

import json
from pathlib import Path

from nanodrift.bus.session import session_config
from nanodrift.config import ZenohSettings


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
