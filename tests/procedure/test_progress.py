"""Progress shows the wall-clock time left: the plan's timing at the start, scaled by the measured pace
once steps are done (issue 13, item 6; issue 11)."""

import io

from helpers.sim_helpers import Capture

from nanodrift.calibration.plans import StepTiming, calibration_plan
from nanodrift.config import ActuatorConfig
from nanodrift.procedure.progress import Progress
from nanodrift.procedure.steps import planned_seconds


class FakeWall:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def run(progress: Progress, plan, wall: FakeWall, seconds_per_step: float, start: int = 0) -> None:
    for _ in plan[start:]:
        wall.now += seconds_per_step
        progress.advance(True)


def test_time_left_is_the_measured_wall_rate():
    plan = calibration_plan(3)  # 51 steps of 29 s of cell time: "0:16:26 left" after the first cycle
    wall, stream = FakeWall(), Capture()
    progress = Progress(plan, "calibration", stream, wall=wall)
    run(progress, plan, wall, 0.05)  # a virtual clock: 50 ms of wall time per step
    lines = stream.getvalue().splitlines()
    assert lines[0] == "calibration: 17/51 steps, 0:00:02 left, 0 invalid"  # 34 steps x 0.05 s = 1.7 s
    assert lines[-1].startswith("calibration: 51/51 steps, 0:00:00 left")

    wall, stream = FakeWall(), Capture()
    progress = Progress(plan, "calibration", stream, wall=wall)
    run(progress, plan, wall, 29.0)  # real hardware: the plan's 29 s per step
    assert stream.getvalue().splitlines()[0] == "calibration: 17/51 steps, 0:16:26 left, 0 invalid"


def test_a_resumed_run_measures_only_its_own_steps():
    plan = calibration_plan(3)
    wall, stream = FakeWall(), Capture()
    progress = Progress(plan, "calibration", stream, done=17, wall=wall)  # the first cycle is in the file
    run(progress, plan, wall, 2.0, start=17)
    assert stream.getvalue().splitlines()[0] == "calibration: 34/51 steps, 0:00:34 left, 0 invalid"


def test_nothing_measured_yet_is_unknown_not_a_guess():
    progress = Progress(calibration_plan(1), "calibration", Capture(), wall=FakeWall())
    assert progress._hms(progress.seconds_left()) == "?:??:??"


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_the_first_line_comes_at_the_start_with_the_plans_time_then_the_measured_pace_scales_it():
    plan = calibration_plan(3)  # 51 steps
    timing = StepTiming(ramp_s=1.0, hold_s=9.0)  # [procedure] rise_s = 1, hold_s = 9: 10 s a step
    wall, stream = FakeWall(), Capture()
    progress = Progress(plan, "calibration", stream, wall=wall)
    progress.begin(planned_seconds(plan, {"x": 0.0}, timing, {"x": ActuatorConfig()}))
    assert stream.getvalue().splitlines() == ["calibration: 0/51 steps, 0:08:30 left (planned), 0 invalid"]
    wall.now += 3.0  # the first step took 3 s of wall time for its 10 planned: a pace of 0.3
    progress.advance(True)
    assert progress.seconds_left() == 50 * 10.0 * 0.3
    run(progress, plan, wall, 3.0, start=1)
    lines = stream.getvalue().splitlines()
    assert len(lines) == 4 and lines[1] == "calibration: 17/51 steps, 0:01:42 left, 0 invalid"  # 34 x 3 s


def test_the_plan_stretches_a_rise_the_slew_limit_slows_and_knows_nothing_of_an_unknown_start():
    plan = calibration_plan(1, points=(0.0, 480.0, 0.0 + 30.0))
    limits = ActuatorConfig(max_slew_um_per_s=100.0)
    timing = StepTiming(ramp_s=4.0, hold_s=25.0)
    # from 0: no move (4 s rise), 480 um at 100 um/s (4.8 s), 450 um back (4.5 s)
    assert planned_seconds(plan, {"x": 0.0}, timing, {"x": limits}) == [29.0, 29.8, 29.5]
    # unknown start: written at once, then the rise
    assert planned_seconds(plan, {"x": None}, timing, {"x": limits})[0] == 29.0


def test_a_resumed_run_starts_from_the_plan_of_what_is_left():
    plan = calibration_plan(3)
    wall, stream = FakeWall(), Capture()
    progress = Progress(plan, "calibration", stream, done=17, wall=wall)
    progress.begin(planned_seconds(plan[17:], {"x": 480.0}, StepTiming(), {"x": ActuatorConfig()}))
    assert stream.getvalue().splitlines() == ["calibration: 17/51 steps, 0:16:26 left (planned), 0 invalid"]


def test_on_a_terminal_the_bar_shows_at_once_and_a_note_goes_below_it():
    plan = calibration_plan(1)
    stream = Terminal()
    progress = Progress(plan, "calibration", stream, wall=FakeWall())
    progress.begin([29.0] * len(plan))
    assert stream.getvalue() == "\rcalibration [------------------------------] 0/17 steps, 0:08:13 left (planned) "
    progress.note("the first move is written at once")
    progress.finish()
    assert stream.getvalue().endswith(" \ncalibration: the first move is written at once\n")
