"""A recorded run of the simulated cell as a :class:`Dataset`, in process: what ``nanodrift simulate`` writes.

One code path for the command, the tests and scripts: the scenario's trajectory picks the plan
(calibration: forward sweeps 0..480 µm by 30, the paper's Fig. 7, or on a stack the space-filling plan;
``bidirectional``: alternating up/down sweeps, so direction-dependent effects show; validation: the ISO 9283
points, both ways), :func:`nanodrift.drivers.simulated.runs.simulate_steps` produces the step averages.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.plans import (
    bidirectional_plan,
    calibration_plan,
    cell_calibration_plan,
    cell_validation_plan,
    validation_plan,
)
from nanodrift.drivers.simulated.physics import CELL_AXES, THERMOCOUPLES, CellPhysics, cell_variant, cross_params
from nanodrift.drivers.simulated.runs import ONE_MOVE, simulate_steps

#: cycles of a run when none are asked for: the paper's calibration (24 sweeps, ~3.3 h) and validation (30)
DEFAULT_CYCLES = {"calibration": 24, "bidirectional": 24, "validation": 30}

EffectsSpec = str | Sequence[str] | Mapping[str, Any] | None


def run_plan(physics: CellPhysics, cycles: int | None = None, *,
             bidirectional: bool = False) -> tuple[dict[str, list[float]], list[int]]:
    """(targets per axis, cycle per step) of a run of ``physics.scenario`` (``bidirectional`` turns one-axis
    calibration sweeps up-and-down; a stack runs the space-filling calibration or the ISO 9283 points)."""
    trajectory = physics.scenario.trajectory
    if bidirectional and trajectory == "calibration":
        trajectory = "bidirectional"
    n = DEFAULT_CYCLES[trajectory] if cycles is None else cycles
    if n < 1:
        raise ValueError(f"cycles must be at least 1, got {n}")
    if len(physics.axes) > 1:
        stack = (cell_validation_plan if trajectory == "validation" else cell_calibration_plan)(physics.axes, n)
        return {a: [s.target(a) for s in stack] for a in physics.axes}, [s.cycle for s in stack]
    # validation: ISO 9283, forward sweeps, each point approached from one side
    plan = {"validation": validation_plan, "bidirectional": bidirectional_plan}.get(trajectory, calibration_plan)(n)
    return {physics.axes[0]: [s.target_um for s in plan]}, [s.cycle for s in plan]


def simulate_dataset(scenario: str = "train", effects: EffectsSpec = None, *, axes: str = "",
                     cycles: int | None = None, seed: int = 0, bidirectional: bool = False, source: str | None = None,
                     cell: str = "ideal", **param_overrides: float) -> Dataset:
    """A run of the simulated cell with ``effects`` hidden, exactly as ``nanodrift simulate`` writes it.

    ``axes``: "" the paper's one-axis cell (columns ``x_um``, ``q_um``); ``"xy"`` or ``"xyz"`` a stack (per axis
    ``<a>_um``, ``q_<a>_um`` and the true positions ``<a>_true_um``), whose ``effects`` text names its cross-axis
    effects (all on by default). ``effects`` (one axis): the ``--effects`` text (``"thermal_lag,creep:c=0.02"``),
    a list of names, or a mapping name -> parameters; unknown names raise
    :class:`nanodrift.drivers.simulated.effects.UnknownNameError`.
    ``cycles``: None for the scenario's default (24 calibration sweeps, 30 validation sweeps).
    ``bidirectional``: alternate up and down sweeps on a calibration scenario (the ``bidirectional``
    scenario always does). ``cell``: ``ideal`` or ``realistic`` (``physics.CELLS``).
    ``param_overrides``: the cell's magnitudes (``CellParams`` fields), over the cell's own.
    """
    params = cell_variant(cell).params.with_overrides(param_overrides)
    if axes:
        if effects is not None and not isinstance(effects, str):
            raise TypeError("a stack's effects are the --effects text of its cross-axis effects")
        physics = CellPhysics.create(scenario, None, seed, params, axes=CELL_AXES[axes],
                                     cross=cross_params(effects or None))
    else:
        physics = CellPhysics.create(scenario, effects or None, seed, params, cell=cell)
    targets, step_cycles = run_plan(physics, cycles, bidirectional=bidirectional)
    out = simulate_steps(physics, targets, step_cycles, schedule=ONE_MOVE if axes else None)
    channels = {c: out[c] for c in THERMOCOUPLES}
    prefix = "" if cell == "ideal" else f"{cell}:"  # the ideal cell's sources stay as they were
    if axes:
        return Dataset(t=out["t_s"], x=out["x_um"], q=None, channels=channels,
                       extra={"cycle": out["cycle"], **{f"{a}_true_um": out[f"{a}_true_um"] for a in physics.axes}},
                       source=source or f"simulated:{prefix}{axes}:{scenario}:seed {seed}",
                       positions={a: out[f"{a}_um"] for a in physics.axes},
                       commands={a: out[f"q_{a}_um"] for a in physics.axes})
    label = ",".join(physics.effects) or "none"
    return Dataset(t=out["t_s"], x=out["x_um"], q=out["q_x_um"], channels=channels, extra={"cycle": out["cycle"]},
                   source=source or f"simulated:{prefix}{scenario}:{label}:seed {seed}")
