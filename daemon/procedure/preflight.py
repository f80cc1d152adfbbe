"""Before a procedure moves real hardware: nobody else is commanding the cell, and, when the steps go
out on Zenoh (``[actuator] kind = "zenoh"``), something is there to apply them.

Both checks use a *probe* session built from the operator's ``[zenoh]`` section that listens on
nothing (a running daemon may hold the configured endpoints) and connects to the endpoints the
daemon would listen on (wildcards as loopback) besides the configured ones; multicast scouting, when
on, finds the rest. Zenoh's own answers decide: the liveliness token ``nanodrift/<cell>/alive`` of a
serving daemon, and the matching status of a publisher on ``nanodrift/<cell>/command``.
"""

from __future__ import annotations

import asyncio
import json
import re
import time
from typing import Any

import zenoh

from nanodrift.bus.session import Keys, session_config
from nanodrift.config import Config, ZenohSettings
from nanodrift.errors import UserError

ALIVE_WAIT_S = 1.0  # a daemon's token answers within milliseconds once connected
OUTPUT_WAIT_S = 5.0  # an output node (re)connecting after the procedure's session opened
POLL_S = 0.02

_WILDCARDS = {"0.0.0.0": "127.0.0.1", "[::]": "[::1]"}


class PreflightError(UserError):
    """The procedure must not start (the message says why and what to do)."""


def _endpoints(value: Any, mode: str) -> list[str]:
    if isinstance(value, dict):  # zenoh's defaults are per mode
        value = value.get(mode, [])
    return [str(e) for e in value] if isinstance(value, list) else []


def loopback(endpoint: str) -> str | None:
    """Where a local client reaches a listening endpoint (None for a random port: nobody can)."""
    match = re.fullmatch(r"(?P<proto>[a-z0-9]+)/(?P<host>\[[^\]]*\]|[^:/]+):(?P<port>\d+)(?P<rest>.*)", endpoint)
    if match is None:
        return endpoint
    if match["port"] == "0":
        return None
    host = _WILDCARDS.get(match["host"], match["host"])
    return f"{match['proto']}/{host}:{match['port']}{match['rest']}"


def probe_config(settings: ZenohSettings) -> zenoh.Config:
    """The operator's zenoh config as a prober: listening on nothing, connecting where the cell's daemon listens."""
    conf = session_config(settings)
    mode = json.loads(conf.get_json("mode") or "null") or "peer"
    listen = _endpoints(json.loads(conf.get_json("listen/endpoints")), mode)
    connect = _endpoints(json.loads(conf.get_json("connect/endpoints")), mode)
    local = [e for e in (loopback(x) for x in listen) if e is not None]
    conf.insert_json5("listen/endpoints", "[]")
    conf.insert_json5("connect/endpoints", json.dumps(list(dict.fromkeys([*connect, *local]))))
    if mode == "router":
        conf.insert_json5("mode", '"peer"')
    return conf


def _open(config: Config) -> zenoh.Session:
    try:
        return zenoh.open(probe_config(config.zenoh))
    except zenoh.ZError as error:
        raise PreflightError(f"cannot join the zenoh network of [zenoh] to check the cell: {error}") from None


def check_not_served(config: Config, wait_s: float = ALIVE_WAIT_S) -> None:
    """:class:`PreflightError` when a daemon serves ``config.cell`` (its ``alive`` token is present)."""
    keys = Keys(config.cell, config.zenoh.prefix)
    session = _open(config)
    try:  # the liveliness tokens present on the cell's key
        tokens = [str(reply.ok.key_expr) for reply in session.liveliness().get(keys.alive, timeout=wait_s)
                  if reply.ok is not None]
    finally:
        session.close()
    if tokens:
        raise PreflightError(
            f"a daemon is commanding cell {config.cell!r} (its liveliness token {tokens[0]} is present): stop it "
            "first (systemctl stop nanodrift), so that only this procedure moves the stage")


async def wait_for_output(config: Config, wait_s: float | None = None) -> None:
    """:class:`PreflightError` unless a subscriber of ``nanodrift/<cell>/command`` appears within ``wait_s``
    (default :data:`OUTPUT_WAIT_S`)."""
    wait_s = OUTPUT_WAIT_S if wait_s is None else wait_s
    key = Keys(config.cell, config.zenoh.prefix).command
    session = await asyncio.to_thread(_open, config)
    try:
        publisher = session.declare_publisher(key)
        deadline = time.monotonic() + wait_s
        # zenoh 1.10's stub types matching_status as bool; it is a zenoh.MatchingStatus
        while not publisher.matching_status.matching:  # type: ignore[attr-defined]
            if time.monotonic() > deadline:
                raise PreflightError(
                    f"no output node is subscribed to {key} after {wait_s:g} s: nothing would put the steps on the "
                    "amplifier. Start the node that applies `command` to the stage, or set [actuator] kind to the "
                    "output device (modbus, serial_line); --no-output-check skips this check")
            await asyncio.sleep(POLL_S)
        publisher.undeclare()
    finally:
        await asyncio.to_thread(session.close)
