"""The Zenoh side of the daemon, kept thin: keys, session config, declarations, thread hand-off.

Zenoh runs callbacks on its own threads. The status query is handed to the asyncio loop with
``loop.call_soon_threadsafe``; targets are answered right on Zenoh's thread by the service's
thread-safe ``on_target`` (it locks the state the loop writes), because the hand-off alone would
cost more than the latency budget allows. The service hands everything else to the loop.
Keys (under ``nanodrift/<cell>/``) are the public contract of ARCHITECTURE.md.
"""

from __future__ import annotations

import asyncio
import functools
import json
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from daemon.config import ZenohSettings
from daemon.service_core import MAX_PAYLOAD_BYTES, Oversized


def session_config(
    settings: ZenohSettings | None = None,
    *,
    mode: str | None = None,
    listen: Sequence[str] | None = None,
    connect: Sequence[str] | None = None,
    multicast_scouting: bool | None = None,
) -> zenoh.Config:
    """A zenoh Config from the operator's ``[zenoh]`` section, then command-line overrides.

    As in the zenoh examples: ``-l``/``-e``/``--mode`` replace what the file says.
    """
    settings = settings or ZenohSettings()
    conf = zenoh.Config.from_file(str(settings.config_file)) if settings.config_file else zenoh.Config()
    fields = settings.model_fields_set
    if settings.config_file is None or "mode" in fields:
        conf.insert_json5("mode", json.dumps(settings.mode))
    if settings.listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    if settings.connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    if settings.config_file is None or "multicast_scouting" in fields:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(settings.multicast_scouting))
    if mode:
        conf.insert_json5("mode", json.dumps(mode))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    if multicast_scouting is not None:
        conf.insert_json5("scouting/multicast/enabled", json.dumps(multicast_scouting))
    return conf


class Keys:
    """The contract's key expressions for one cell."""

    def __init__(self, cell: str) -> None:
        self.prefix = f"nanodrift/{cell}"
        self.target = f"{self.prefix}/target"
        self.command = f"{self.prefix}/command"
        self.error = f"{self.prefix}/error"
        self.compensate = f"{self.prefix}/compensate"
        self.status = f"{self.prefix}/status"
        self.alive = f"{self.prefix}/alive"

    def telemetry(self, role: str, channel: str) -> str:
        if role == "position":
            return f"{self.prefix}/sensors/position"
        return f"{self.prefix}/sensors/temperature/{channel}"


OnTarget = Callable[[bytes, "zenoh.Query | None"], None]
OnQuery = Callable[["zenoh.Query"], None]


class Bus:
    """The daemon's declarations on one Zenoh session."""

    def __init__(self, session: zenoh.Session, cell: str) -> None:
        self.session = session
        self.keys = Keys(cell)
        self._declared: list[Any] = []
        self._telemetry: dict[str, zenoh.Publisher] = {}
        self._token: zenoh.LivelinessToken | None = None
        # answers must not be dropped under load: block rather than lose one
        self._command_pub = session.declare_publisher(
            self.keys.command, congestion_control=zenoh.CongestionControl.BLOCK, express=True
        )
        self._error_pub = session.declare_publisher(
            self.keys.error, congestion_control=zenoh.CongestionControl.BLOCK, express=True
        )
        #: put one answer (bytes); the publishers' own methods, no wrapper on the hot path
        self.publish_command: Callable[[bytes], None] = self._command_pub.put
        self.publish_error: Callable[[bytes], None] = self._error_pub.put

    def serve(self, loop: asyncio.AbstractEventLoop, on_target: OnTarget, on_status: OnQuery,
              targets_on_loop: bool = False) -> None:
        """Declare the target subscriber and the two queryables; announce liveliness last.

        ``on_target`` is thread-safe and runs on Zenoh's callback thread: handing each target to the
        loop costs a thread wake-up (~50 us here, as much as the whole Zenoh round trip's margin in
        benchmarks/daemon_latency.py). ``targets_on_loop`` hands them over anyway (for comparison).
        ``on_status`` always runs on the loop.
        """
        call = loop.call_soon_threadsafe
        limit = MAX_PAYLOAD_BYTES  # larger payloads are refused without being copied
        if targets_on_loop:
            on_target = functools.partial(call, on_target)

        def target_sample(sample: zenoh.Sample) -> None:
            payload = sample.payload
            on_target(payload.to_bytes() if len(payload) <= limit else Oversized.of(len(payload)), None)

        def compensate_query(query: zenoh.Query) -> None:
            payload = query.payload
            if payload is None:
                on_target(b"", query)
            else:
                on_target(payload.to_bytes() if len(payload) <= limit else Oversized.of(len(payload)), query)

        def status_query(query: zenoh.Query) -> None:
            call(on_status, query)

        self._declared.append(self.session.declare_subscriber(self.keys.target, target_sample))
        self._declared.append(self.session.declare_queryable(self.keys.compensate, compensate_query))
        self._declared.append(self.session.declare_queryable(self.keys.status, status_query))
        self._token = self.session.liveliness().declare_token(self.keys.alive)


    def publish_telemetry(self, role: str, channel: str, payload: bytes) -> None:
        key = self.keys.telemetry(role, channel)
        publisher = self._telemetry.get(key)
        if publisher is None:
            publisher = self._telemetry[key] = self.session.declare_publisher(key)
        publisher.put(payload)

    def reply(self, query: zenoh.Query, key: str, payload: bytes) -> None:
        """Reply on the queryable's own key (the query's may be a wildcard), then release the query."""
        try:
            query.reply(key, payload)
        finally:
            query.drop()

    def reply_err(self, query: zenoh.Query, payload: bytes) -> None:
        try:
            query.reply_err(payload)
        finally:
            query.drop()

    def withdraw(self) -> None:
        """Undeclare the liveliness token and stop taking targets (clients see the daemon gone)."""
        if self._token is not None:
            self._token.undeclare()
            self._token = None
        for entity in self._declared:
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self._declared.clear()

    def close(self) -> None:
        """Withdraw, undeclare everything, close the session."""
        self.withdraw()
        for entity in [*self._telemetry.values(), self._command_pub, self._error_pub]:
            try:
                entity.undeclare()
            except zenoh.ZError:
                pass
        self._telemetry.clear()
        if not self.session.is_closed():
            self.session.close()
