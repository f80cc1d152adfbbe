"""The daemon's Zenoh session, kept thin: its config, its declarations, the thread hand-off.

Zenoh runs callbacks on its own threads. The status query is handed to the asyncio loop with
``loop.call_soon_threadsafe``; targets are answered right on Zenoh's thread by the service's
thread-safe ``on_target`` (see ``nanodrift.service.targets``), because the hand-off alone (a thread
wake-up, ~50 us here: as much as the whole Zenoh round trip's margin in benchmarks/daemon_latency.py, whose
``--targets-on-loop`` measures that variant) would cost more than the latency budget allows. What the keys
and payloads are is ``nanodrift.bus.protocol``'s.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import socket
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from nanodrift.bus.protocol import DEFAULT_PREFIX, MAX_PAYLOAD_BYTES, Keys, Oversized
from nanodrift.settings import ZenohSettings

# Keys is re-exported: a client opens a session and names the keys with one import
__all__ = ["ANSWER_CONGESTION", "ANSWER_EXPRESS", "Bus", "Keys", "describe_zenoh_error", "listen_endpoints",
           "session_config"]


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
    own = settings.config_file is None  # no file: the section's defaults are the config
    for key, value, given in (
        ("mode", settings.mode, own or "mode" in fields),
        ("listen/endpoints", list(settings.listen), bool(settings.listen)),
        ("connect/endpoints", list(settings.connect), bool(settings.connect)),
        ("scouting/multicast/enabled", settings.multicast_scouting, own or "multicast_scouting" in fields),
        ("mode", mode, bool(mode)),
        ("listen/endpoints", list(listen or ()), bool(listen)),
        ("connect/endpoints", list(connect or ()), bool(connect)),
        ("scouting/multicast/enabled", multicast_scouting, multicast_scouting is not None),
    ):
        if given:
            conf.insert_json5(key, json.dumps(value))
    return conf


#: zenoh's messages end each cause with where in its Rust sources it was raised: no use to an operator
_RUST_LOCATION = re.compile(r"\s*at /\S+?\.rs:\d+\.?")
_BOUND_TO = re.compile(r"bound to (?P<ep>[a-z0-9]+/\S+?):? \[")
_UNABLE = re.compile(r"Unable to connect to any of \[(?P<eps>.*?)\]")
_SINGLE = re.compile(r"Single\((?P<ep>[^)]+)\)")
_PROBE_TIMEOUT_S = 0.5


def _reachable(endpoint: str) -> bool:
    """Whether something accepts a TCP connection at a ``tcp/HOST:PORT`` or ``tls/HOST:PORT`` endpoint."""
    match = re.match(r"^(?:tcp|tls)/\[?(?P<host>[^\]]+?)\]?:(?P<port>\d+)", endpoint)
    if match is None:
        return False
    try:
        with socket.create_connection((match["host"], int(match["port"])), timeout=_PROBE_TIMEOUT_S):
            return True
    except OSError:
        return False


def describe_zenoh_error(error: BaseException, *, connect: Sequence[str] = ()) -> str:
    """One sentence for an operator from a zenoh error: no Rust source paths, the endpoint named.

    Zenoh says "Unable to connect" both when nobody listens and when the daemon refused the
    handshake (wrong user or password, TLS without the right certificate): a TCP probe of the
    endpoint tells the two apart. ``run``, ``target``, ``status`` and ``demo`` print this.
    """
    text = str(error)
    bound = _BOUND_TO.search(text)
    if bound and "Address already in use" in text:
        host = bound["ep"].rsplit(":", 1)[0]
        return (f"{bound['ep']} is already in use: another nanodrift daemon or zenoh program listens there; "
                f"stop it, or listen elsewhere with -l {host}:PORT")
    if bound and "Cannot assign requested address" in text:
        return f"cannot listen on {bound['ep']}: that address is not one of this computer's"
    unable = _UNABLE.search(text)
    if unable:
        endpoints = _SINGLE.findall(unable["eps"]) or list(connect)
        answering = [ep for ep in endpoints if _reachable(ep)]
        if answering:
            return (f"{', '.join(answering)} answered but refused the session: authentication refused "
                    "(check the user and password in --zenoh-config) or a different protocol (tls/tcp)")
        where = ", ".join(endpoints) or "the configured endpoints"
        return f"nobody is listening at {where} (is the daemon running? which port does it listen on?)"
    cleaned = _RUST_LOCATION.sub("", text).strip()
    return cleaned.rstrip(".]! ").replace("  ", " ") or type(error).__name__


def listen_endpoints(conf: zenoh.Config) -> list[str]:
    """The endpoints a session config listens on (as given: what the operator wrote)."""
    try:
        value = json.loads(conf.get_json("listen/endpoints"))
    except (zenoh.ZError, ValueError):
        return []
    if isinstance(value, dict):  # zenoh's per-mode form: {"router": [...], "peer": [...]}
        mode = json.loads(conf.get_json("mode") or '"peer"')
        value = value.get(mode, [])
    return [str(ep) for ep in value] if isinstance(value, list) else []


OnTarget = Callable[[bytes, "zenoh.Query | None"], None]
OnQuery = Callable[["zenoh.Query"], None]
#: a ``stop`` (its payload; the query when it came as one), thread-safe, called on Zenoh's thread
OnStop = Callable[[bytes, "zenoh.Query | None"], None]

#: How the ``command`` and ``error`` publishers (the answers) meet a subscriber that does not read.
#: Not BLOCK: one frozen subscriber would block every put for zenoh's ``block.wait_before_close``
#: (5 s) until its link is closed, so nobody would get an answer (tests/service/test_congestion.py).
#: DROP: only that subscriber misses answers. Not express: answers are batched when the link backs
#: up, so a queue of 2 batches holds hundreds of answers instead of 2 and a healthy client that
#: lags a few ms loses none (DROP + express lost 1 and 82 answers of a 5000-target burst in
#: benchmarks/daemon_latency.py on a loaded 2-core machine; DROP batched: 0 of 20000, same p50).
ANSWER_CONGESTION = zenoh.CongestionControl.DROP
ANSWER_EXPRESS = False


def undeclare_all(entities: list[Any]) -> None:
    """Undeclare each subscriber/publisher/queryable and empty the list; one the session already dropped
    (a closed session raises ``ZError``) is gone anyway."""
    for entity in entities:
        with contextlib.suppress(zenoh.ZError):
            entity.undeclare()
    entities.clear()


class Bus:
    """The daemon's declarations on one Zenoh session."""

    def __init__(self, session: zenoh.Session, cell: str, prefix: str = DEFAULT_PREFIX) -> None:
        self.session = session
        self.keys = Keys(cell, prefix)
        self._declared: list[Any] = []
        self._telemetry: dict[str, zenoh.Publisher] = {}
        self._token: zenoh.LivelinessToken | None = None
        # ``done`` (how each served command ended) meets a stalled subscriber as the answers do
        command, error, done = (session.declare_publisher(key, congestion_control=ANSWER_CONGESTION,
                                                          express=ANSWER_EXPRESS)
                                for key in (self.keys.command, self.keys.error, self.keys.done))
        #: put one answer (bytes); the publishers' own methods, no wrapper on the hot path
        self.publish_command: Callable[[bytes], None] = command.put
        self.publish_error: Callable[[bytes], None] = error.put
        self.publish_done: Callable[[bytes], None] = done.put

    def serve(self, loop: asyncio.AbstractEventLoop, on_target: OnTarget, on_status: OnQuery,
              on_stop: OnStop | None = None) -> None:
        """Declare the target subscriber and the two queryables (and ``stop``'s subscriber and queryable:
        ``on_stop`` runs on Zenoh's thread like ``on_target``, so a stop is ordered among the targets as
        it arrived); announce liveliness last. ``on_status`` always runs on the loop."""
        call = loop.call_soon_threadsafe
        limit = MAX_PAYLOAD_BYTES  # larger payloads are refused without being copied

        def samples_to(handle: OnTarget) -> Callable[[zenoh.Sample], None]:  # a put of a target or a stop
            def on_sample(sample: zenoh.Sample) -> None:
                payload = sample.payload
                handle(payload.to_bytes() if len(payload) <= limit else Oversized.of(len(payload)), None)
            return on_sample

        def queries_to(handle: OnTarget) -> Callable[[zenoh.Query], None]:  # a query: ``compensate``, ``stop``
            def on_query(query: zenoh.Query) -> None:
                payload = query.payload
                handle(b"" if payload is None else (payload.to_bytes() if len(payload) <= limit
                                                    else Oversized.of(len(payload))), query)
            return on_query

        def status_query(query: zenoh.Query) -> None:
            call(on_status, query)

        self._declared.append(self.session.declare_subscriber(self.keys.target, samples_to(on_target)))
        self._declared.append(self.session.declare_queryable(self.keys.compensate, queries_to(on_target)))
        self._declared.append(self.session.declare_queryable(self.keys.status, status_query))
        if on_stop is not None:
            self._declared.append(self.session.declare_subscriber(self.keys.stop, samples_to(on_stop)))
            self._declared.append(self.session.declare_queryable(self.keys.stop, queries_to(on_stop)))
        self._token = self.session.liveliness().declare_token(self.keys.alive)

    def publish_telemetry(self, role: str, channel: str, payload: bytes, axis: str | None = None) -> None:
        key = self.keys.telemetry(role, channel, axis)
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
        undeclare_all(self._declared)

    def close(self) -> None:
        """Withdraw, undeclare the telemetry, close the session.

        The answer publishers (``command``, ``error``, ``done``) are closed with the session, not undeclared
        one by one: a target that arrived before the withdrawal may still be publishing its answer on Zenoh's
        thread, and undeclaring a publisher during its ``put`` raises ``RuntimeError: Already borrowed``
        (zenoh-python's object is borrowed by the put), which ended a stopping daemon with a traceback and
        exit code 1 under a stream of targets. Closing the session under a ``put`` is safe: that put and any
        later one raise ``ZError``, which the target path handles (``answer_not_sent``).
        """
        self.withdraw()
        undeclare_all(list(self._telemetry.values()))  # published from the loop only, like this call
        self._telemetry.clear()
        if not self.session.is_closed():
            self.session.close()
