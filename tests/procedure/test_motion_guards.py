"""What protects a procedure's motion, on the simulated cell's virtual clock: the follow check, slew-limited
ramps, the safe voltage at the end, and the ``[procedure]`` table driving ``nanodrift calibrate``."""

from __future__ import annotations

import asyncio
import itertools
import math
from pathlib import Path
from typing import Literal

import numpy as np
import pytest
from helpers.sim_helpers import Capture

from nanodrift.assembly import simulated_drivers
from nanodrift.calibration.dataset import read_csv
from nanodrift.calibration.plans import PlannedStep, StepTiming, calibration_plan
from nanodrift.cli import main
from nanodrift.config import ActuatorConfig
from nanodrift.drivers.base import Actuator, Clock
from nanodrift.drivers_set import DriverSet
from nanodrift.procedure.follow import FollowCheck, StageNotFollowingError
from nanodrift.procedure.recording import record_calibration
from nanodrift.procedure.steps import run_steps


class Wired(Actuator):
    """Between the procedure and the simulated stage: records (time, q, V); ``gain`` is what the stage gets;
    ``holds`` is what reading the output back answers (None: it cannot be read)."""

    def __init__(self, inner: Actuator, clock: Clock, gain: float = 1.0) -> None:
        self.inner, self.clock, self.gain = inner, clock, gain
        self.sent: list[tuple[float, float, float]] = []
        self.holds: tuple[Literal["voltage_v", "q_um"], float] | None = None

    async def open(self) -> None:
        await self.inner.open()

    async def read_back(self) -> tuple[Literal["voltage_v", "q_um"], float] | None:
        return self.holds

    async def command(self, q_um: float, voltage_v: float, *, x_um: float | None = None) -> None:
        self.sent.append((self.clock.now(), q_um, voltage_v))
        await self.inner.command(q_um * self.gain, voltage_v * self.gain)

    async def close(self) -> None:
        await self.inner.close()


def wired(gain: float = 1.0, seed: int = 1) -> tuple[DriverSet, Wired]:
    drivers = simulated_drivers("train", seed=seed)
    actuator = Wired(drivers.actuators["x"], drivers.clock, gain)
    drivers.actuators = {"x": actuator}
    return drivers, actuator


def test_a_stage_that_does_not_move_stops_the_run_after_its_first_move(tmp_path: Path) -> None:
    drivers, _ = wired(gain=0.0)
    data = tmp_path / "cal.csv"
    with pytest.raises(StageNotFollowingError) as caught:
        asyncio.run(record_calibration(drivers, data, cycles=2, progress_stream=Capture(),
                                       follow={"x": FollowCheck("interferometer")}))
    message = str(caught.value)
    assert message.startswith("the stage did not follow: commanded +30 µm, the interferometer moved ")
    assert message.endswith(" µm; check the amplifier and [actuator]")
    moved = float(message.split("moved ")[1].split(" µm")[0])
    assert abs(moved) < 0.2  # what the room's drift and the noise do to a stage standing still
    assert len(read_csv(data)) == 2  # steps 0 and 1 are recorded (the evidence); nothing after


@pytest.mark.parametrize(("gain", "tolerance", "follows"), [(0.3, 0.5, False), (0.9, 0.5, True), (-1.0, 0.5, False),
                                                             (0.9, 0.05, False), (1.0, 0.05, True)])
def test_the_tolerance_is_a_fraction_of_the_commanded_move(gain: float, tolerance: float, follows: bool,
                                                           tmp_path: Path) -> None:
    drivers, _ = wired(gain=gain)
    follow = FollowCheck("interferometer", tolerance=tolerance, steps=3)
    plan = [PlannedStep.on_x(i, 0, x) for i, x in enumerate((0.0, 30.0, 60.0, 90.0, 120.0))]
    run = run_steps(drivers, plan, follow={"x": follow}, timing=StepTiming(hold_s=6.0, window_s=2.0))
    if follows:
        results = asyncio.run(run)
        assert len(results) == 5 and follow.checked == 3 and follow.done
    else:
        with pytest.raises(StageNotFollowingError, match=r"commanded \+30 µm"):
            asyncio.run(run)


def test_a_jump_is_ramped_no_faster_than_max_slew_and_ends_at_the_target() -> None:
    drivers, actuator = wired()
    limits = ActuatorConfig(max_slew_um_per_s=100.0)
    plan = [PlannedStep.on_x(0, 0, 0.0), PlannedStep.on_x(1, 0, 480.0), PlannedStep.on_x(2, 0, 0.0)]
    results = asyncio.run(run_steps(drivers, plan, limits={"x": limits}))  # the paper's 4 s ramp would be 120 um/s
    sent = actuator.sent
    rates = [abs(q1 - q0) / (t1 - t0) for (t0, q0, _), (t1, q1, _) in itertools.pairwise(sent) if t1 > t0]
    assert max(rates) <= 100.0 * (1 + 1e-9)
    assert max(q for _, q, _ in sent) == 480.0
    times_at_top = [t for t, q, _ in sent if q == 480.0]
    first_move = next(t for t, q, _ in sent if q > 0)
    assert times_at_top[0] - first_move == pytest.approx(4.8 - 4.8 / 19, abs=1e-6)  # 480 um at 100 um/s, 19 steps
    assert sent[-1][1] == 0.0 and results[1].q_um["x"] == 480.0
    assert all(limits.v_min <= v <= limits.v_max for _, _, v in sent)
    assert results[1].positions_um["x"] == pytest.approx(480.0, abs=1.0)  # the stage got there


def test_the_first_ramp_starts_where_the_output_reads_back_also_when_a_run_resumes(tmp_path: Path) -> None:
    limits = ActuatorConfig(max_slew_um_per_s=100.0)
    data = tmp_path / "cal.csv"
    plan = calibration_plan(2)  # two sweeps 0 .. 480 um
    first, _ = wired()
    asyncio.run(record_calibration(first, data, limits={"x": limits}, plan=plan[:17], progress_stream=Capture()))
    last_t = float(read_csv(data).t[-1])
    # the run was stopped after its first sweep; the output still holds 480 um (9.6 V) when it resumes
    drivers = simulated_drivers("train", seed=1, start_s=last_t + 1.0)
    actuator = Wired(drivers.actuators["x"], drivers.clock)
    drivers.actuators = {"x": actuator}
    actuator.holds = ("voltage_v", 9.6)
    stream = Capture()
    assert asyncio.run(record_calibration(drivers, data, limits={"x": limits}, plan=plan, resume=True,
                                          progress_stream=stream)) == 17
    descent = [q for _, q, _ in actuator.sent][:19]  # 480 -> 0 um at 100 um/s: 4.8 s, 19 steps
    assert descent[0] == pytest.approx(480.0 - 480.0 / 19) and descent[-1] == 0.0  # not a jump from 480 to 0
    rates = [abs(q1 - q0) / (t1 - t0) for (t0, q0, _), (t1, q1, _) in itertools.pairwise(actuator.sent) if t1 > t0]
    assert max(rates) <= 100.0 * (1 + 1e-9)
    assert "where the stage is before the first move is unknown" not in stream.getvalue()
    # the plan's time left: 17 steps of a 4 s rise and a 25 s hold, the first rise stretched to 4.8 s
    assert stream.getvalue().splitlines()[0] == "calibration: 17/34 steps, 0:08:14 left (planned), 0 invalid"


def test_the_paper_ramp_is_kept_when_it_is_slower_than_the_limit() -> None:
    drivers, actuator = wired()
    plan = [PlannedStep.on_x(0, 0, 0.0), PlannedStep.on_x(1, 0, 30.0)]
    asyncio.run(run_steps(drivers, plan, limits={"x": ActuatorConfig(max_slew_um_per_s=100.0)}))
    moving = [(t, q) for t, q, _ in actuator.sent if 0 < q]
    # the first move (to 0 um, from where the simulated stage is: unknown, it cannot be read back) is one write
    assert len(actuator.sent) == 1 + 16 and moving[-1][0] - moving[0][0] == pytest.approx(4.0 - 0.25)  # 16 x 0.25 s


def test_a_finite_safe_voltage_is_where_the_stage_is_left_even_after_a_failure(tmp_path: Path) -> None:
    limits = ActuatorConfig(safe_voltage_v=1.0, max_slew_um_per_s=50.0)
    drivers, actuator = wired()
    plan = [PlannedStep.on_x(0, 0, 0.0), PlannedStep.on_x(1, 0, 480.0)]
    asyncio.run(run_steps(drivers, plan, limits={"x": limits}))
    assert actuator.sent[-1][1:] == pytest.approx((50.0, 1.0))  # 1.0 V / 0.02 V/um
    descent = [(t, q) for t, q, _ in actuator.sent if t > actuator.sent[-1][0] - 8.6]
    assert descent[0][1] < 480.0 and abs(descent[-1][0] - descent[0][0]) > 8.0  # ramped: 430 um at 50 um/s
    assert math.isnan(ActuatorConfig().safe_voltage_v) and ActuatorConfig().safe_q_um is None

    stuck, stuck_actuator = wired(gain=0.0)
    with pytest.raises(StageNotFollowingError):
        asyncio.run(run_steps(stuck, [PlannedStep.on_x(i, 0, x) for i, x in enumerate((0.0, 30.0, 60.0))],
                              limits={"x": limits}, follow={"x": FollowCheck("interferometer")}))
    assert stuck_actuator.sent[-1][1] == pytest.approx(50.0)


def test_calibrate_takes_its_trajectory_and_timing_from_the_procedure_table(tmp_path: Path) -> None:
    config = tmp_path / "sim.toml"
    config.write_text('[simulation]\nscenario = "train"\nseed = 2\n'
                      "[procedure]\nstep_um = 60\nmax_um = 480\ncycles = 2\nrise_s = 2\nhold_s = 10\naverage_s = 2\n")
    data = tmp_path / "cal.csv"
    assert main(["calibrate", "--config", str(config), "--out", str(tmp_path / "m.json"), "--data", str(data)]) == 0
    ds = read_csv(data)
    assert np.allclose(ds.q, np.tile(np.arange(0.0, 481.0, 60.0), 2))
    assert np.allclose(np.diff(ds.t), 12.0)  # rise_s + hold_s
    short = tmp_path / "short.csv"
    assert main(["calibrate", "--config", str(config), "--out", str(tmp_path / "m2.json"), "--data", str(short),
                 "--cycles", "3"]) == 0
    assert len(read_csv(short)) == 27  # --cycles overrides [procedure] cycles


def test_the_trajectory_is_the_procedure_tables_and_the_scenario_only_the_simulated_room(tmp_path: Path) -> None:
    """``[procedure] trajectory`` chooses the sweeps on every cell; ``--scenario bidirectional`` names the
    simulated room's history, never the stage's trajectory (it used to, on hardware too)."""
    table = "[procedure]\nstep_um = 120\nmax_um = 480\ncycles = 2\nrise_s = 1\nhold_s = 4\naverage_s = 1\n"
    up_down = tmp_path / "bidirectional.toml"
    up_down.write_text('[simulation]\nscenario = "train"\n' + table + 'trajectory = "bidirectional"\n')
    forward = tmp_path / "forward.toml"
    forward.write_text('[simulation]\nscenario = "train"\n' + table)
    runs = {"table": (up_down, []), "scenario": (forward, ["--scenario", "bidirectional"])}
    q = {}
    for name, (config, extra) in runs.items():
        data = tmp_path / f"{name}.csv"
        assert main(["calibrate", "--config", str(config), "--out", str(tmp_path / f"{name}.json"),
                     "--data", str(data), *extra]) == 0
        q[name] = list(read_csv(data).q)
    sweep = [0.0, 120.0, 240.0, 360.0, 480.0]
    assert q["table"] == sweep + sweep[::-1]
    assert q["scenario"] == sweep + sweep


def test_an_output_that_fails_to_close_hides_neither_the_run_nor_its_error() -> None:
    class Sticky(Wired):
        closes = 0

        async def close(self) -> None:
            Sticky.closes += 1
            await self.inner.close()
            raise OSError("the output's link is gone")

    drivers = simulated_drivers("train", seed=3)
    actuator = Sticky(drivers.actuators["x"], drivers.clock, gain=0.0)
    drivers.actuators = {"x": actuator}
    plan = [PlannedStep.on_x(i, 0, x) for i, x in enumerate((0.0, 30.0))]
    with pytest.raises(StageNotFollowingError):  # the run's own error, not the close's
        asyncio.run(run_steps(drivers, plan, follow={"x": FollowCheck("interferometer")},
                              timing=StepTiming(hold_s=6.0, window_s=2.0)))
    assert Sticky.closes == 1
    actuator.gain = 1.0
    assert len(asyncio.run(run_steps(drivers, plan, timing=StepTiming(hold_s=6.0, window_s=2.0)))) == 2
    assert Sticky.closes == 2
