"""``nanodrift.service.targets``: every target gets exactly one answer, a command or an error with its id.

A real :class:`CellState` and :class:`Compensator` (the harness' known model), a real
:class:`Actuation` driving a recording actuator, and a recording bus standing for Zenoh; targets
arrive on other threads, as from Zenoh's callbacks, while the asyncio loop runs.
"""

from __future__ import annotations

import asyncio
import json
import logging
import threading
import time
from collections.abc import Awaitable, Callable, Mapping
from pathlib import Path
from typing import Any

import pytest
import zenoh
from helpers.daemon_harness import TEMPS, expected_q, write_test_model

from nanodrift.bus.protocol import Keys
from nanodrift.compensation import Compensator
from nanodrift.config import parse_config
from nanodrift.drivers.base import Actuator, Reading, SensorConfig
from nanodrift.service.actuation import Actuation
from nanodrift.service.state import CellState
from nanodrift.service.table import SensorTable
from nanodrift.service.targets import TargetHandler

NOW = 1000.0


class ManualClock:
    def __init__(self, t: float) -> None:
        self.t = t

    def now(self) -> float:
        return self.t

    async def sleep(self, seconds: float) -> None:
        await asyncio.sleep(0)


class Events:
    """A logger keeping every line; ``debug`` says whether debug lines are wanted."""

    def __init__(self, debug: bool = False) -> None:
        self.debug_on = debug
        self.lines: list[tuple[str, str, dict[str, Any]]] = []

    def is_enabled_for(self, level: int) -> bool:
        return self.debug_on or level > logging.DEBUG

    def __getattr__(self, level: str) -> Callable[..., None]:
        return lambda event, **fields: self.lines.append((level, event, fields))

    def named(self, event: str) -> list[dict[str, Any]]:
        return [fields for _, name, fields in self.lines if name == event]


class RecordingBus:
    """Stands for :class:`nanodrift.bus.session.Bus`: every call, in order, in the shared ``events``."""

    def __init__(self, events: list[tuple[Any, ...]]) -> None:
        self.keys = Keys("t")
        self.events = events
        self.fail: Exception | None = None

    def publish_command(self, data: bytes) -> None:
        if self.fail is not None:
            raise self.fail
        self.events.append(("command", json.loads(data)))

    def publish_error(self, data: bytes) -> None:
        if self.fail is not None:
            raise self.fail
        self.events.append(("error", json.loads(data)))

    def reply(self, query: Any, key: str, data: bytes) -> None:
        self.events.append(("reply", key, json.loads(data)["id"]))

    def reply_err(self, query: Any, data: bytes) -> None:
        self.events.append(("reply_err", json.loads(data)["id"]))

    def answers(self) -> list[tuple[str, dict[str, Any]]]:
        return [(e[0], e[1]) for e in self.events if e[0] in ("command", "error")]


class RecordingActuation(Actuation):
    """The real actuation; its offers and wakes also go into the shared ``events``."""

    def __init__(self, log: Any, events: list[tuple[Any, ...]]) -> None:
        super().__init__(log)
        self.events = events

    def offer(self, q_um: Mapping[str, float], voltage_v: Mapping[str, float],
              positions_um: Mapping[str, float] | None = None, target_id: str | int | None = None) -> bool:
        self.events.append(("offer", None if positions_um is None else positions_um["x"]))
        return super().offer(q_um, voltage_v, positions_um, target_id)

    def wake(self) -> None:
        self.events.append(("wake",))
        super().wake()


class Output(Actuator):
    description = "recording output"

    def __init__(self, events: list[tuple[Any, ...]]) -> None:
        self.events = events

    async def open(self) -> None: ...

    async def close(self) -> None: ...

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        self.events.append(("written", x_um, voltage_v))


class Query:
    def __init__(self) -> None:
        self.dropped = 0

    def drop(self) -> None:
        self.dropped += 1


class Cell:
    def __init__(self, tmp_path: Path, *, model: bool = True, debug: bool = False) -> None:
        self.config = parse_config({"sensors": []})
        self.table = SensorTable([SensorConfig(name=name, kind="x", max_age_s=5.0) for name in TEMPS])
        for name, value in TEMPS.items():
            self.table.update(name, Reading(value, t=NOW), now=NOW)
        loaded = write_test_model(tmp_path / "model.json") if model else None
        self.compensator = Compensator(loaded, {"x": self.config.actuator}, self.table)
        self.compensator.observe(NOW, TEMPS)
        self.clock = ManualClock(NOW + 0.1)
        self.state = CellState(self.config, self.compensator, self.clock)
        self.state.serving = True
        self.events: list[tuple[Any, ...]] = []
        self.log = Events(debug)
        self.bus = RecordingBus(self.events)
        self.actuation = RecordingActuation(self.log, self.events)
        self.output = Output(self.events)

    def handler(self, loop: asyncio.AbstractEventLoop) -> TargetHandler:
        return TargetHandler(self.state, self.bus, loop, self.actuation, self.log)  # type: ignore[arg-type]


def run(body: Callable[[], Awaitable[None]]) -> None:
    asyncio.run(asyncio.wait_for(body(), 30))


async def until(condition: Callable[[], bool], what: str, timeout: float = 5.0) -> None:
    deadline = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < deadline, f"not within {timeout} s: {what}"
        await asyncio.sleep(0.005)


async def settle() -> None:
    """Let the callbacks the handler handed to the loop run."""
    for _ in range(5):
        await asyncio.sleep(0)


def target(x_um: float, target_id: Any) -> bytes:
    return json.dumps({"x_um": x_um, "id": target_id}).encode()


def test_every_target_from_many_threads_gets_exactly_one_command_with_its_id(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    threads, per_thread = 4, 25

    async def body() -> None:
        handler = cell.handler(asyncio.get_running_loop())

        def send(k: int) -> None:
            for i in range(per_thread):
                handler.on_target(target(100.0 + i, f"{k}-{i}"), None)

        workers = [threading.Thread(target=send, args=(k,)) for k in range(threads)]
        for worker in workers:
            worker.start()
        for worker in workers:
            await asyncio.to_thread(worker.join, 10)
        await settle()

    run(body)
    answers = cell.bus.answers()
    ids = [doc["id"] for kind, doc in answers]
    assert sorted(ids) == sorted(f"{k}-{i}" for k in range(threads) for i in range(per_thread))  # each once
    assert {kind for kind, _ in answers} == {"command"}
    for _, doc in answers:
        i = int(doc["id"].split("-")[1])
        assert doc["x_um"] == 100.0 + i
        assert doc["q_um"] == pytest.approx(expected_q(100.0 + i, TEMPS), abs=1e-6)
    assert cell.state.counters.targets == cell.state.counters.commands == threads * per_thread
    assert sum(cell.state.counters.errors.values()) == 0


def test_a_command_is_published_before_the_actuator_hears_of_it_and_the_reply_follows(
        tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    query = Query()

    async def body() -> None:
        await cell.actuation.start({"x": cell.output}, {"x": cell.config.actuator})
        handler = cell.handler(asyncio.get_running_loop())
        cell.events.clear()
        await asyncio.to_thread(handler.on_target, target(120.0, 7), query)  # type: ignore[arg-type]
        await until(lambda: any(e[0] == "written" for e in cell.events), "the output written")
        await cell.actuation.stop()

    run(body)
    order = [e[0] for e in cell.events]
    # the answer first, then the actuation hears of it, then the querier; the write is the loop's business
    assert order[:3] == ["command", "offer", "reply"], cell.events
    assert sorted(order[3:]) == ["wake", "written"], cell.events  # one wake for the burst
    [(_, doc)] = cell.bus.answers()
    assert cell.events[2] == ("reply", cell.bus.keys.compensate, 7)
    [written] = [e for e in cell.events if e[0] == "written"]
    assert written == ("written", 120.0, pytest.approx(doc["voltage_v"]))
    assert query.dropped == 0


def test_the_command_a_target_replaces_ends_superseded_on_the_target_thread_after_its_answer(
        tmp_path: Path) -> None:
    """Each target tells the command it replaced: the loop, which never runs here, would otherwise tell a burst of
    them at its next wake (at 1 kHz, ~20 at each of its 50 wakes a second, holding the GIL while targets wait)."""
    cell = Cell(tmp_path)
    handler = cell.handler(asyncio.new_event_loop())
    told: list[tuple[Any, str, str]] = []
    cell.actuation._active = True  # a drive loop runs (it is never woken here)
    cell.actuation.done_listeners.append(
        lambda goal, state, held, error: told.append((goal.id, state, threading.current_thread().name)))
    cell.events.clear()
    for i in range(1, 6):
        handler.on_target(target(100.0 + i, i), None)
        if i > 1:  # the one it replaced ended before this target's handler returned, after its command went out
            assert told[-1] == (i - 1, "superseded", threading.current_thread().name), told
            assert [e[0] for e in cell.events][-2:] == ["command", "offer"], cell.events
    assert [t[0] for t in told] == [1, 2, 3, 4]  # one each; the newest is still pending, owed its done
    handler.loop.close()


@pytest.mark.parametrize(
    ("kind", "payload", "setup"),
    [
        ("bad_payload", b"{not json", None),
        ("out_of_workspace", target(1e6, 3), None),
        ("no_model", target(100.0, 3), "no_model"),
        ("stale", target(100.0, 3), "stale"),
        ("actuator_fault", target(100.0, 3), "actuator_fault"),
        ("shutting_down", target(100.0, 3), "stopping"),
        ("internal", target(100.0, 3), "bug"),
    ],
)
def test_each_refusal_is_one_error_with_its_kind_and_id_and_nothing_reaches_the_actuator(
        tmp_path: Path, kind: str, payload: bytes, setup: str | None) -> None:
    cell = Cell(tmp_path, model=setup != "no_model")
    if setup == "stale":
        cell.clock.t = NOW + 60.0  # the readings are a minute old (max_age_s 5)
    elif setup == "actuator_fault":
        cell.actuation.fault_reason = "write failed: no response"
    elif setup == "stopping":
        cell.state.stopping = True
    elif setup == "bug":
        def broken(*args: Any) -> Any:
            raise RuntimeError("a bug")

        cell.compensator.compensate = broken  # type: ignore[method-assign]
    query = Query()

    async def body() -> None:
        handler = cell.handler(asyncio.get_running_loop())
        await asyncio.to_thread(handler.on_target, payload, query)  # type: ignore[arg-type]
        await settle()

    run(body)
    [(answer, doc)] = cell.bus.answers()
    assert answer == "error" and doc["kind"] == kind, doc
    assert doc["id"] == (None if kind == "bad_payload" else 3)
    assert [e for e in cell.events if e[0] in ("offer", "wake")] == []
    assert cell.events[-1] == ("reply_err", doc["id"])
    assert cell.state.counters.targets == 1 and cell.state.counters.commands == 0
    assert cell.state.counters.errors == {kind: 1}
    [refused] = cell.log.named("target_refused")
    assert refused["kind"] == kind and refused["id"] == doc["id"]
    if kind == "actuator_fault":
        assert "write failed: no response" in doc["error"]
    if kind == "internal":
        assert "RuntimeError: a bug" in doc["error"]
        assert "RuntimeError('a bug')" in cell.log.named("target_failed")[0]["error"]


def test_a_refusal_flood_is_logged_rate_limited_but_every_target_is_answered(tmp_path: Path) -> None:
    cell = Cell(tmp_path)

    async def body() -> None:
        handler = cell.handler(asyncio.get_running_loop())
        for i in range(200):
            handler.on_target(target(-5000.0, i), None)
        await settle()
        assert len(cell.bus.answers()) == 200
        logged = cell.log.named("target_refused")
        assert 0 < len(logged) < 200
        assert len(logged) + handler.take_suppressed() == 200  # not logged is counted

    run(body)


def test_a_daemon_that_is_not_serving_yet_answers_nothing_and_frees_the_query(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    cell.state.serving = False
    query = Query()

    async def body() -> None:
        handler = cell.handler(asyncio.get_running_loop())
        handler.on_target(target(100.0, 1), query)  # type: ignore[arg-type]
        await settle()

    run(body)
    assert cell.events == [] and query.dropped == 1 and cell.state.counters.targets == 0


def test_a_bus_that_fails_to_publish_is_logged_and_the_query_freed_and_the_actuator_not_told(tmp_path: Path) -> None:
    cell = Cell(tmp_path)
    cell.bus.fail = zenoh.ZError("session closed")
    query = Query()

    async def body() -> None:
        handler = cell.handler(asyncio.get_running_loop())
        await asyncio.to_thread(handler.on_target, target(100.0, 1), query)  # type: ignore[arg-type]
        await settle()

    run(body)
    assert cell.events == [] and query.dropped == 1
    assert cell.log.named("answer_not_sent") == [{"error": "session closed"}]


def test_at_debug_every_answer_is_logged_with_its_latency_and_at_info_none(tmp_path: Path) -> None:
    for debug in (True, False):
        cell = Cell(tmp_path, debug=debug)

        async def body(cell: Cell = cell) -> None:
            handler = cell.handler(asyncio.get_running_loop())
            handler.on_target(target(100.0, "a"), None)
            handler.on_target(target(1e6, "b"), None)
            await settle()

        run(body)
        lines = cell.log.named("target_answered")
        if not debug:
            assert lines == []
            continue
        served, refused = lines
        assert served["id"] == "a" and served["x_um"] == 100.0 and served["latency_us"] > 0
        assert refused["id"] == "b" and refused["error"] == "out_of_workspace"
