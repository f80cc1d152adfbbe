"""The ``[simulation]`` table of the operator config and the simulated sensors' own keys.

```toml
[simulation]
scenario = "train"            # steady | train | bidirectional | test1..test5 | room | daily | week
speed = 60.0                  # simulated seconds per wall second (daemon); procedures use a VirtualClock
seed = 0
effects = ["thermal_lag", "hysteresis"]          # or a table with parameters:
# effects = { thermal_lag = { tau_s = 1800.0 }, creep = {} }
params = { interferometer_noise_um = 0.01 }      # overrides of the cell's baseline magnitudes
truth_log = "truth.csv"       # every interferometer reading beside the true position (benchmarks/week.py)
axes = "xy"                   # a stacked XY (or "xyz") stage: one simulated output and interferometer per axis
cell = "realistic"            # ideal (default: the model's own form) | realistic (physics no term reproduces)
```
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import fields
from typing import Any, Literal

from pydantic import Field, field_validator, model_validator

from nanodrift.drivers.base import ActuatorOptions, SensorConfig, StrictModel
from nanodrift.drivers.simulated.effects import resolve_effects
from nanodrift.drivers.simulated.physics import CELL_AXES, CELLS, CellParams, CellPhysics
from nanodrift.drivers.simulated.scenarios import get_scenario

#: the top-level table this plugin owns
SECTION = "simulation"
#: the fastest ``speed``: each poll makes the cell compute ``speed`` x the wall time since the last one
MAX_SPEED = 10_000.0

#: What the daemon can serve on a scaled clock, in WALL seconds: each poll costs about a millisecond of
#: wall time, so a group is polled at most every WALL_POLL_S; and a reading may wait up to WALL_LATENCY_S
#: of wall time before a target is judged against it (hand-offs of the GIL between Zenoh's threads and
#: the event loop, a process descheduled on a busy machine). At ``speed`` these are ``speed`` times as
#: many seconds of the cell's clock, the one every age is judged on: at speed 10000 a poll at most every
#: 20 s and a reading fresh for at least 1000 s of cell time.
WALL_POLL_S = 0.002
WALL_LATENCY_S = 0.1

_PARAM_NAMES = {f.name for f in fields(CellParams)} - {"offsets_c", "geometry_e_um"}


class SimulationConfig(StrictModel):
    """The ``[simulation]`` table (strict: no ``"2"`` for 2)."""

    scenario: str = Field(default="train", description="room-temperature history (see drivers/simulated/README.md)")
    speed: float = Field(
        default=1.0, gt=0, le=MAX_SPEED,
        description=f"simulated seconds per wall second, at most {MAX_SPEED:g}: the tests and the hardware-in-the-"
                    "loop emulator run at 1000 (the demo at 50), so this leaves a margin of ten; far beyond it the "
                    "simulated cell computes more room history per poll than the daemon can follow (1e9 froze the "
                    "daemon, deaf to SIGTERM)")
    seed: int = Field(default=0, description="every run with the same seed is identical")
    effects: list[str] | dict[str, dict[str, float]] = Field(
        default_factory=list, description="hidden effects: names, or name -> {param = value}"
    )
    params: dict[str, float] = Field(default_factory=dict, description="overrides of CellParams magnitudes")
    truth_log: str = Field(
        default="", description='"" = off; else a CSV the cell appends every interferometer reading to, beside the '
                                "true attained position (t_s on the cell's clock, q_um, true_x_um, measured_x_um): "
                                "what a benchmark scores the daemon against")

    axes: str = Field(
        default="", description='"" = the paper\'s one-axis cell; "xy" or "xyz": a stacked XY/XYZ stage in the same '
                                "room (drivers/simulated/physics.py): one simulated output per axis "
                                "([axes.actuator] kind = \"simulated\") and one interferometer beam per axis "
                                "(channels interferometer_x, interferometer_y[, interferometer_z])")

    cell: str = Field(
        default="ideal", description='"ideal": the paper\'s model form (what a fit can represent exactly); '
                                     '"realistic": a lab\'s cell that no candidate term reproduces (asymmetric, '
                                     "lagging bending, an unmonitored heat source, interferometer refraction, "
                                     "hysteresis and creep, thermocouple noise and lags: drivers/simulated/README.md)")

    @field_validator("cell")
    @classmethod
    def _known_cell(cls, value: str) -> str:
        if value not in CELLS:
            raise ValueError(f"unknown simulated cell {value!r}; expected " + " or ".join(f'"{c}"' for c in CELLS))
        return value

    @field_validator("axes")
    @classmethod
    def _known_axes(cls, value: str) -> str:
        if value and value not in CELL_AXES:
            raise ValueError(f'unknown simulated axes {value!r}; expected "" (one axis), '
                             + " or ".join(f'"{name}"' for name in CELL_AXES))
        return value

    @model_validator(mode="after")
    def _sound_params(self) -> SimulationConfig:
        problems = CELLS[self.cell].params.with_overrides(self.params).problems()
        if problems:
            raise ValueError(f"params of the {self.cell} cell: " + "; ".join(problems))
        return self

    @model_validator(mode="after")
    def _multi_axis_effects(self) -> SimulationConfig:
        if self.axes and self.effects:
            raise ValueError(f"effects: the hidden effects are the one-axis cell's; the simulated {self.axes} cell has "
                             "its cross-axis effects (crosstalk, non-orthogonality, coupled bending) built in: "
                             "remove effects or axes")
        return self

    @property
    def axis_names(self) -> tuple[str, ...]:
        """The simulated stage's axes (``("x",)``: the one-axis cell)."""
        return CELL_AXES[self.axes] if self.axes else ("x",)

    @field_validator("scenario")
    @classmethod
    def _known_scenario(cls, value: str) -> str:
        get_scenario(value)
        return value

    @field_validator("effects")
    @classmethod
    def _known_effects(cls, value: Any) -> Any:
        resolve_effects(value)
        return value

    @field_validator("params")
    @classmethod
    def _known_params(cls, value: dict[str, float]) -> dict[str, float]:
        unknown = sorted(set(value) - _PARAM_NAMES)
        if unknown:
            known = ", ".join(sorted(_PARAM_NAMES))
            raise ValueError(f"unknown cell parameter(s) {', '.join(unknown)}; known: {known}")
        return value

    @property
    def min_interval_s(self) -> float:
        """The shortest poll interval (cell seconds) the daemon keeps at this speed: :data:`WALL_POLL_S`."""
        return self.speed * WALL_POLL_S

    @property
    def min_max_age_s(self) -> float:
        """The shortest ``max_age_s`` (cell seconds) that stays fresh at this speed: :data:`WALL_LATENCY_S`."""
        return self.speed * WALL_LATENCY_S

    def timing_warnings(self, sensors: Sequence[tuple[int, SensorConfig]]) -> list[str]:
        """Sensors whose timing this speed cannot serve, in check-config's form (``sensors[2] (T3).max_age_s: ...``)."""
        out = []
        for index, sensor in sensors:
            where = f"sensors[{index}] ({sensor.name})"
            if sensor.max_age_s < self.min_max_age_s:
                out.append(
                    f"{where}.max_age_s: {sensor.max_age_s:g} s of cell time is "
                    f"{1e3 * sensor.max_age_s / self.speed:.3g} ms of wall time at simulation.speed {self.speed:g}: "
                    f"shorter than the daemon's latency ({1e3 * WALL_LATENCY_S:g} ms of wall time), so the channel "
                    f"flaps between ok and stale and targets are refused; make it at least {self.min_max_age_s:g} s "
                    f"or lower the speed to {sensor.max_age_s / WALL_LATENCY_S:g}")
            if sensor.interval_s < self.min_interval_s:
                out.append(
                    f"{where}.interval_s: {sensor.interval_s:g} s of cell time is "
                    f"{1e3 * sensor.interval_s / self.speed:.3g} ms of wall time at simulation.speed {self.speed:g}: "
                    f"the daemon polls at most every {1e3 * WALL_POLL_S:g} ms of wall time (the poller spins a core "
                    f"trying); make it at least {self.min_interval_s:g} s")
        return out

    def physics(self) -> CellPhysics:
        """The cell of this table: its room, seed, magnitudes and axes."""
        return CellPhysics.create(self.scenario, self.effects, self.seed,
                                  CELLS[self.cell].params.with_overrides(self.params), axes=self.axis_names,
                                  cell=self.cell)


class SimulatedSensorConfig(SensorConfig):
    """A ``[[sensors]]`` entry with ``kind = "simulated"``.

    ``channel`` picks what the sensor reads in the simulated cell: T1..T4 (thermocouples), ``air``
    (true air temperature) or ``interferometer``; by default the sensor's own name.
    """

    kind: Literal["simulated"] = "simulated"
    channel: str | None = None

    @property
    def source(self) -> str:
        return self.channel or self.name


class SimulatedActuatorConfig(ActuatorOptions):
    """``[actuator] kind = "simulated"``: the simulated stage's closed loop takes each command (no other keys)."""

    kind: Literal["simulated"] = "simulated"
