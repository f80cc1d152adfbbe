"""``nanodrift.Client``: the client a lab script, a notebook, Bluesky, the EPICS bridge and the CLI's own
``target`` and ``status`` use to move a cell and read it (README, *Python API*, shows it in use).

Synchronous and thread-safe: every method may be called from any thread; the Zenoh callbacks (the
``done`` subscriber) only fill a table under one condition variable, which the waiting ``move`` reads.
What the keys and payloads are is :mod:`nanodrift.bus.protocol`'s and the README's; this module only
sends, waits and turns answers into Python values and exceptions.
"""

from __future__ import annotations

import itertools
import json
import math
import threading
import time
import uuid
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from types import TracebackType
from typing import Any

import zenoh

from nanodrift.bus.protocol import DEFAULT_PREFIX, Keys, key_prefix
from nanodrift.bus.session import describe_zenoh_error, session_config, undeclare_all
from nanodrift.settings import ZenohSettings, checked_prefix

__all__ = ["Client", "Command", "MoveEnded", "Refused", "client_config", "json_object", "number", "outcome",
           "status_key"]

#: seconds to collect the cells' ``status`` replies when a cell did not answer (to name those that do)
DISCOVERY_TIMEOUT_S = 2.0
Position = float | Mapping[str, float]
Endpoints = str | Sequence[str] | None


class Refused(Exception):
    """The daemon refused the target (an ``error`` answer): ``kind`` (``outside_workspace``,
    ``bad_payload``, ``stale``, ...), ``error`` (what was wrong, in words), ``id`` (the target's id);
    ``payload`` is the error object as received."""

    def __init__(self, kind: str, error: str, target_id: Any, payload: Mapping[str, Any] | None = None) -> None:
        super().__init__(error)
        self.kind = kind
        self.error = error
        self.id = target_id
        self.payload: dict[str, Any] = dict(payload) if payload is not None else {
            "id": target_id, "error": error, "kind": kind}


class MoveEnded(Exception):
    """A move the daemon answered but that ended without being reached: ``state`` ``stopped``,
    ``superseded`` or ``failed`` (its ``done``), ``error`` (why it failed, else None), ``command`` (the
    :class:`Command` the daemon had answered)."""

    def __init__(self, state: str, error: str | None, command: Command) -> None:
        why = f": {error}" if error else ""
        super().__init__(f"move {command.id!r} ended {state}{why}")
        self.state = state
        self.error = error
        self.command = command


@dataclass(frozen=True)
class Command:
    """The daemon's answer to one target (its ``command`` payload).

    In a one-axis cell ``target``, ``q_um``, ``voltage_v`` and ``q_sigma_um`` are numbers; in a cell of
    several axes, mappings by axis. ``q_sigma_um`` is None where the model carries no uncertainty.
    ``extrapolating`` lists what lies outside the model's training range (axes, channels).
    ``payload`` is the raw ``command`` object; ``done`` the ``done`` object that ended the move
    (None for ``move(wait=False)``).
    """

    id: str | int | None
    target: Position
    q_um: Position
    voltage_v: Position
    q_sigma_um: float | Mapping[str, float] | None
    extrapolating: list[str]
    model: str | None
    t: float
    payload: Mapping[str, Any] = field(repr=False)
    done: Mapping[str, Any] | None = field(default=None, repr=False)

    @classmethod
    def from_payload(cls, doc: Mapping[str, Any], done: Mapping[str, Any] | None = None) -> Command:
        """A ``command`` payload (one axis or several) as a :class:`Command`."""
        q = doc.get("q_um")
        if isinstance(q, Mapping):
            target: Position = {axis: float(doc[f"{axis}_um"]) for axis in q if f"{axis}_um" in doc}
        else:
            target = float(doc.get("x_um", math.nan))
        t = number(doc.get("t"))
        return cls(id=doc.get("id"), target=target, q_um=_position(q), voltage_v=_position(doc.get("voltage_v")),
                   q_sigma_um=_by_axis(doc.get("q_sigma_um")), extrapolating=list(doc.get("extrapolating") or []),
                   model=doc.get("model"), t=math.nan if t is None else t,
                   payload=dict(doc), done=dict(done) if done is not None else None)

    def with_done(self, done: Mapping[str, Any]) -> Command:
        return Command.from_payload(self.payload, done)


def outcome(command: Command, done: Mapping[str, Any]) -> Command:
    """The move of ``command`` ended by ``done``: the command with its done when ``reached``, else
    :class:`MoveEnded` (``stopped``, ``superseded``, ``failed``). Shared by :meth:`Client.move` and the
    asyncio bridges, which await the ``done`` on their loop (:mod:`nanodrift.async_moves`)."""
    ended = command.with_done(done)
    state = str(done.get("state"))
    if state == "reached":
        return ended
    error = done.get("error")
    raise MoveEnded(state, str(error) if error is not None else None, ended)


def json_object(raw: bytes) -> dict[str, Any] | None:
    """A payload as a JSON object; None when it is not one (a stray payload never raises in a callback)."""
    try:
        doc = json.loads(raw)
    except ValueError:
        return None
    return doc if isinstance(doc, dict) else None


def number(value: Any) -> float | None:
    """A finite JSON number as a float (a bool is not one), else None: what a payload's number must be."""
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    value = float(value)
    return value if math.isfinite(value) else None


def _by_axis(value: Any) -> float | dict[str, float] | None:
    """A payload's value of one axis (a number) or several (a mapping by axis; nan where not a number);
    None when it is neither."""
    if isinstance(value, Mapping):
        return {str(k): math.nan if (v := number(each)) is None else v for k, each in value.items()}
    return number(value)


def _position(value: Any) -> Position:
    found = _by_axis(value)
    return math.nan if found is None else found


#: the reply error zenoh itself delivers when a query's timeout ran out before the queryable that took it
#: answered (a stalled daemon); a daemon's own refusals are JSON objects, never this
QUERY_TIMED_OUT = b"Timeout"


def _refused(raw: bytes, target_id: Any) -> Refused:
    """A reply error as :class:`Refused`: the daemon's error object, else its text."""
    doc = json_object(raw)
    if doc is None:
        return Refused("reply_error", raw.decode("utf-8", "replace"), target_id)
    return Refused(str(doc.get("kind") or "refused"), str(doc.get("error")), doc.get("id", target_id), doc)


def _endpoints(endpoint: Endpoints) -> list[str]:
    if endpoint is None:
        return []
    return [endpoint] if isinstance(endpoint, str) else [str(ep) for ep in endpoint]


def client_config(endpoint: Endpoints = None, *, zenoh_config: str | Path | None = None, mode: str | None = None,
                  label: str = "zenoh_config") -> zenoh.Config:
    """A client's session config: ``zenoh_config`` (a zenoh json5: credentials, TLS) as the base, then the
    endpoints and ``mode``.

    Without a file: client mode towards the endpoints, else a peer that scouts. With a file, its mode,
    endpoints and scouting stand unless endpoints or ``mode`` are given (the zenoh examples' rule).
    ``label`` names the file's option in messages (``--zenoh-config`` for the CLI). A missing file is a
    :class:`FileNotFoundError`, one zenoh refuses a :class:`ValueError`.
    """
    connect = _endpoints(endpoint)
    if not zenoh_config:
        return session_config(mode=mode or ("client" if connect else "peer"), connect=connect,
                              multicast_scouting=not connect)  # an explicit endpoint needs no scouting
    if not Path(zenoh_config).is_file():
        raise FileNotFoundError(f"{label} {zenoh_config}: no such file")
    try:
        return session_config(ZenohSettings(config_file=Path(zenoh_config)), mode=mode, connect=connect,
                              multicast_scouting=False if connect else None)
    except zenoh.ZError as error:
        raise ValueError(f"{label} {zenoh_config}: zenoh cannot use it: {error}") from None


def status_key(cell: str | None, prefix: str = DEFAULT_PREFIX) -> str:
    """One cell's ``status`` key, or every cell's (``None``: ``<prefix>/*/status``)."""
    return f"{key_prefix(cell or '*', prefix)}/status"


class Client:
    """One cell of the network (``cell``), or the network's cells (``cell=None``: :meth:`statuses` only).

    ``endpoint``: ``"tcp/HOST:PORT"``, a list of them, or None (a peer that finds the daemons by
    scouting); ``zenoh_config``: a zenoh json5 file (credentials, TLS) used as the base; ``prefix``: the
    daemons' ``[zenoh] prefix``. A session that cannot open is a :class:`ConnectionError` naming where.
    ``mode`` (``"peer"``/``"client"``) overrides the session's mode, as the CLI's ``--mode``; ``label`` is
    how messages name ``zenoh_config`` (the CLI: ``--zenoh-config``).

    How a move is sent: through the ``compensate`` queryable, not a ``target`` put. A query gets exactly
    its own answer (the command, or the refusal as a reply error), so nothing has to pick this client's
    answer out of every client's ``command``/``error`` broadcasts, and a daemon that is not there is told
    by the query's end rather than a guessed wait. The ``done`` subscriber is declared once, when the
    client opens, and each move's id is registered before its query leaves, so a ``done`` that overtakes
    the query's reply is kept, never missed.
    """

    def __init__(self, endpoint: Endpoints = None, cell: str | None = "cell0", *,
                 zenoh_config: str | Path | None = None, prefix: str = DEFAULT_PREFIX, mode: str | None = None,
                 label: str = "zenoh_config") -> None:
        self.endpoints = _endpoints(endpoint)
        self.cell = cell
        self.prefix = checked_prefix(prefix, label="prefix: ")
        self.keys = Keys(cell or "*", prefix)
        self._where = ", ".join(self.endpoints) or (str(zenoh_config) if zenoh_config else "scouting")
        conf = client_config(self.endpoints, zenoh_config=zenoh_config, mode=mode, label=label)
        try:
            #: the underlying zenoh session, for what the client does not wrap (telemetry subscribers)
            self.session: zenoh.Session = zenoh.open(conf)
        except zenoh.ZError as error:
            raise ConnectionError(f"cannot open a zenoh session ({self._where}): "
                                  f"{describe_zenoh_error(error, connect=self.endpoints)}") from None
        self._cond = threading.Condition()
        self._closed = False
        self._pending: dict[str | int, dict[str, Any] | None] = {}  # id -> its done, once it came
        self._unanswered = ""  # why the cell does not answer, asked once until it answers again
        self._ids = itertools.count()
        self._id_base = uuid.uuid4().hex[:12]
        self._subscribers: list[Any] = []
        if cell is not None:
            self._subscribers.append(self.session.declare_subscriber(self.keys.done, self._on_done))

    # --- lifetime ---------------------------------------------------------------------------------

    def __enter__(self) -> Client:
        return self

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()

    def close(self) -> None:
        """Undeclare the subscribers and close the session; a ``move`` still waiting raises. Idempotent."""
        with self._cond:
            if self._closed:
                return
            self._closed = True
            self._cond.notify_all()
        undeclare_all(self._subscribers)
        if not self.session.is_closed():
            self.session.close()

    @property
    def closed(self) -> bool:
        return self._closed

    # --- moving -----------------------------------------------------------------------------------

    def new_id(self) -> str:
        """A target id no other client or invocation shares: a random prefix and this client's counter."""
        return f"{self._id_base}-{next(self._ids)}"

    def move(self, target: Position, *, wait: bool = True, timeout_s: float = 60.0,
             id: str | int | None = None, on_answer: Callable[[Command], None] | None = None) -> Command:
        """Send ``target`` (µm; a mapping by axis in a cell of several axes) and return the answered
        :class:`Command` once its ``done`` says ``reached`` (``wait=False``: at once).

        :class:`Refused` when the daemon refuses the target; :class:`MoveEnded` on a ``done`` of
        ``stopped``, ``superseded`` or ``failed``; :class:`TimeoutError` when no answer, or no ``done``,
        comes within ``timeout_s``. ``id`` defaults to a fresh unique one (:meth:`new_id`).
        ``on_answer`` is called (in this thread) with the answered command before the wait for its
        ``done``: a bridge that shows "moving" (the EPICS ``DMOV``) only for a move the daemon took.
        """
        cell = self._cell()
        target_id: str | int = self.new_id() if id is None else id
        deadline = time.monotonic() + timeout_s
        if wait:
            with self._cond:
                self._check_open()
                self._pending[target_id] = None  # before the query leaves: a fast done is kept
        try:
            command = self._ask(cell, target, target_id, timeout_s)
            if on_answer is not None:
                on_answer(command)
            if not wait:
                return command
            return self._wait_done(command, target_id, deadline, timeout_s)
        finally:
            if wait:
                with self._cond:
                    self._pending.pop(target_id, None)

    def _request(self, target: Position, target_id: str | int) -> str:
        if isinstance(target, Mapping):
            return json.dumps({**{f"{axis}_um": float(v) for axis, v in target.items()}, "id": target_id})
        return json.dumps({"x_um": float(target), "id": target_id})

    def _ask(self, cell: str, target: Position, target_id: str | int, timeout_s: float) -> Command:
        key = self.keys.compensate
        try:
            for reply in self.session.get(key, payload=self._request(target, target_id), timeout=timeout_s):
                result = reply.result  # a Sample, or a ReplyError
                raw = result.payload.to_bytes()
                if not isinstance(result, zenoh.Sample) and raw == QUERY_TIMED_OUT:
                    break  # taken and not answered in time: no answer, not a refusal
                self._unanswered = ""
                if not isinstance(result, zenoh.Sample):
                    raise _refused(raw, target_id)
                doc = json_object(raw)
                if doc is None:
                    raise Refused("bad_reply", f"the reply on {key} is not a JSON object: {raw[:200]!r}", target_id)
                return Command.from_payload(doc)
            self._unanswered = self._unanswered or self.no_answer(key, timeout_s)
        except zenoh.ZError as error:  # the session closed under the query (close() from another thread)
            self._check_open()
            raise ConnectionError(f"the query of cell {cell!r} failed ({self._where}): "
                                  f"{describe_zenoh_error(error, connect=self.endpoints)}") from None
        raise TimeoutError(self._unanswered)

    def _wait_done(self, command: Command, target_id: str | int, deadline: float, timeout_s: float) -> Command:
        with self._cond:
            while True:
                self._check_open()
                done = self._pending.get(target_id)
                if done is not None:
                    break
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"no done for move {target_id!r} on {self.keys.prefix}/done within "
                                       f"{timeout_s:g} s (the command was answered; the output may still be ramping)")
                self._cond.wait(remaining)
        return outcome(command, done)

    def _on_done(self, sample: zenoh.Sample) -> None:
        """Zenoh's thread: keep a ``done`` whose id a ``move`` waits for; ignore the rest."""
        doc = json_object(sample.payload.to_bytes())
        target_id = doc.get("id") if doc is not None else None
        if doc is None or not isinstance(target_id, str | int):
            return
        with self._cond:
            if target_id in self._pending and self._pending[target_id] is None:
                self._pending[target_id] = doc
                self._cond.notify_all()

    def stop(self, id: str | int | None = None, *, timeout_s: float = 5.0) -> dict[str, Any]:
        """Every output of the cell holds where it is; the move in flight ends ``stopped``.

        A query on ``stop``, so this returns once the daemon has answered (its reply, the values
        held, as a dict). No reply within ``timeout_s``: the stop is also put (a daemon that takes it
        only as a put still gets it), then :class:`TimeoutError`. ``id``: the move to stop (optional).
        """
        self._cell()
        key = self.keys.stop
        payload = json.dumps({} if id is None else {"id": id})
        for reply in self.session.get(key, payload=payload, timeout=timeout_s):
            result = reply.result
            raw = result.payload.to_bytes()
            if not isinstance(result, zenoh.Sample) and raw == QUERY_TIMED_OUT:
                break  # taken and not answered in time: put the stop too
            if not isinstance(result, zenoh.Sample):
                raise _refused(raw, id)
            doc = json_object(raw)
            return doc if doc is not None else {"reply": raw.decode("utf-8", "replace")}
        self.session.put(key, payload)
        raise TimeoutError(f"no answer on {key} within {timeout_s:g} s ({self._where}); the stop was also put")

    # --- reading ----------------------------------------------------------------------------------

    def status(self, *, timeout_s: float = 5.0) -> dict[str, Any]:
        """The cell's ``status`` payload as a dict (it names its ``"cell"``); :class:`TimeoutError` when
        the cell does not answer within ``timeout_s``."""
        key = status_key(self._cell(), self.prefix)
        for reply in self.session.get(key, timeout=timeout_s):
            result = reply.result
            doc = json_object(result.payload.to_bytes()) if isinstance(result, zenoh.Sample) else None
            if doc is not None:
                return doc
        raise TimeoutError(f"no answer on {key} within {timeout_s:g} s ({self._where}): is the daemon of cell "
                           f"{self.cell!r} running?")

    def statuses(self, cell: str | None = None, *, timeout_s: float = 2.0, retry_s: float = 0.2
                 ) -> list[dict[str, Any]]:
        """Every cell's ``status`` (``<prefix>/*/status``; ``cell``: that one only), sorted by cell.

        Queries until some cell answers or ``timeout_s`` is over (a scouting peer needs a moment to
        find them); an empty list when none does."""
        key = status_key(cell, self.prefix)
        deadline = time.monotonic() + timeout_s
        while True:
            docs = self._query_status(key, max(deadline - time.monotonic(), 0.05))
            if docs or deadline - time.monotonic() <= retry_s:
                return docs
            time.sleep(retry_s)

    def _query_status(self, key: str, timeout_s: float) -> list[dict[str, Any]]:
        """Every reply to one query on ``key``, sorted by cell; errors and non-JSON replies are skipped."""
        docs: dict[str, dict[str, Any]] = {}
        for reply in self.session.get(key, target=zenoh.QueryTarget.ALL, consolidation=zenoh.ConsolidationMode.NONE,
                                      timeout=timeout_s):
            sample = reply.ok
            doc = json_object(sample.payload.to_bytes()) if sample is not None else None
            if sample is not None and doc is not None:
                under = str(sample.key_expr)[len(self.prefix) + 1:]
                cell = str(doc.get("cell") or under.split("/")[0])
                docs[cell] = doc
        return [docs[cell] for cell in sorted(docs)]

    @classmethod
    def cells(cls, endpoint: Endpoints = None, *, prefix: str = DEFAULT_PREFIX, zenoh_config: str | Path | None = None,
              timeout_s: float = 2.0) -> list[dict[str, Any]]:
        """Every cell's ``status`` on the network under ``prefix``, sorted by cell (empty when none answers)."""
        with cls(endpoint, None, prefix=prefix, zenoh_config=zenoh_config) as network:
            return network.statuses(timeout_s=timeout_s)

    def no_answer(self, key: str, timeout_s: float) -> str:
        """Why nothing answered on ``key``: a cell nobody serves (naming those that answer), or no daemon at all."""
        cell = self.cell
        everyone = status_key(None, self.prefix)
        docs = self._query_status(everyone, min(timeout_s, DISCOVERY_TIMEOUT_S))
        cells = [str(doc.get("cell")) for doc in docs]
        if cell in cells:
            return (f"cell {cell!r} answers status but gave no command on {key} within {timeout_s:g} s "
                    f"(a busy or stalled daemon: nanodrift status --cell {cell})")
        if cells:
            return (f"no daemon serves cell {cell!r} (nothing answers on {key}); the cell(s) answering on this "
                    f"network: {', '.join(cells)} (--cell {cells[0]})")
        return (f"no daemon serves cell {cell!r}, and no cell answered on {everyone} either "
                "(is the daemon running? give its endpoint with -e tcp/HOST:PORT)")

    # --- helpers ----------------------------------------------------------------------------------

    def _cell(self) -> str:
        if self.cell is None:
            raise ValueError("this client names no cell (Client(endpoint, cell=...)): it can only list statuses")
        self._check_open()
        return self.cell

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"the client of cell {self.cell!r} is closed")
