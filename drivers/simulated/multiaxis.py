"""The simulated multi-axis cell: an XY or XYZ stage of stacked piezo stages in one room.

Every axis is the one-axis stage (a closed-loop setpoint with a cubic geometric error of a few
hundred nm) with its own nonlinearity and its own thermal drift (different sign and magnitude: the
stacked stages and their brackets expand into different directions). What only a stack shows:

- **crosstalk**: an axis' actuator pushes the others by a fraction of its stroke (~0.25 %);
- **non-orthogonality**: an upper stage is mounted ~1.8 mrad off square, so its travel has a
  component along the lower axis (the lower axis' position moves by that angle times it);
- **coupled bending**: with both stages extended the stack bends (``x*y``: a few hundred nm at full
  extension of both).

The room (air, structure temperatures, thermocouples T1..T4) is the one-axis cell's
(:class:`nanodrift.drivers.simulated.physics.CellPhysics`: shared by every axis); each axis has its own
interferometer beam with its own white noise and its own ~25 nm slow wander, independent of the
others'. Magnitudes are calibrated so that on the 2-axis cell two independent one-axis models of the
paper's form reach only about 2.7x (~1.9 µm -> ~0.7 µm, the issue's figures) while a model with
cross terms reaches several tens (``benchmarks/multiaxis.py``).

The run (:func:`simulate_cell_steps`) has the paper's step schedule (:mod:`nanodrift.drivers.simulated.runs`):
each step's measurement is the mean of the samples in the last seconds of its hold, when every
axis' command has long landed, so the attained position is a function of the step's commands and the
time. The true position is kept beside the measurement (``<axis>_true_um``) to score against.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from nanodrift.calibration.dataset import Dataset
from nanodrift.calibration.plans import cell_calibration_plan, cell_validation_plan
from nanodrift.drivers.simulated.effects import resolve_cross_effects
from nanodrift.drivers.simulated.physics import THERMOCOUPLES, CellParams, CellPhysics, Exogenous
from nanodrift.drivers.simulated.runs import StepSchedule, _window_offsets
from nanodrift.drivers.simulated.scenarios import get_scenario
from nanodrift.model.cell_model import CellModel
from nanodrift.model.model import Model

#: the multi-axis cells ``simulate --axes`` knows
CELL_AXES: dict[str, tuple[str, ...]] = {"xy": ("x", "y"), "xyz": ("x", "y", "z")}


@dataclass(frozen=True)
class AxisParams:
    """One stacked stage: its geometric error and its thermal drift (µm, °C)."""

    geometry_e_um: tuple[float, float, float]
    k_stage_um_per_c: float
    k_bracket_um_per_c: float
    k_beam_um_per_c: float
    k2_bracket_um_per_c2: float

    @property
    def drift_um_per_c(self) -> float:
        return self.k_stage_um_per_c + self.k_bracket_um_per_c + self.k_beam_um_per_c


#: per axis: x is the one-axis cell's stage (-1.1 µm/°C); y drifts the other way, z less
AXIS_PARAMS: dict[str, AxisParams] = {
    "x": AxisParams((-0.25, 1.20, -0.75), -0.40, -0.50, -0.20, -0.20),
    "y": AxisParams((0.20, -0.90, 0.60), 0.30, 0.25, 0.10, 0.12),
    "z": AxisParams((-0.15, 0.70, -0.45), -0.25, -0.20, -0.10, -0.10),
}


@dataclass(frozen=True)
class CrossParams:
    """The cross-axis magnitudes of the stack (the issue's XY stage model), scaled by three knobs.

    Per pair the sign and share are fixed (``CROSSTALK``, ``TILT``, ``BENDING``); the knobs scale them
    all: 0 switches an effect off (the cross-axis effects of the catalogue, ``nanodrift.drivers.simulated.effects``).
    """

    crosstalk_fraction: float = 0.0025
    non_orthogonality_rad: float = 0.0018
    #: displacement of the bent axis when both axes of a pair are at full stroke
    bending_um: float = 0.30
    full_um: float = 480.0

    def crosstalk(self, to: str, frm: str) -> float:
        """Fraction of axis ``frm``'s stroke that moves axis ``to``."""
        return self.crosstalk_fraction * CROSSTALK.get((to, frm), 0.0)

    def tilt(self, to: str, frm: str) -> float:
        """The angle (rad) by which the upper stage ``frm`` is mounted off square to ``to``."""
        return self.non_orthogonality_rad * TILT.get((to, frm), 0.0)

    def bending(self, to: str, a: str, b: str) -> float:
        """µm that axis ``to`` moves when both ``a`` and ``b`` are at full stroke."""
        first, second = sorted((a, b))
        return self.bending_um * BENDING.get((to, first, second), 0.0)


#: (moved axis, pushing axis) -> share of the crosstalk fraction. The signs: every cross effect pushes an axis
#: the way its own drift goes when the room warms (x and z down, y up), so a warm room (test 5) sees them add
#: and a cool one (tests 1-4) sees x's drift partly cancel its crosstalk; the opposite choice would hide the
#: cross effects out of range, where the model's own drift error is largest
CROSSTALK: dict[tuple[str, str], float] = {("x", "y"): -1.0, ("y", "x"): 1.0, ("x", "z"): -0.8, ("z", "x"): -0.8,
                                           ("y", "z"): 0.8, ("z", "y"): -1.0}
#: (lower axis, upper stage) -> share of the non-orthogonality angle (only an upper stage tilts into a lower axis)
TILT: dict[tuple[str, str], float] = {("x", "y"): -1.0, ("x", "z"): -0.7, ("y", "z"): 0.8}
#: (moved axis, pair) -> share of the bending displacement
BENDING: dict[tuple[str, str, str], float] = {("x", "x", "y"): -1.0, ("y", "x", "y"): 0.8, ("x", "x", "z"): -0.6,
                                             ("z", "x", "z"): -0.6, ("y", "y", "z"): 0.6, ("z", "y", "z"): -0.6}


@dataclass
class MultiAxisPhysics:
    """A stacked XY or XYZ stage in the one-axis cell's room. Pure and vectorised."""

    axes: tuple[str, ...]
    room: CellPhysics
    cross: CrossParams = field(default_factory=CrossParams)
    axis_params: Mapping[str, AxisParams] = field(default_factory=lambda: dict(AXIS_PARAMS))

    def __post_init__(self) -> None:
        unknown = [a for a in self.axes if a not in self.axis_params]
        if len(self.axes) < 2 or unknown or len(set(self.axes)) != len(self.axes):
            raise ValueError(f"a multi-axis cell has 2 or 3 distinct axes of {', '.join(self.axis_params)}, "
                             f"got {self.axes}")
        # one slow wander per beam: the x beam is the room's own, the others independent draws
        self.beams: dict[str, Exogenous] = {}
        for k, axis in enumerate(self.axes[1:], start=1):
            beam_node = {"beam": self.room.params.tau_beam_s}  # only its wander is read
            self.beams[axis] = Exogenous(self.room.scenario, self.room.params, beam_node,
                                         (self.room.seed + 1) * 1_000_003 + k)

    @classmethod
    def create(cls, axes: str | Sequence[str] = "xy", scenario: str = "train", seed: int = 0,
               cross: CrossParams | None = None, params: CellParams | None = None) -> MultiAxisPhysics:
        """By names: ``MultiAxisPhysics.create("xy", "test2", seed=3)``."""
        names = CELL_AXES[axes] if isinstance(axes, str) and axes in CELL_AXES else tuple(axes)
        room = CellPhysics(get_scenario(scenario), {}, seed, params or CellParams())
        return cls(names, room, cross or CrossParams())

    @property
    def seed(self) -> int:
        return self.room.seed

    def geometry(self, axis: str, q: np.ndarray) -> np.ndarray:
        u = q / self.cross.full_um
        e1, e2, e3 = self.axis_params[axis].geometry_e_um
        result: np.ndarray = q + u * (e1 + u * (e2 + u * e3))
        return result

    def static(self, q: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
        """Attained positions (no drift) for commands ``q`` per axis: own geometry plus the cross effects."""
        c = self.cross
        full2 = c.full_um * c.full_um
        strokes = {a: self.geometry(a, np.asarray(q[a], dtype=np.float64)) for a in self.axes}
        out = {}
        for to in self.axes:
            p = strokes[to].copy()
            for frm in self.axes:
                if frm != to:
                    p += (c.crosstalk(to, frm) + c.tilt(to, frm)) * strokes[frm]
            for i, a in enumerate(self.axes):
                for b in self.axes[i + 1:]:
                    p += c.bending(to, a, b) * q[a] * q[b] / full2
            out[to] = p
        return out

    def drift(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """Thermal drift of every axis at times ``t`` (µm)."""
        nodes = self.room.thermal(np.asarray(t, dtype=np.float64))
        t_ref = self.room.params.t_ref_c
        d_bracket = nodes["bracket"] - t_ref
        out = {}
        for a in self.axes:
            k = self.axis_params[a]
            out[a] = (k.k_stage_um_per_c * (nodes["stage"] - t_ref) + k.k_bracket_um_per_c * d_bracket
                      + k.k2_bracket_um_per_c2 * d_bracket * d_bracket + k.k_beam_um_per_c * (nodes["beam"] - t_ref))
        return out

    def wander(self, axis: str, t: np.ndarray) -> np.ndarray:
        """The slow wander of ``axis``' interferometer beam at times ``t``."""
        exo = self.room.exogenous if axis == self.axes[0] else self.beams[axis]
        return exo.at(np.atleast_1d(np.asarray(t, dtype=np.float64)))[2]

    def measure(self, axis: str, t: np.ndarray, true_um: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """``axis``' interferometer: truth + its beam's wander + white noise (``noise`` ~ N(0, 1)), quantised."""
        p = self.room.params
        raw = true_um + self.wander(axis, t) + p.interferometer_noise_um * noise
        result: np.ndarray = np.round(raw / p.interferometer_resolution_um) * p.interferometer_resolution_um
        return result


CommandFor = Callable[[dict[str, float], float, dict[str, float]], dict[str, float]]


def simulate_cell_steps(
    physics: MultiAxisPhysics,
    targets: Mapping[str, Sequence[float] | np.ndarray],
    cycles: Sequence[int],
    *,
    schedule: StepSchedule | None = None,
    channels: Sequence[str] = tuple(THERMOCOUPLES),
    command_for: CommandFor | None = None,
    t_start: float = 0.0,
) -> dict[str, np.ndarray]:
    """Step averages for ``targets`` (per axis, one entry per step), as
    :func:`nanodrift.drivers.simulated.runs.simulate_steps`.

    Returns ``t_s``, per axis ``<a>_um`` (measured), ``q_<a>_um`` (commanded) and ``<a>_true_um`` (the
    true position averaged over the same window), ``cycle`` and the channels.
    ``command_for(targets, t, temps)`` turns one step's targets (every axis) into its commands (a
    :class:`nanodrift.model.cell_model.CellModel`'s compensation); by default the command is the target.
    """
    schedule = schedule or StepSchedule()
    axes = physics.axes
    target_um = {a: np.asarray(targets[a], dtype=np.float64) for a in axes}
    n = target_um[axes[0]].size
    if any(v.size != n for v in target_um.values()) or len(cycles) != n:
        raise ValueError("every axis needs one target per step, and every step a cycle")
    step_start = t_start + schedule.step_s * np.arange(n)
    hold_start = step_start + schedule.ramp_s
    commands = {a: v.copy() for a, v in target_um.items()}
    noise_rng = np.random.default_rng([physics.seed, 3])
    if command_for is not None:  # needs the temperatures seen when each step is commanded
        thermal = physics.room.thermal(step_start)
        seen = {c: physics.room.measure_temperature(c, physics.room.sensor_truth(c, thermal), noise_rng.normal(size=n))
                for c in channels}
        for k in range(n):
            temps = {c: float(seen[c][k]) for c in channels}
            q = command_for({a: float(target_um[a][k]) for a in axes}, float(step_start[k]), temps)
            for a in axes:
                commands[a][k] = q[a]
    landing_rng = np.random.default_rng([physics.seed, 2])
    landing = {a: landing_rng.normal(0.0, physics.room.params.landing_sigma_um, n) for a in axes}

    pos_off = _window_offsets(schedule.position_interval_s, schedule)
    m = pos_off.size
    pos_t = (hold_start[:, None] + pos_off[None, :]).ravel()
    static = physics.static(commands)
    drift = physics.drift(pos_t)
    out: dict[str, np.ndarray] = {"t_s": hold_start + schedule.hold_s}
    for a in axes:
        true = np.repeat(static[a] + landing[a], m) + drift[a]
        meas = physics.measure(a, pos_t, true, noise_rng.normal(size=pos_t.size))
        out[f"{a}_um"] = meas.reshape(n, m).mean(axis=1)
        out[f"{a}_true_um"] = true.reshape(n, m).mean(axis=1)
    for a in axes:
        out[f"q_{a}_um"] = commands[a]
    out["cycle"] = np.asarray(cycles, dtype=np.float64)
    tc_off = _window_offsets(schedule.temperature_interval_s, schedule)
    tc_t = (hold_start[:, None] + tc_off[None, :]).ravel()
    thermal = physics.room.thermal(tc_t)
    for c in channels:
        read = physics.room.measure_temperature(c, physics.room.sensor_truth(c, thermal),
                                                noise_rng.normal(size=tc_t.size))
        out[c] = read.reshape(n, -1).mean(axis=1)
    return out


def steps_dataset(out: Mapping[str, np.ndarray], axes: Sequence[str], source: str,
                  channels: Sequence[str] = tuple(THERMOCOUPLES)) -> Dataset:
    """A :func:`simulate_cell_steps` result as a multi-axis :class:`nanodrift.calibration.dataset.Dataset`
    (the truth in ``<axis>_true_um`` columns)."""
    return Dataset(t=out["t_s"], x=out["x_um"], q=None, channels={c: out[c] for c in channels},
                   extra={"cycle": out["cycle"], **{f"{a}_true_um": out[f"{a}_true_um"] for a in axes}},
                   source=source, positions={a: out[f"{a}_um"] for a in axes},
                   commands={a: out[f"q_{a}_um"] for a in axes})



@dataclass
class CellValidationRun:
    """One ISO 9283 test on the simulated cell, run twice in the same room with the same noise: commanded
    through a model (``compensated``, None without one) and uncompensated (command = target)."""

    name: str
    axes: tuple[str, ...]
    targets_um: dict[str, np.ndarray]
    uncompensated: dict[str, np.ndarray]
    compensated: dict[str, np.ndarray] | None
    extrapolating_steps: int = 0

    def attained(self, with_model: bool, against: str = "truth") -> dict[str, np.ndarray]:
        """Per axis, the attained positions: the true ones (``truth``) or as the interferometer measured them."""
        run = self.compensated if with_model else self.uncompensated
        if run is None:
            raise ValueError(f"{self.name}: ran without a model")
        suffix = "_true_um" if against == "truth" else "_um"
        return {a: run[a + suffix] for a in self.axes}


def cell_command(model: CellModel) -> CommandFor:
    """A cell model as a run's ``command_for``: every axis' command from one temperature sample and target."""
    evaluator = model.evaluator()

    def command(targets: dict[str, float], t: float, temps: dict[str, float]) -> dict[str, float]:
        evaluator.observe(t, temps)
        return evaluator.command(targets, t)

    return command


def independent_command(models: Mapping[str, Model]) -> CommandFor:
    """One-axis models side by side (each fitted on ``Dataset.alone``): each axis' command from its own
    target only, what two or three one-axis cells on the stage would serve."""
    evaluators = {a: m.evaluator() for a, m in models.items()}

    def command(targets: dict[str, float], t: float, temps: dict[str, float]) -> dict[str, float]:
        out = {}
        for axis, ev in evaluators.items():
            ev.observe(t, temps)
            out[axis] = float(ev.command(targets[axis], t))
        return out

    return command


def run_cell_validation(physics: MultiAxisPhysics, command: CommandFor | None, *, cycles: int = 30,
                        name: str | None = None, out_of_range: Callable[[dict[str, float], dict[str, float]], bool]
                        | None = None) -> CellValidationRun:
    """The ISO 9283 plan (:func:`nanodrift.calibration.plans.cell_validation_plan`) on ``physics``, uncompensated
    and, given ``command`` (targets, t, temps -> commands), through it; ``out_of_range`` counts the steps
    a model extrapolates."""
    plan = cell_validation_plan(physics.axes, cycles)
    targets = {a: np.array([s.target(a) for s in plan]) for a in physics.axes}
    step_cycles = [s.cycle for s in plan]
    extrapolating = 0

    def counted(t_um: dict[str, float], t: float, temps: dict[str, float]) -> dict[str, float]:
        nonlocal extrapolating
        if out_of_range is not None and out_of_range(t_um, temps):
            extrapolating += 1
        assert command is not None
        return command(t_um, t, temps)

    without = simulate_cell_steps(physics, targets, step_cycles)
    with_ = simulate_cell_steps(physics, targets, step_cycles, command_for=counted) if command else None
    return CellValidationRun(name or physics.room.scenario.name, physics.axes, targets, without, with_, extrapolating)


def cross_params(spec: str | None = None) -> CrossParams:
    """The stack's cross-axis magnitudes with ``spec`` (the ``--effects`` text over the cross-axis catalogue,
    ``nanodrift.drivers.simulated.effects.CROSS_AXIS_EFFECTS``) applied."""
    effects = resolve_cross_effects(spec)
    return CrossParams(crosstalk_fraction=effects["crosstalk"]["fraction"],
                       non_orthogonality_rad=effects["non_orthogonality"]["rad"],
                       bending_um=effects["coupled_bending"]["um"])


def simulate_cell_dataset(axes: str | Sequence[str] = "xy", scenario: str = "train", effects: str | None = None,
                          *, cycles: int | None = None, seed: int = 0) -> Dataset:
    """A run of the simulated multi-axis cell as ``nanodrift simulate --axes`` writes it: the space-filling
    calibration (24 cycles) on a calibration scenario, the ISO 9283 points (30 cycles both ways) on a
    validation scenario; the true positions in ``<axis>_true_um``."""
    physics = MultiAxisPhysics.create(axes, scenario, seed, cross_params(effects))
    validation = physics.room.scenario.trajectory == "validation"
    n = (30 if validation else 24) if cycles is None else cycles
    if n < 1:
        raise ValueError(f"cycles must be at least 1, got {n}")
    plan = cell_validation_plan(physics.axes, n) if validation else cell_calibration_plan(physics.axes, n)
    out = simulate_cell_steps(physics, {a: [s.target(a) for s in plan] for a in physics.axes}, [s.cycle for s in plan])
    return steps_dataset(out, physics.axes, f"simulated:{''.join(physics.axes)}:{scenario}:seed {seed}")
