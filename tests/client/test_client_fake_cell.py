"""``nanodrift.Client``'s waiting logic against a stand-in cell: a Zenoh peer in this process that answers
``compensate`` and ``stop`` and publishes ``done`` when the test says so (the wire format of the README).

The daemon itself is exercised in ``test_client.py`` and ``test_client_done.py``; here the order of events
is the test's: a ``done`` that overtakes the query's reply, a move superseded, a stop from another thread,
a ``done`` that never comes.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import zenoh
from helpers.daemon_harness import free_port

from nanodrift import Client, MoveEnded, Refused
from nanodrift.bus.session import session_config

PREFIX = "site/a"
CELL = "fake"


class FakeCell:
    """A peer listening on 127.0.0.1 that serves one cell's ``compensate``, ``stop`` and ``done``."""

    def __init__(self, prefix: str = PREFIX) -> None:
        self.port = free_port()
        self.base = f"{prefix}/{CELL}"
        self.session = zenoh.open(session_config(mode="peer", listen=[f"tcp/127.0.0.1:{self.port}"],
                                                 multicast_scouting=False))
        self.lock = threading.Condition()
        self.in_flight: Any = None
        self.targets: list[dict[str, Any]] = []
        #: what to do with a target: "reached_first" (done before the reply), "reached", "hold" (no done), "refuse",
        #: "stall" (take the query and never answer it: a stalled daemon; zenoh ends it as a "Timeout" reply error)
        self.behaviour = "reached"
        self.stall_stop = False  # take stop queries and never answer them
        self.held: list[zenoh.Query] = []
        self._entities = [self.session.declare_queryable(f"{self.base}/compensate", self._compensate),
                          self.session.declare_queryable(f"{self.base}/stop", self._stop)]

    def done(self, target_id: Any, state: str, error: str | None = None) -> None:
        self.session.put(f"{self.base}/done", json.dumps(
            {"id": target_id, "state": state, "t": 0.0, "voltage_v": 1.0, "error": error}))

    def _compensate(self, query: zenoh.Query) -> None:
        doc = json.loads(query.payload.to_bytes()) if query.payload is not None else {}
        target_id = doc.get("id")
        with self.lock:
            self.targets.append(doc)
            previous, self.in_flight = self.in_flight, target_id
            self.lock.notify_all()
        if self.behaviour == "stall":
            self.held.append(query)
            return
        if self.behaviour == "refuse":
            query.reply_err(json.dumps({"id": target_id, "error": "no", "kind": "bad_payload"}))
            query.drop()
            return
        if previous is not None:
            self.done(previous, "superseded")
        command = {"id": target_id, "x_um": doc.get("x_um"), "q_um": 1.5, "voltage_v": 0.03,
                   "temperatures_c": {"T1": 21.0}, "model": "m-fake", "t": 1.0, "extrapolating": [],
                   "q_sigma_um": 0.01}
        if self.behaviour == "reached_first":
            self.done(target_id, "reached")
        query.reply(f"{self.base}/compensate", json.dumps(command))
        query.drop()
        if self.behaviour == "reached":
            self.done(target_id, "reached")

    def _stop(self, query: zenoh.Query) -> None:
        if self.stall_stop:
            self.held.append(query)
            return
        with self.lock:
            stopped, self.in_flight = self.in_flight, None
        if stopped is not None:
            self.done(stopped, "stopped")
        query.reply(f"{self.base}/stop", json.dumps({"voltage_v": 0.5}))
        query.drop()

    def wait_targets(self, n: int) -> None:
        with self.lock:
            assert self.lock.wait_for(lambda: len(self.targets) >= n, 10), self.targets

    def close(self) -> None:
        for entity in self._entities:
            entity.undeclare()
        self.held.clear()
        self.session.close()


@pytest.fixture
def fake() -> Iterator[FakeCell]:
    cell = FakeCell()
    yield cell
    cell.close()


def connect(fake: FakeCell) -> Client:
    return Client(f"tcp/127.0.0.1:{fake.port}", cell=CELL, prefix=PREFIX)


@pytest.mark.parametrize("behaviour", ["reached", "reached_first"])
def test_move_returns_on_reached_even_when_done_overtakes_the_reply(fake: FakeCell, behaviour: str) -> None:
    fake.behaviour = behaviour
    with connect(fake) as cell:
        command = cell.move(12.0, timeout_s=5.0)
    assert command.done is not None and command.done["state"] == "reached" and command.done["id"] == command.id
    assert command.q_um == 1.5 and command.q_sigma_um == 0.01 and command.target == 12.0


def background(call: Callable[[], Any]) -> tuple[threading.Thread, list[Any]]:
    out: list[Any] = []

    def run() -> None:
        try:
            out.append(call())
        except BaseException as error:  # the test asserts which
            out.append(error)

    thread = threading.Thread(target=run)
    thread.start()
    return thread, out


def test_stop_from_another_thread_ends_the_waiting_move(fake: FakeCell) -> None:
    fake.behaviour = "hold"
    with connect(fake) as cell:
        thread, out = background(lambda: cell.move(100.0, timeout_s=10.0))
        fake.wait_targets(1)
        assert cell.stop() == {"voltage_v": 0.5}
        thread.join(10)
        assert not thread.is_alive()
    assert len(out) == 1 and isinstance(out[0], MoveEnded), out
    assert out[0].state == "stopped" and out[0].error is None and out[0].command.target == 100.0


def test_a_newer_target_supersedes_the_waiting_move(fake: FakeCell) -> None:
    fake.behaviour = "hold"
    with connect(fake) as cell, connect(fake) as other:
        thread, out = background(lambda: cell.move(100.0, timeout_s=10.0))
        fake.wait_targets(1)
        newer = other.move(200.0, wait=False)
        thread.join(10)
    assert isinstance(out[0], MoveEnded) and out[0].state == "superseded", out
    assert newer.id != out[0].command.id


def test_no_done_in_time_is_a_timeout_and_a_refusal_is_refused(fake: FakeCell) -> None:
    fake.behaviour = "hold"
    with connect(fake) as cell:
        with pytest.raises(TimeoutError, match="no done for move"):
            cell.move(1.0, timeout_s=0.3)
        fake.behaviour = "refuse"
        with pytest.raises(Refused) as caught:
            cell.move(1.0, timeout_s=5.0)
    assert caught.value.kind == "bad_payload" and caught.value.error == "no"


def test_a_failed_done_carries_its_error(fake: FakeCell) -> None:
    fake.behaviour = "hold"
    with connect(fake) as cell:
        thread, out = background(lambda: cell.move(5.0, timeout_s=10.0))
        fake.wait_targets(1)
        fake.done(fake.targets[0]["id"], "failed", "PI error 7: axis not referenced")
        thread.join(10)
    assert isinstance(out[0], MoveEnded) and (out[0].state, out[0].error) == ("failed",
                                                                                "PI error 7: axis not referenced")


def test_closing_the_client_ends_a_waiting_move(fake: FakeCell) -> None:
    fake.behaviour = "hold"
    cell = connect(fake)
    thread, out = background(lambda: cell.move(5.0, timeout_s=10.0))
    fake.wait_targets(1)
    cell.close()
    thread.join(10)
    assert isinstance(out[0], RuntimeError) and "closed" in str(out[0])


def test_stop_without_an_answer_puts_it_and_times_out() -> None:
    fake = FakeCell()
    heard: list[bytes] = []
    got = threading.Event()

    def on_stop(sample: zenoh.Sample) -> None:
        heard.append(sample.payload.to_bytes())
        got.set()

    fake._entities[1].undeclare()  # no stop queryable: a daemon that takes stop as a put only
    fake._entities = fake._entities[:1]
    subscriber = fake.session.declare_subscriber(f"{fake.base}/stop", on_stop)
    try:
        with connect(fake) as cell:
            with pytest.raises(TimeoutError, match="the stop was also put"):
                cell.stop(timeout_s=0.3)
        assert got.wait(5) and json.loads(heard[0]) == {}
    finally:
        subscriber.undeclare()
        fake.close()


def test_a_query_taken_and_never_answered_is_a_timeout_not_a_refusal(fake: FakeCell) -> None:
    """Zenoh ends such a query with a reply error "Timeout": no answer, which the client must not report as the
    daemon refusing the target (an EPICS put would say "refused: Timeout"), and after which a stop is also put."""
    fake.behaviour, fake.stall_stop = "stall", True
    heard = threading.Event()
    subscriber = fake.session.declare_subscriber(f"{fake.base}/stop", lambda sample: heard.set())
    try:
        with connect(fake) as cell:
            with pytest.raises(TimeoutError) as ended:
                cell.move(5.0, timeout_s=0.5)
            assert not isinstance(ended.value, Refused)
            assert len(fake.held) == 1  # the query did reach the cell
            with pytest.raises(TimeoutError, match="the stop was also put"):
                cell.stop(timeout_s=0.5)
        assert heard.wait(5)
    finally:
        subscriber.undeclare()
