"""Zenoh's errors as one sentence for an operator (issue 13, reproduction 1): real sessions on 127.0.0.1."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import zenoh
from helpers.daemon_harness import free_port

from nanodrift.bus.session import describe_zenoh_error, listen_endpoints, session_config


def open_error(conf: zenoh.Config) -> zenoh.ZError:
    with pytest.raises(zenoh.ZError) as raised:
        zenoh.open(conf).close()
    return raised.value


def one_sentence(text: str) -> None:
    assert "/root/.cargo" not in text and ".rs:" not in text and "\n" not in text


def test_address_in_use_names_the_endpoint_and_suggests_another() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    holder = zenoh.open(session_config(listen=[endpoint], multicast_scouting=False))
    try:
        error = open_error(session_config(listen=[endpoint], multicast_scouting=False))
        assert ".rs:" in str(error)  # zenoh's own message carries its Rust source paths ...
        text = describe_zenoh_error(error)
        one_sentence(text)  # ... the operator's does not
        assert text.startswith(f"{endpoint} is already in use") and "-l tcp/127.0.0.1:PORT" in text
    finally:
        holder.close()


def test_nobody_listening() -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    text = describe_zenoh_error(open_error(session_config(mode="client", connect=[endpoint])))
    one_sentence(text)
    assert text.startswith(f"nobody is listening at {endpoint}")


def test_authentication_refused_is_told_apart_from_nobody_listening(tmp_path: Path) -> None:
    credentials = tmp_path / "credentials.txt"
    credentials.write_text("lab:right\n")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    daemon_conf = session_config(listen=[endpoint], multicast_scouting=False)
    daemon_conf.insert_json5("transport/auth/usrpwd", json.dumps({"dictionary_file": str(credentials)}))
    daemon = zenoh.open(daemon_conf)
    try:
        client = session_config(mode="client", connect=[endpoint], multicast_scouting=False)
        client.insert_json5("transport/auth/usrpwd", json.dumps({"user": "lab", "password": "wrong"}))
        text = describe_zenoh_error(open_error(client))
        one_sentence(text)
        assert text.startswith(f"{endpoint} answered but refused the session: authentication refused")
    finally:
        daemon.close()


def test_listen_endpoints_are_what_the_config_says() -> None:
    assert listen_endpoints(session_config(listen=["tcp/127.0.0.1:7447"])) == ["tcp/127.0.0.1:7447"]
