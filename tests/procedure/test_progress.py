"""Progress shows the wall-clock time left, measured, not the cell's planned time (issue 13, item 6)."""

from helpers.sim_helpers import Capture

from daemon.calibration.plans import StepResult, calibration_plan
from daemon.procedure.progress import Progress


class FakeWall:
    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def run(progress: Progress, plan, wall: FakeWall, seconds_per_step: float, start: int = 0) -> None:
    for step in plan[start:]:
        wall.now += seconds_per_step
        progress.advance(StepResult(step, 0.0, step.target_um, step.target_um, {}, True))


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
