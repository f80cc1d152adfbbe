"""The simulated XY/XYZ cell, the multi-axis plans and the ISO 9283 figures in 2-D/3-D."""

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.iso9283 import pose_accuracy, pose_repeatability, summarize_runs
from nanodrift.calibration.plans import (
    CALIBRATION_POINTS_UM,
    PAPER_TIMING,
    cell_calibration_plan,
    cell_validation_plan,
    cell_validation_points,
)
from nanodrift.drivers.simulated.datasets import simulate_dataset
from nanodrift.drivers.simulated.physics import CellPhysics, CrossParams, cross_params
from nanodrift.drivers.simulated.runs import (
    ONE_MOVE,
    cell_command,
    independent_command,
    run_cell_validation,
    simulate_steps,
)
from nanodrift.model.identify import fit, fit_cell


def _x_moved_by_y(cross: CrossParams) -> float:
    """x's true position change when y steps 0 -> 400 µm with x held at 100 µm, in a steady room."""
    physics = CellPhysics.create("steady", seed=4, axes="xy", cross=cross)
    out = simulate_steps(physics, {"x": [100.0] * 6, "y": [0.0, 400.0] * 3}, [0] * 6, schedule=ONE_MOVE)
    x = out["x_true_um"]
    stroke = physics.axis_params["y"].geometry(400.0) - physics.axis_params["y"].geometry(0.0)
    return float(np.mean(x[1::2]) - np.mean(x[0::2])) / stroke


def test_moving_y_moves_x_by_the_set_crosstalk_and_tilt():
    only_crosstalk = _x_moved_by_y(CrossParams(crosstalk_fraction=0.0025, non_orthogonality_rad=0, bending_um=0))
    assert only_crosstalk == pytest.approx(-0.0025, abs=3e-5)  # 3e-5 of 400 µm: 12 nm of landing noise and drift
    only_tilt = _x_moved_by_y(CrossParams(crosstalk_fraction=0, non_orthogonality_rad=0.0018, bending_um=0))
    assert only_tilt == pytest.approx(-0.0018, abs=3e-5)
    assert _x_moved_by_y(cross_params("crosstalk:fraction=0,non_orthogonality:rad=0,coupled_bending:um=0")) \
        == pytest.approx(0.0, abs=3e-5)


def test_bending_needs_both_axes_out():
    physics = CellPhysics.create("steady", axes="xy", cross=CrossParams(crosstalk_fraction=0, non_orthogonality_rad=0,
                                                                        bending_um=0.3))
    corners = physics.static({"x": np.array([0.0, 480.0, 0.0, 480.0]), "y": np.array([0.0, 0.0, 480.0, 480.0])})
    own = physics.axis_params["x"].geometry(np.array([0.0, 480.0, 0.0, 480.0]))
    np.testing.assert_allclose(corners["x"] - own, [0.0, 0.0, 0.0, -0.3], atol=1e-12)


def test_each_beam_wanders_on_its_own():
    physics = CellPhysics.create("steady", seed=2, axes="xyz")
    t = np.arange(0.0, 200 * 3600.0, 60.0)
    wander = {a: physics.wander(a, t) for a in "xyz"}
    for a in "xyz":
        assert 0.012 < np.std(wander[a]) < 0.040  # ~25 nm each
    assert abs(np.corrcoef(wander["x"], wander["y"])[0, 1]) < 0.3
    assert abs(np.corrcoef(wander["y"], wander["z"])[0, 1]) < 0.3


def test_drift_differs_in_sign_between_axes():
    physics = CellPhysics.create("test5", seed=1, axes="xy")  # a room well above the 22.0 °C reference
    drift = physics.drift(np.array([3600.0]))
    assert drift["x"][0] < -0.5 and drift["y"][0] > 0.3


@pytest.mark.parametrize("axes", ["xy", "xyz"])
def test_calibration_plan_covers_the_workspace_within_the_paper_time(axes):
    plan = cell_calibration_plan(tuple(axes))
    assert len(plan) * PAPER_TIMING.step_s <= 4 * 3600  # the paper's ~4 h, with its 4 s + 25 s step
    for c in range(24):
        cycle = [s for s in plan if s.cycle == c]
        for a in axes:  # a Latin hypercube per cycle on the paper's 17 levels
            assert sorted(s.target(a) for s in cycle) == list(CALIBRATION_POINTS_UM)
    pairs = {(s.target("x"), s.target("y")) for s in plan if s.cycle < 17}
    assert len(pairs) == 17 * 17  # the first 17 cycles: every grid pair once
    u = {a: (np.array([s.target(a) for s in plan]) - 240.0) / 240.0 for a in axes}
    columns = [u[a] for a in axes] + [u[a] ** 2 for a in axes]
    columns += [u[a] * u[b] for i, a in enumerate(axes) for b in axes[i + 1:]]
    corr = np.corrcoef(columns)
    np.fill_diagonal(corr, 0.0)
    assert np.abs(corr).max() < 0.05  # every cross term identifiable on its own


@pytest.mark.parametrize("axes", ["xy", "xyz"])
def test_validation_points_are_off_the_grid_and_approached_from_one_side(axes):
    points = cell_validation_points(tuple(axes))
    assert len(points) == 5
    for point in points:
        assert all(value not in CALIBRATION_POINTS_UM for _, value in point)
    plan = cell_validation_plan(tuple(axes), cycles=4)
    assert len(plan) == 20
    first, second = [s.targets_um for s in plan if s.cycle == 0], [s.targets_um for s in plan if s.cycle == 1]
    assert second == first  # ISO 9283: P1 -> P5 every cycle, each point always approached from the same pose


def test_pose_accuracy_and_repeatability_by_hand():
    attained = np.array([[1.0, 0.0], [3.0, 0.0], [2.0, 3.0]])  # barycentre (2, 1)
    assert pose_accuracy(attained, (0.0, 0.0)) == pytest.approx(math.sqrt(5.0))
    distances = np.array([math.sqrt(2.0), math.sqrt(2.0), 2.0])  # to the barycentre
    mean = (2 * math.sqrt(2.0) + 2.0) / 3.0
    spread = math.sqrt(((distances - mean) ** 2).sum() / 2.0)
    assert pose_repeatability(attained) == pytest.approx(mean + 3.0 * spread)
    assert pose_repeatability(attained) == pytest.approx(2.624087, abs=1e-6)
    result = summarize_runs("t", {"x": np.array([0.0, 0.0, 0.0, 5.0]), "y": np.array([0.0, 0.0, 0.0, 5.0])},
                            {"x": np.array([1.0, 3.0, 2.0, 5.0]), "y": np.array([0.0, 0.0, 3.0, 4.0])}, None)
    points = result.points_without
    assert [p.visits for p in points] == [3, 1] and not result.compensated and not result.points
    assert points[0].accuracy_nm == pytest.approx(math.sqrt(5.0) * 1e3)
    assert points[0].axis_accuracy_nm == pytest.approx({"x": 2000.0, "y": 1000.0})
    assert points[1].accuracy_nm == pytest.approx(1000.0) and points[1].repeatability_nm == 0.0
    assert result.accuracy_without_nm == pytest.approx((math.sqrt(5.0) * 1e3 + 1000.0) / 2)
    assert math.isnan(result.accuracy_nm)  # no run through the model


def test_cross_terms_beat_independent_one_axis_models_by_a_wide_factor():
    data = simulate_dataset("train", axes="xy", seed=11)
    cell = fit_cell(data).model
    assert {"y", "x*y"} <= set(cell.models["x"].term_names()) and "x" in cell.models["y"].term_names()
    alone = {a: fit(Dataset(t=data.t, x=data.positions[a], q=data.commands[a], channels=data.channels,
                            extra={"cycle": data.extra["cycle"]})).model for a in "xy"}
    room = CellPhysics.create("test2", seed=1102, axes="xy")
    runs = [run_cell_validation(room, command, cycles=10)
            for command in (cell_command(cell), independent_command(alone))]
    cell, alone = (summarize_runs("t", run.targets_um, run.attained(False), run.attained(True)) for run in runs)
    without, cell_nm, alone_nm = cell.accuracy_without_nm, cell.accuracy_nm, alone.accuracy_nm
    assert without > 800.0
    assert alone_nm > 5.0 * cell_nm  # the benchmark's 8 seeds: 10-50x
    assert without > 10.0 * cell_nm


@given(st.lists(st.tuples(st.floats(-1e3, 1e3), st.floats(-1e3, 1e3)), min_size=2, max_size=30),
       st.floats(-1e3, 1e3), st.floats(-1e3, 1e3), st.floats(0.0, 2 * math.pi))
def test_pose_figures_do_not_depend_on_where_or_how_the_plane_is_drawn(points, dx, dy, angle):
    """AP and RP are distances: moving and turning the attained points and the target together changes neither."""
    attained = np.array(points)
    target = np.array([3.0, -7.0])
    turn = np.array([[math.cos(angle), -math.sin(angle)], [math.sin(angle), math.cos(angle)]])
    moved, moved_target = attained @ turn.T + [dx, dy], turn @ target + [dx, dy]
    assert pose_accuracy(moved, moved_target) == pytest.approx(pose_accuracy(attained, target), abs=1e-6)
    assert pose_repeatability(moved) == pytest.approx(pose_repeatability(attained), abs=1e-6)
    assert pose_repeatability(attained) >= 0.0
