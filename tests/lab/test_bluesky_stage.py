"""``nanodrift.bluesky.Stage`` driven by a real ``RunEngine`` against simulated cells served by real daemons
(``nanodrift run`` subprocesses, Zenoh over 127.0.0.1): ``bps.mv``, a 5-point ``scan`` and ``count`` on one
axis and on XY (a motor per axis); a refused move fails the plan's status with the refusal; a ``stop``
mid-ramp ends the move ``stopped`` and the output holds short of the target.

Every wait is on an event (a ``done``, a published command, a status); the slew makes the ramp long enough
to be stopped (a 0 -> 480 µm move ramps for 1.9 s at 250 µm/s).
"""

from __future__ import annotations

import asyncio
import os
import threading
from collections.abc import Iterator
from typing import Any

import pytest
from bluesky import RunEngine
from bluesky import plan_stubs as bps
from bluesky import plans as bp
from bluesky.run_engine import call_in_bluesky_event_loop
from bluesky.utils import FailedStatus
from helpers.running_cell import VOLTS_PER_UM, RunningCell
from helpers.scripted_cell import ScriptedCell
from ophyd_async.core import init_devices

from nanodrift import Client, MoveEnded, Refused
from nanodrift.bluesky import Stage

SLEW_UM_PER_S = 250.0
#: how far the measured position may lie from a compensated target: the simulated interferometer's
#: noise (tens of nm) and the model's residual on the simulated cell (~0.1 µm)
MEASURED_TOLERANCE_UM = 0.5


@pytest.fixture(scope="module")
def run_engine() -> RunEngine:
    return RunEngine({})


@pytest.fixture(scope="module")
def one_axis(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningCell]:
    cell = RunningCell(tmp_path_factory.mktemp("one"), "bs1", slew_um_per_s=SLEW_UM_PER_S)
    yield cell
    assert cell.close() == 0


@pytest.fixture(scope="module")
def stage(run_engine: RunEngine, one_axis: RunningCell) -> Iterator[Stage]:
    with init_devices():
        stage = Stage(one_axis.endpoint, one_axis.cell, name="stage")
    yield stage
    stage.close()


def events(run_engine: RunEngine, plan: Any) -> list[dict[str, Any]]:
    """Run ``plan``; the ``data`` of every event document it emitted."""
    found: list[dict[str, Any]] = []
    token = run_engine.subscribe(lambda name, doc: found.append(doc["data"]) if name == "event" else None)
    try:
        run_engine(plan)
    finally:
        run_engine.unsubscribe(token)
    return found


def test_mv_moves_the_cell_and_the_readings_are_the_answered_command(run_engine: RunEngine, stage: Stage,
                                                                     one_axis: RunningCell) -> None:
    run_engine(bps.mv(stage, 240.0))
    [data] = events(run_engine, bp.count([stage], num=1))
    assert data["stage-setpoint"] == 240.0
    assert data["stage"] == pytest.approx(240.0, abs=MEASURED_TOLERANCE_UM)  # measured after the done
    assert data["stage-voltage_v"] == pytest.approx(data["stage-q_um"] * VOLTS_PER_UM, rel=1e-9)
    assert 0.0 < data["stage-q_sigma_um"] < 1.0
    assert one_axis.last_voltage_v() == pytest.approx(data["stage-voltage_v"], abs=1e-9)  # the device holds it


def test_a_scan_of_five_points_reads_each_point_after_its_move(run_engine: RunEngine, stage: Stage) -> None:
    data = events(run_engine, bp.scan([stage], stage, 0.0, 100.0, 5))
    assert [d["stage-setpoint"] for d in data] == [0.0, 25.0, 50.0, 75.0, 100.0]
    for d in data:
        assert d["stage"] == pytest.approx(d["stage-setpoint"], abs=MEASURED_TOLERANCE_UM), d
        assert d["stage-voltage_v"] == pytest.approx(d["stage-q_um"] * VOLTS_PER_UM, rel=1e-9)
    assert len({d["stage-q_um"] for d in data}) == 5


def test_count_reads_the_held_target_each_time(run_engine: RunEngine, stage: Stage) -> None:
    run_engine(bps.mv(stage, 60.0))
    data = events(run_engine, bp.count([stage], num=3))
    assert len(data) == 3
    assert all(d["stage-setpoint"] == 60.0 for d in data)
    assert all(d["stage"] == pytest.approx(60.0, abs=MEASURED_TOLERANCE_UM) for d in data)


def test_a_refused_move_fails_the_plan_with_the_refusal(run_engine: RunEngine, stage: Stage,
                                                         one_axis: RunningCell) -> None:
    run_engine(bps.mv(stage, 20.0))
    held_v = one_axis.last_voltage_v()
    with pytest.raises(FailedStatus) as failed:
        run_engine(bps.mv(stage, 600.0))
    refusal = failed.value.args[0].exception()
    assert isinstance(refusal, Refused) and refusal.kind == "out_of_workspace", refusal
    assert "600" in refusal.error
    [data] = events(run_engine, bp.count([stage], num=1))
    assert data["stage-setpoint"] == 20.0  # nothing was commanded
    assert one_axis.last_voltage_v() == held_v


def test_stop_mid_ramp_ends_the_move_stopped_and_the_output_holds_short(run_engine: RunEngine, stage: Stage,
                                                                        one_axis: RunningCell) -> None:
    run_engine(bps.mv(stage, 0.0))
    answered, subscriber = one_axis.watch_command(lambda doc: doc.get("x_um") == 480.0)
    ended: list[BaseException] = []

    def plan() -> Any:
        yield from bps.abs_set(stage, 480.0, group="ramp")
        yield from bps.wait_for([lambda: asyncio.to_thread(answered.wait, 10.0)])  # the 1.9 s ramp has begun
        try:  # the RunEngine throws the failed status in at the stop, or at the wait if it fails later
            yield from bps.stop(stage)
            yield from bps.wait(group="ramp")
        except FailedStatus as error:
            ended.append(error.args[0].exception())

    try:
        run_engine(plan())
    finally:
        subscriber.undeclare()
    assert answered.is_set()
    assert len(ended) == 1 and isinstance(ended[0], MoveEnded) and ended[0].state == "stopped", ended
    target_v = ended[0].command.voltage_v
    assert isinstance(target_v, float)
    assert one_axis.last_voltage_v() < 0.9 * target_v  # stopped on the ramp, well short of 480 µm
    run_engine(bps.mv(stage, 10.0))  # the next move moves again
    assert one_axis.last_voltage_v() < 0.05 * target_v


def test_a_plans_end_does_not_stop_another_clients_move(run_engine: RunEngine, stage: Stage,
                                                         one_axis: RunningCell) -> None:
    run_engine(bps.mv(stage, 0.0))  # the RunEngine calls stage.stop() at this plan's end: nothing in flight
    answered, subscriber = one_axis.watch_command(lambda doc: doc.get("x_um") == 480.0)
    ended: list[Any] = []
    with Client(one_axis.endpoint, cell=one_axis.cell) as other:
        moving = threading.Thread(target=lambda: ended.append(_outcome(other, 480.0)))
        moving.start()
        try:
            assert answered.wait(10), "the other client's 480 µm target was never answered"
            run_engine(bp.count([stage], num=1))  # a plan that moved nothing ...
            run_engine(bps.null())
            call_in_bluesky_event_loop(stage.stop())  # ... and the stop a plan's end would send: no move of its own
        finally:
            moving.join(15)
            subscriber.undeclare()
    assert ended == ["reached"]  # the other client's 1.9 s ramp ran to its end


def test_stop_is_not_queued_behind_moves_that_wait_for_their_done(run_engine: RunEngine) -> None:
    """More moves in flight than asyncio's default executor has threads (``min(32, cpus + 4)``), on a cell that
    answers them and never says ``done``: the ``stop`` still reaches the cell, and its ``done``s end them all."""
    cell = ScriptedCell("bsscript")
    cell.answering.set()
    moves = min(32, (os.cpu_count() or 1) + 4) + 2
    try:
        with init_devices():
            stage = Stage(cell.endpoint, cell.cell, name="scripted")
        loop = run_engine.loop

        async def start() -> list[Any]:
            return [stage.set(100.0 + i, timeout=60.0) for i in range(moves)]

        statuses = asyncio.run_coroutine_threadsafe(start(), loop).result(10)
        for _ in range(moves):
            assert cell.asked.acquire(timeout=20), "the cell received every move"  # each answered, none done
        asyncio.run_coroutine_threadsafe(stage.stop(), loop).result(20)
        assert cell.stops == ["{}"]
        for status in statuses:
            asyncio.run_coroutine_threadsafe(asyncio.wait_for(_settled(status), 20), loop).result(30)
            ended = status.exception()
            assert isinstance(ended, MoveEnded) and ended.state == "stopped", ended
        stage.close()
    finally:
        cell.close()


async def _settled(status: Any) -> None:
    """Wait for an ophyd-async status to end, whichever way."""
    try:
        await status
    except Exception:
        pass


def _outcome(client: Client, x_um: float) -> str:
    try:
        command = client.move(x_um, timeout_s=15.0)
    except MoveEnded as error:
        return error.state
    assert command.done is not None
    return str(command.done["state"])


# --- XY: a motor per axis ---------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def xy_cell(tmp_path_factory: pytest.TempPathFactory) -> Iterator[RunningCell]:
    cell = RunningCell(tmp_path_factory.mktemp("xy"), "bsxy", axes="xy")
    yield cell
    assert cell.close() == 0


@pytest.fixture(scope="module")
def xy(run_engine: RunEngine, xy_cell: RunningCell) -> Iterator[Stage]:
    with init_devices():
        xy = Stage(xy_cell.endpoint, xy_cell.cell, name="xy")
    yield xy
    xy.close()


def test_xy_mv_takes_a_mapping_and_a_scan_moves_one_axis_holding_the_other(run_engine: RunEngine, xy: Stage,
                                                                            xy_cell: RunningCell) -> None:
    run_engine(bps.mv(xy, {"x": 100.0, "y": 200.0}))
    data = events(run_engine, bp.scan([xy], xy.x, 0.0, 100.0, 5))  # type: ignore[attr-defined]
    assert [d["xy-x-setpoint"] for d in data] == [0.0, 25.0, 50.0, 75.0, 100.0]
    for d in data:
        assert d["xy-x"] == pytest.approx(d["xy-x-setpoint"], abs=MEASURED_TOLERANCE_UM), d
        assert d["xy-y-setpoint"] == 200.0
        assert d["xy-y"] == pytest.approx(200.0, abs=MEASURED_TOLERANCE_UM), d
    assert xy_cell.last_voltage_v("x") == pytest.approx(data[-1]["xy-x-voltage_v"], abs=1e-9)


def test_xy_refuses_a_plain_number_and_a_refused_axis_moves_neither(run_engine: RunEngine, xy: Stage,
                                                                     xy_cell: RunningCell) -> None:
    run_engine(bps.mv(xy, {"x": 50.0, "y": 50.0}))
    with pytest.raises(FailedStatus) as failed:
        run_engine(bps.mv(xy, 10.0))
    wrong = failed.value.args[0].exception()
    assert isinstance(wrong, ValueError) and "axes x, y" in str(wrong) and "mapping" in str(wrong)
    with pytest.raises(FailedStatus) as failed:
        run_engine(bps.mv(xy, {"x": 10.0, "z": 10.0}))
    wrong = failed.value.args[0].exception()
    assert isinstance(wrong, ValueError) and "no axis z" in str(wrong) and "its axes: x, y" in str(wrong)
    held = (xy_cell.last_voltage_v("x"), xy_cell.last_voltage_v("y"))
    with pytest.raises(FailedStatus) as failed:
        run_engine(bps.mv(xy.y, 700.0))  # type: ignore[attr-defined]
    refusal = failed.value.args[0].exception()
    assert isinstance(refusal, Refused) and refusal.kind == "out_of_workspace", refusal
    assert (xy_cell.last_voltage_v("x"), xy_cell.last_voltage_v("y")) == held
