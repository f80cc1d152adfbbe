"""A recorded run of the simulated cell as a :class:`Dataset`, in process: what ``nanodrift simulate`` writes.

One code path for the command, the tests and scripts: the scenario's trajectory picks the plan
(calibration: forward sweeps 0..480 µm by 30, the paper's Fig. 7; ``bidirectional``: alternating
up/down sweeps, so direction-dependent effects show; validation: the ISO 9283 points, both ways),
:func:`nanodrift.drivers.simulated.runs.simulate_steps` produces the step averages.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.plans import PlannedStep, bidirectional_plan, calibration_plan, validation_plan
from nanodrift.drivers.simulated.physics import THERMOCOUPLES, CellParams, CellPhysics
from nanodrift.drivers.simulated.runs import simulate_steps

#: cycles of a run when none are asked for: the paper's calibration (24 sweeps, ~3.3 h) and validation (30)
DEFAULT_CYCLES = {"calibration": 24, "bidirectional": 24, "validation": 30}

EffectsSpec = str | Sequence[str] | Mapping[str, Any] | None


def run_plan(physics: CellPhysics, cycles: int | None = None, *, bidirectional: bool = False) -> list[PlannedStep]:
    """The steps a run of ``physics.scenario`` visits (``bidirectional`` turns calibration sweeps up-and-down)."""
    trajectory = physics.scenario.trajectory
    if bidirectional and trajectory == "calibration":
        trajectory = "bidirectional"
    n = DEFAULT_CYCLES[trajectory] if cycles is None else cycles
    if n < 1:
        raise ValueError(f"cycles must be at least 1, got {n}")
    if trajectory == "validation":  # already visits every point from both sides
        return validation_plan(n)
    return (bidirectional_plan if trajectory == "bidirectional" else calibration_plan)(n)


def simulate_dataset(scenario: str = "train", effects: EffectsSpec = None, *, cycles: int | None = None,
                     seed: int = 0, bidirectional: bool = False, source: str | None = None,
                     **param_overrides: float) -> Dataset:
    """A run of the simulated cell with ``effects`` hidden, exactly as ``nanodrift simulate`` writes it.

    ``effects``: the ``--effects`` text (``"thermal_lag,creep:c=0.02"``), a list of names, or a mapping
    name -> parameters; unknown names raise :class:`nanodrift.drivers.simulated.effects.UnknownNameError`.
    ``cycles``: None for the scenario's default (24 calibration sweeps, 30 validation sweeps).
    ``bidirectional``: alternate up and down sweeps on a calibration scenario (the ``bidirectional``
    scenario always does). ``param_overrides``: the cell's magnitudes (``CellParams`` fields).
    """
    physics = CellPhysics.create(scenario, effects or None, seed, CellParams().with_overrides(param_overrides))
    plan = run_plan(physics, cycles, bidirectional=bidirectional)
    out = simulate_steps(physics, [s.target_um for s in plan], [s.cycle for s in plan])
    label = ",".join(physics.effects) or "none"
    return Dataset(t=out["t_s"], x=out["x_um"], q=out["q_um"], channels={c: out[c] for c in THERMOCOUPLES},
                   extra={"cycle": out["cycle"]}, source=source or f"simulated:{scenario}:{label}:seed {seed}")
