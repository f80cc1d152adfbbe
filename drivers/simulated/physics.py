"""The simulated cell's physics as a pure, vectorised core: times and commands in, positions and
temperatures out.

Thermal part: the air temperature is piecewise linear between knots (every ``knot_dt_s``: the
scenario's shape plus a small random fluctuation). Every structure/sensor temperature is a
first-order lag of the air, and a first-order lag of a piecewise-linear input has an exact closed
form, so node temperatures are exact at any time, at any spacing, with no integration step. The
state at the knots is computed once per chunk by the exact recursion (:func:`first_order_filter`), and
the grid is extended lazily, so a daemon can run for days.

Mechanical part: each axis' stage follows its command (closed-loop setpoint) with a few nm of landing
error; the optional effects add direction memory (hysteresis) and settling (creep). The state after
each command is an exact update, evaluated at any later time. A cell of one axis is the paper's stage;
a stack of two or three (XY, XYZ) shares the room, has its own stage per axis (:data:`AXIS_PARAMS`) and
beam, and its stages push each other (crosstalk, non-orthogonality, coupled bending: :class:`CrossParams`).

Magnitudes after the paper: drift about -1.1 µm/°C overall (Fig. 1: 0.4 µm for -0.35 °C), split
between the stage (T1), the bracket (T2) and the air the beam crosses (T3/T4); the bracket's
bending adds a small quadratic part (the "nonlinear combination of thermal expansions", II.B.2)
that is invisible inside a 0.5 °C training range and is what makes extrapolation (test 5) degrade.
The interferometer has ~20 nm white noise plus a slow ~25 nm wander (its wavelength/dead-path
uncertainty, III.A: < 40 nm); thermocouples 5 mK noise and 0.01 °C quantisation.

That is the ideal cell: its drift is the paper's model form. The realistic cell (:data:`CELLS`) is the same code
with more :class:`CellParams` switched on (each 0 in the ideal cell): bending that is not a square and lags the
bracket, an unmonitored heat source, refraction the interferometer's compensation misses, hysteresis and creep,
thermocouple noise and lags (drivers/simulated/README.md, "The realistic cell").
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import Any, NamedTuple

import numpy as np

from nanodrift.drivers.simulated.effects import UnknownNameError, resolve_cross_effects, resolve_effects
from nanodrift.drivers.simulated.scenarios import Scenario, get_scenario

#: temperature channels of the cell and the thermal node each reads (paper III.A, Fig. 5)
THERMOCOUPLES: dict[str, str] = {"T1": "stage", "T2": "bracket", "T3": "t3", "T4": "t4"}
POSITION_CHANNEL = "interferometer"
#: extra channels a config may map a sensor to: the true air temperature (no sensor offset)
TRUTH_CHANNELS: dict[str, str] = {"air": "air"}


@dataclass(frozen=True)
class CellParams:
    """Every magnitude of the baseline cell (no hidden effect). Units: µm, s, °C."""

    t_ref_c: float = 22.0  # temperature at which the interferometer was zeroed
    # thermal time constants of the nodes (first-order lags of the air)
    tau_stage_s: float = 900.0
    tau_bracket_s: float = 2400.0
    tau_t3_s: float = 60.0
    tau_t4_s: float = 150.0
    tau_beam_s: float = 120.0  # air along the interferometer beam
    # drift sensitivities: sum -1.1 um/degC
    k_stage_um_per_c: float = -0.40
    k_bracket_um_per_c: float = -0.50
    k_beam_um_per_c: float = -0.20
    k2_bracket_um_per_c2: float = -0.40  # bracket bending: nonlinear part
    # geometry x = g(q) = q + e(q / full), e cubic (few hundred nm over the range)
    geometry_full_um: float = 480.0
    geometry_e_um: tuple[float, float, float] = (-0.25, 1.20, -0.75)
    # thermocouples
    offsets_c: tuple[tuple[str, float], ...] = (("T1", 0.04), ("T2", -0.03), ("T3", 0.06), ("T4", -0.02))
    tc_noise_c: float = 0.005
    tc_quantum_c: float = 0.01
    # interferometer
    interferometer_noise_um: float = 0.020
    interferometer_resolution_um: float = 0.0003
    interferometer_wander_um: float = 0.025
    interferometer_wander_tau_s: float = 1200.0
    # room
    air_fluctuation_c: float = 0.01
    air_fluctuation_tau_s: float = 600.0
    # stage
    landing_sigma_um: float = 0.003
    knot_dt_s: float = 30.0
    # ----- the realistic cell's physics (:data:`CELLS`); each 0 = off, as in the ideal cell ---------------
    #: thermocouple lag (s): the junction and its sheath lag the surface they are glued to (first order)
    tc_lag_s: float = 0.0
    #: bracket bending is not a square (°C): 2·s²·(exp(ΔT/s) − 1 − ΔT/s) instead of ΔT²: equal for |ΔT| << s,
    #: steeper on the warm side (the bracket bears on its clamp), flattening to linear on the cool side
    bend_scale_c: float = 0.0
    #: bending follows the bracket's temperature with this further lag (s): the gradient through its thickness
    bend_lag_s: float = 0.0
    #: an unmonitored heat source: rise (°C) of the part it heats were it always on, its on/off period and
    #: on-time (s), the part's time constant (s) and the drift per °C of it (µm/°C)
    heat_rise_c: float = 0.0
    heat_period_s: float = 5400.0
    heat_on_s: float = 2400.0
    heat_tau_s: float = 1200.0
    heat_k_um_per_c: float = -0.5
    #: interferometer refraction: beam length in air (µm, dead path + measuring path) whose index the
    #: built-in compensation follows imperfectly: its Pt100 lags the air (``refraction_comp_tau_s``) and the
    #: index wanders (pressure/humidity the barometer misses) as a random walk (ppm per √h)
    dead_path_um: float = 0.0
    refraction_comp_tau_s: float = 1800.0
    index_walk_ppm_per_sqrt_h: float = 0.0

    def offset(self, channel: str) -> float:
        return self._offsets.get(channel, 0.0)

    @cached_property
    def _offsets(self) -> dict[str, float]:
        """``offsets_c`` as a dict, made once (a stepped cell asks it per reading)."""
        return dict(self.offsets_c)

    def problems(self) -> list[str]:
        """What is wrong with the realistic cell's magnitudes, one ``field: what was expected`` each (none: fine)."""
        out = [f"{name}: expected >= 0, got {getattr(self, name):g}"
               for name in ("tc_lag_s", "bend_scale_c", "bend_lag_s", "heat_rise_c", "dead_path_um",
                            "index_walk_ppm_per_sqrt_h") if not getattr(self, name) >= 0]
        if self.heat_rise_c and not 0 < self.heat_on_s < self.heat_period_s:
            out.append(f"heat_on_s: expected between 0 and heat_period_s ({self.heat_period_s:g} s), "
                       f"got {self.heat_on_s:g}")
        if self.heat_rise_c and not self.heat_tau_s > 0:
            out.append(f"heat_tau_s: expected > 0, got {self.heat_tau_s:g}")
        if self.dead_path_um and not self.refraction_comp_tau_s > 0:
            out.append(f"refraction_comp_tau_s: expected > 0, got {self.refraction_comp_tau_s:g}")
        return out

    def with_overrides(self, overrides: Mapping[str, float]) -> CellParams:
        """A copy with the magnitudes ``overrides`` names (this class's fields) replaced."""
        changes: dict[str, Any] = dict(overrides)
        return replace(self, **changes)


#: Edlén (1966) / Birch & Downs (1993) near 20 °C, 101.3 kPa, 633 nm: the index of air falls 0.93 ppm per K
DN_DT_PER_C = -0.93e-6


def cascade(tau_a_s: float, lag_a: Any, tau_b_s: float, lag_b: Any) -> Any:
    """A lag of ``tau_b_s`` of a lag of ``tau_a_s`` of the air, exactly, from the two single lags of the air:
    1/((1+sτa)(1+sτb)) = (τa/(1+sτa) − τb/(1+sτb))/(τa − τb). Needs τa ≠ τb."""
    return (tau_a_s * lag_a - tau_b_s * lag_b) / (tau_a_s - tau_b_s)


def heated_rise(params: CellParams, t: Any, phase_s: float) -> Any:
    """Temperature rise (°C) of the part an unmonitored source heats, on, off, on, ... every ``heat_period_s``
    for ``heat_on_s``: a first-order lag of a square wave, in its periodic steady state (the source has cycled
    for days), exact at any time. Floats and arrays both work."""
    p = params
    tau, period, on = p.heat_tau_s, p.heat_period_s, p.heat_on_s
    low = (1.0 - math.exp(-on / tau)) * math.exp(-(period - on) / tau) / (1.0 - math.exp(-period / tau))
    high = 1.0 - (1.0 - low) * math.exp(-on / tau)
    s = np.mod(np.asarray(t, dtype=np.float64) + phase_s, period)
    rise = np.where(s < on, 1.0 - (1.0 - low) * np.exp(-s / tau), high * np.exp(-(s - on) / tau))
    return p.heat_rise_c * (rise if rise.ndim else float(rise))


def first_order_filter(b0: float, b1: float, a1: float, x: np.ndarray, z0: float) -> np.ndarray:
    """``y[n] = b0 x[n] + b1 x[n-1] - a1 y[n-1]`` with initial state ``z0``: ``scipy.signal.lfilter([b0, b1],
    [1, a1], x, zi=[z0])[0]``, the same operations in the same order (direct form II transposed), so the same
    bits. Written out because importing ``scipy.signal`` costs every simulated daemon and CLI run a second
    of CPU; a chunk is a few hundred knots, so the loop costs under a millisecond."""
    out = np.empty(len(x))
    z = z0
    for n, xn in enumerate(x.tolist()):
        yn = z + b0 * xn
        z = xn * b1 - yn * a1
        out[n] = yn
    return out


def _walk(held: np.ndarray, steps: np.ndarray, chunk: int) -> np.ndarray:
    """A random walk by ``steps`` on from the last ``held`` value (0 on an empty grid; chunk 0's first step is 0)."""
    if chunk == 0:
        steps[0] = 0.0
    return (float(held[-1]) if held.size else 0.0) + np.cumsum(steps)


def _ou_step(prev: float, n: int, dt: float, tau: float, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """``n`` further samples of an Ornstein-Uhlenbeck process (stationary std ``sigma``), exact."""
    a = math.exp(-dt / tau)
    shocks = rng.normal(0.0, sigma * math.sqrt(1.0 - a * a), n)
    return first_order_filter(1.0, 0.0, -a, shocks, a * prev)


class Exogenous:
    """Everything that depends on time only, on a lazily extended knot grid.

    Per knot: air temperature, interferometer wander, unmonitored random walk, and the exact state
    of every thermal node. Chunks are generated in order from per-chunk seeds, each continuing the
    last knot of the one before, so any query order gives the same numbers.

    Memory is bounded: at most :attr:`KEEP_CHUNKS` chunks are held (more only while one query spans
    more). A daemon's queries move forward in time, so the oldest chunks are dropped as new ones are
    made; a later query before the oldest held chunk regenerates the grid from the start (identical
    numbers, at the cost of recomputing the history up to it: about a millisecond per simulated day).
    """

    CHUNK = 720
    #: chunks held at most (each CHUNK knots): two days at the default 30 s knots
    KEEP_CHUNKS = 8
    #: the per-knot series (``nodes``: a column per node), extended and dropped together
    SERIES = ("t", "air", "wander", "walk", "index_ppm", "nodes")

    def __init__(self, scenario: Scenario, params: CellParams, node_taus: Mapping[str, float], seed: int,
                 walk_um_per_sqrt_h: float = 0.0) -> None:
        self.scenario = scenario
        self.params = params
        self.node_names = tuple(node_taus)
        self.taus = np.array([node_taus[n] for n in self.node_names], dtype=np.float64)
        self.seed = seed
        self.walk_sigma = walk_um_per_sqrt_h * math.sqrt(params.knot_dt_s / 3600.0)
        self.index_sigma = params.index_walk_ppm_per_sqrt_h * math.sqrt(params.knot_dt_s / 3600.0)
        self.t0 = scenario.start_h * 3600.0
        self.dt = params.knot_dt_s
        #: :meth:`at1`'s last answer (a beam's reading asks for the room and its wander at one instant) and the
        #: knot interval it read, in plain floats (the stepped drivers stay in one interval for many samples)
        self._at1_last: tuple[float, tuple[float, dict[str, float], float, float]] = (math.nan, (0.0, {}, 0.0, 0.0))
        self._at1_interval: _Interval | None = None
        a = np.exp(-self.dt / self.taus)
        r = (self.taus / self.dt) * (1.0 - a)
        self._a, self._b_now, self._b_prev = a, 1.0 - r, r - a
        self._restart()

    def _restart(self) -> None:
        """Back to an empty grid: the next chunk made is chunk 0."""
        self.t = np.empty(0)
        self.air = np.empty(0)
        self.wander = np.empty(0)
        self.walk = np.empty(0)
        self.index_ppm = np.empty(0)
        self.nodes = np.empty((0, len(self.node_names)))
        self._fluct_last = 0.0
        self._chunks = 0  # chunks made so far, held or dropped
        self.first_knot = 0  # global index of the first held knot (t[0] is knot first_knot of the grid)

    @property
    def knots_held(self) -> int:
        return int(self.t.size)

    def ensure(self, t_max: float, t_min: float | None = None) -> None:
        """Hold every knot needed to evaluate times in ``[t_min, t_max]`` (``t_min`` None: ``t_max``)."""
        low = max(0, int(((t_max if t_min is None else min(t_min, t_max)) - self.t0) // self.dt))  # its first knot
        if low < self.first_knot:  # before the oldest held chunk: regenerate from the start
            self._restart()
        while self.t.size < 2 or self.t[-1] < t_max + self.dt:
            self._extend()
            self._drop_before(low // self.CHUNK)

    def _drop_before(self, needed_chunk: int) -> None:
        """Drop the oldest chunks beyond :attr:`KEEP_CHUNKS`, never chunk ``needed_chunk`` or later."""
        first_chunk = self.first_knot // self.CHUNK
        drop = min(needed_chunk, self._chunks - self.KEEP_CHUNKS) - first_chunk
        if drop <= 0:
            return
        cut = drop * self.CHUNK
        for name in self.SERIES:
            setattr(self, name, getattr(self, name)[cut:].copy())
        self.first_knot += cut

    def _extend(self) -> None:
        p, k, n = self.params, self._chunks, self.CHUNK
        rng = np.random.default_rng([self.seed, 1, k])
        t = self.t0 + self.dt * (np.arange(n) + k * n)
        fluct = _ou_step(self._fluct_last, n, self.dt, p.air_fluctuation_tau_s, p.air_fluctuation_c, rng)
        if k == 0:  # start the fluctuation from its stationary distribution, at the first knot
            fluct = fluct - fluct[0] + rng.normal(0.0, p.air_fluctuation_c)
        self._fluct_last = float(fluct[-1])
        air = self.scenario.air(t) + fluct
        prev_wander = float(self.wander[-1]) if self.wander.size else rng.normal(0.0, p.interferometer_wander_um)
        wander = _ou_step(prev_wander, n, self.dt, p.interferometer_wander_tau_s, p.interferometer_wander_um, rng)
        walk = _walk(self.walk, rng.normal(0.0, self.walk_sigma, n) if self.walk_sigma > 0 else np.zeros(n), k)
        index_steps = (np.random.default_rng([self.seed, 4, k]).normal(0.0, self.index_sigma, n)  # its own stream:
                       if self.index_sigma > 0 else np.zeros(n))  # the ideal cell's draws stay the same
        index_ppm = _walk(self.index_ppm, index_steps, k)
        nodes = np.empty((n, len(self.node_names)))
        for j in range(len(self.node_names)):
            if self.nodes.shape[0]:
                zi = self._b_prev[j] * self.air[-1] + self._a[j] * self.nodes[-1, j]
            else:  # equilibrium with the first knot's air
                zi = air[0] * (1.0 - self._b_now[j])
            nodes[:, j] = first_order_filter(self._b_now[j], self._b_prev[j], -self._a[j], air, zi)
        for name, new in zip(self.SERIES, (t, air, wander, walk, index_ppm, nodes), strict=True):
            setattr(self, name, np.concatenate((getattr(self, name), new)))
        self._chunks += 1

    def at(self, t: np.ndarray) -> tuple[np.ndarray, dict[str, np.ndarray], np.ndarray, np.ndarray]:
        """(air, nodes by name, wander, walk) at times ``t``: exact for the nodes, linear otherwise."""
        i, h = self._locate(np.asarray(t, dtype=np.float64))
        u0, u1 = self.air[i], self.air[i + 1]
        slope = (u1 - u0) / self.dt
        air = u0 + slope * h
        s_tau = slope[:, None] * self.taus[None, :]
        decay = np.exp(-h[:, None] / self.taus[None, :])
        nodes = air[:, None] - s_tau + (self.nodes[i] - u0[:, None] + s_tau) * decay
        frac = h / self.dt
        wander = self.wander[i] + (self.wander[i + 1] - self.wander[i]) * frac
        walk = self.walk[i] + (self.walk[i + 1] - self.walk[i]) * frac
        return air, {n: nodes[:, j] for j, n in enumerate(self.node_names)}, wander, walk

    def _locate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """For times ``t`` (held first): the held knot each falls after and how far past it (a time before the
        grid's start counts as its start)."""
        if t.size:
            self.ensure(float(t.max()), float(t.min()))
        else:
            self.ensure(0.0)
        tc = np.maximum(t, self.t0)
        i = np.minimum(((tc - self.t0) // self.dt).astype(np.int64) - self.first_knot, self.t.size - 2)
        return i, tc - self.t[i]

    def index_at(self, t: np.ndarray) -> np.ndarray:
        """The random-walk part of the air's refractive index (ppm; 0 at the start of the room's history, when the
        compensation was set, so a run starts already off) at times ``t``, linear between knots."""
        i, h = self._locate(np.atleast_1d(np.asarray(t, dtype=np.float64)))
        frac = h / self.dt
        result: np.ndarray = self.index_ppm[i] + (self.index_ppm[i + 1] - self.index_ppm[i]) * frac
        return result

    def at1(self, t: float) -> tuple[float, dict[str, float], float, float]:
        """:meth:`at` for one time, in plain floats (the stepped drivers call this per sample): the same float
        operations, on the knot interval's values taken out of the arrays once (many samples fall in one)."""
        last_t, (air, nodes, wander, walk) = self._at1_last
        if t == last_t:
            return air, dict(nodes), wander, walk
        tc = max(t, self.t0)
        knot = int((tc - self.t0) // self.dt)
        interval = self._at1_interval
        if interval is None or interval.knot != knot:
            interval = self._at1_interval = self._interval1(t, tc)
        h = tc - interval.t
        air = interval.air + interval.slope * h
        nodes = {name: air - s_tau + c * math.exp(-h / tau) for name, tau, s_tau, c in interval.nodes}
        frac = h / self.dt
        wander = interval.wander + interval.wander_rise * frac
        walk = interval.walk + interval.walk_rise * frac
        self._at1_last = (t, (air, nodes, wander, walk))
        return air, dict(nodes), wander, walk

    def _interval1(self, t: float, tc: float) -> _Interval:
        """The knot interval :meth:`at1` reads at ``t`` (``tc``: ``t`` no earlier than the grid's start)."""
        self.ensure(t)
        raw = int((tc - self.t0) // self.dt) - self.first_knot
        i = min(raw, self.t.size - 2)
        u0, u1 = float(self.air[i]), float(self.air[i + 1])
        slope = (u1 - u0) / self.dt
        row = self.nodes[i].tolist()
        nodes = []
        for j, name in enumerate(self.node_names):
            tau = float(self.taus[j])
            s_tau = slope * tau
            nodes.append((name, tau, s_tau, row[j] - u0 + s_tau))
        w0, w1 = float(self.wander[i]), float(self.wander[i + 1])
        k0, k1 = float(self.walk[i]), float(self.walk[i + 1])
        # an interval clamped at the grid's end (``i < raw``) is never reused: knot -1 matches no time
        return _Interval(i + self.first_knot if i == raw else -1, float(self.t[i]), u0, slope, tuple(nodes),
                         w0, w1 - w0, k0, k1 - k0)


class _Interval(NamedTuple):
    """One knot interval of an :class:`Exogenous` grid in plain floats, as :meth:`Exogenous.at1` reads it."""

    knot: int  # the global index of its first knot (-1: not to be reused)
    t: float  # its first knot's time
    air: float  # the air there, and its slope over the interval
    slope: float
    #: per node (name, tau, slope·tau, node − air + slope·tau at the first knot)
    nodes: tuple[tuple[str, float, float, float], ...]
    wander: float  # the wander and the walk at the first knot, and their rises to the next
    wander_rise: float
    walk: float
    walk_rise: float


@dataclass
class StageState:
    """The stage after its last command: what later positions depend on."""

    t: float = -math.inf
    q: float = 0.0
    direction: float = 1.0
    creep_sum: float = 0.0  # sum_i dq_i exp(-(t - t_i)/tau), as of time t
    landing_um: float = 0.0


@dataclass(frozen=True)
class AxisParams:
    """One stage of the cell: its geometric error and its thermal drift (µm, °C)."""

    geometry_e_um: tuple[float, float, float]
    k_stage_um_per_c: float
    k_bracket_um_per_c: float
    k_beam_um_per_c: float
    k2_bracket_um_per_c2: float
    full_um: float = 480.0

    def geometry(self, q: Any) -> Any:
        """x = g(q) = q + e(q / full), e cubic: plain arithmetic, so floats and arrays both work."""
        u = q / self.full_um
        e1, e2, e3 = self.geometry_e_um
        return q + u * (e1 + u * (e2 + u * e3))


#: the stacked stages (``[simulation] axes``, ``simulate --axes``); a cell of one axis is the paper's stage
CELL_AXES: dict[str, tuple[str, ...]] = {"xy": ("x", "y"), "xyz": ("x", "y", "z")}
#: each stage of a stack: x drifts as the paper's stage (-1.1 µm/°C, bending half as much), y the other way, z less
AXIS_PARAMS: dict[str, AxisParams] = {
    "x": AxisParams((-0.25, 1.20, -0.75), -0.40, -0.50, -0.20, -0.20),
    "y": AxisParams((0.20, -0.90, 0.60), 0.30, 0.25, 0.10, 0.12),
    "z": AxisParams((-0.15, 0.70, -0.45), -0.25, -0.20, -0.10, -0.10),
}


@dataclass(frozen=True)
class CrossParams:
    """What the stages of a stack do to each other, scaled by three knobs (the cross-axis effects of
    :data:`nanodrift.drivers.simulated.effects.CROSS_AXIS_EFFECTS`; 0 switches one off).

    Per pair the sign and share are fixed (``CROSSTALK``, ``TILT``, ``BENDING``).
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


def cross_params(spec: str | None = None) -> CrossParams:
    """The stack's cross-axis magnitudes with ``spec`` (the ``--effects`` text over the cross-axis catalogue)."""
    effects = resolve_cross_effects(spec)
    return CrossParams(crosstalk_fraction=effects["crosstalk"]["fraction"],
                       non_orthogonality_rad=effects["non_orthogonality"]["rad"],
                       bending_um=effects["coupled_bending"]["um"])


@dataclass
class CellPhysics:
    """The cell: a scenario, hidden effects with parameters, a seed, and its stages (``axes``: one, or a stack
    of two or three in the same room, each with its own interferometer beam). Pure and vectorised.

    The room (air, nodes, T1..T4) is shared; the first axis' beam wanders with the room's draws (so a cell of
    one axis is the paper's), every other beam with its own. Per-axis state and results are dicts by axis.
    """

    scenario: Scenario
    effects: dict[str, dict[str, float]] = field(default_factory=dict)
    seed: int = 0
    params: CellParams = field(default_factory=CellParams)
    axes: tuple[str, ...] = ("x",)
    cross: CrossParams = field(default_factory=CrossParams)
    #: each axis' stage; empty: the paper's stage (``params``) for a cell of one axis, :data:`AXIS_PARAMS` for a stack
    axis_params: Mapping[str, AxisParams] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if len(set(self.axes)) != len(self.axes) or not 1 <= len(self.axes) <= 3 or set(self.axes) - set(AXIS_PARAMS):
            raise ValueError(f"a simulated cell has 1 to 3 distinct axes of {', '.join(AXIS_PARAMS)}, got {self.axes}")
        p = self.params
        if not self.axis_params:  # one axis: the paper's stage, as ``params`` (``[simulation] params``) sets it
            paper = AxisParams(p.geometry_e_um, p.k_stage_um_per_c, p.k_bracket_um_per_c, p.k_beam_um_per_c,
                               p.k2_bracket_um_per_c2, p.geometry_full_um)
            self.axis_params = {self.axes[0]: paper} if len(self.axes) == 1 else {a: AXIS_PARAMS[a] for a in self.axes}
        if p.problems():
            raise ValueError("simulated cell parameters: " + "; ".join(p.problems()))
        taus = {"stage": p.tau_stage_s, "bracket": p.tau_bracket_s, "t3": p.tau_t3_s, "t4": p.tau_t4_s,
                "beam": p.tau_beam_s}
        if "thermal_lag" in self.effects:
            taus["hidden_lag"] = self.effects["thermal_lag"]["tau_s"]
        if "temperature_rate" in self.effects:
            taus["rate_lag"] = self.effects["temperature_rate"]["tau_s"]
        if p.tc_lag_s:
            taus["tc_lag"] = p.tc_lag_s
        if p.bend_lag_s:
            taus["bend_lag"] = p.bend_lag_s
        if p.dead_path_um:
            taus["refraction_comp"] = p.refraction_comp_tau_s
        for lagged, lag in (("stage", "tc_lag"), ("bracket", "tc_lag"), ("t3", "tc_lag"), ("t4", "tc_lag"),
                            ("bracket", "bend_lag")):
            if lag in taus and taus[lag] == taus[lagged]:
                raise ValueError(f"{lag} ({taus[lag]:g} s) must differ from the {lagged} node's time constant: "
                                 "the exact cascade of two lags needs two different ones")
        #: every thermal node's time constant (s), by name
        self.node_taus = dict(taus)
        walk = self.effects.get("unmonitored_drift", {}).get("walk_um_per_sqrt_h", 0.0)
        self.exogenous = Exogenous(self.scenario, p, taus, self.seed, walk_um_per_sqrt_h=walk)
        #: where in its on/off cycle the unmonitored heat source is at time 0 (its own stream)
        self.heat_phase_s = (float(np.random.default_rng([self.seed, 5]).uniform(0.0, p.heat_period_s))
                             if p.heat_rise_c else 0.0)
        # a wander per beam: the first is the room's own, the others independent draws (only their wander is read)
        self.beams = {self.axes[0]: self.exogenous}
        for k, axis in enumerate(self.axes[1:], start=1):
            self.beams[axis] = Exogenous(self.scenario, p, {"beam": p.tau_beam_s}, (self.seed + 1) * 1_000_003 + k)
        hyst = self.effects.get("hysteresis", {})
        self.deadband_um = hyst.get("deadband_um", 0.5)
        creep = self.effects.get("creep")
        self.creep_c = creep["c"] if creep else 0.0
        self.creep_tau_s = creep["tau_s"] if creep else 1.0

    @classmethod
    def create(cls, scenario: str = "steady", effects: str | Sequence[str] | Mapping[str, Any] | None = None,
               seed: int = 0, params: CellParams | None = None, *, axes: str | Sequence[str] = "x",
               cross: CrossParams | None = None, cell: str = "ideal", **param_overrides: float) -> CellPhysics:
        """By names: ``CellPhysics.create("train", "thermal_lag:tau_s=1800", seed=3)``, ``(..., axes="xy")``,
        ``(..., cell="realistic")``. ``params`` replaces the variant's magnitudes, ``param_overrides`` and
        ``effects`` go on top of them."""
        variant = cell_variant(cell)
        base = params or variant.params
        if param_overrides:
            base = base.with_overrides(param_overrides)
        return cls(get_scenario(scenario), variant.effects_with(resolve_effects(effects), len(tuple(axes))), seed,
                   base, tuple(axes), cross or CrossParams())

    # ----- thermal -------------------------------------------------------------------------------
    def thermal(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """True temperatures (no sensor noise) of the air and every node at times ``t``."""
        air, nodes, _, _ = self.exogenous.at(np.atleast_1d(t))
        return {"air": air, **nodes}

    def thermal1(self, t: float) -> dict[str, float]:
        air, nodes, _, _ = self.exogenous.at1(t)
        return {"air": air, **nodes}

    def sensor_truth(self, channel: str, thermal: Mapping[str, Any]) -> Any:
        """What a perfect thermocouple ``channel`` reads (node temperature + its mounting offset; in the realistic
        cell lagged by its junction): plain arithmetic, so floats (the stepped cell) and arrays both work."""
        node = THERMOCOUPLES.get(channel) or TRUTH_CHANNELS[channel]
        if self.params.tc_lag_s and channel in THERMOCOUPLES:  # the junction lags the surface it reads
            return (cascade(self.node_taus[node], thermal[node], self.params.tc_lag_s, thermal["tc_lag"])
                    + self.params.offset(channel))
        return thermal[node] + self.params.offset(channel)

    def _drift(self, axis: str, t: Any, air: Any, nodes: Mapping[str, Any], walk: Any) -> Any:
        """``axis``' drift from the exogenous state; plain arithmetic, so floats and arrays both work."""
        k, t_ref, p = self.axis_params[axis], self.params.t_ref_c, self.params
        d_bracket = nodes["bracket"] - t_ref
        if p.bend_scale_c or p.bend_lag_s:  # the realistic bracket: lagging, asymmetric bending
            d_bend = (cascade(p.tau_bracket_s, nodes["bracket"], p.bend_lag_s, nodes["bend_lag"]) - t_ref
                      if p.bend_lag_s else d_bracket)
            s = p.bend_scale_c
            bending = k.k2_bracket_um_per_c2 * (2.0 * s * s * (np.exp(d_bend / s) - 1.0 - d_bend / s) if s
                                                else d_bend * d_bend)
        else:
            bending = k.k2_bracket_um_per_c2 * d_bracket * d_bracket
        drift = (k.k_stage_um_per_c * (nodes["stage"] - t_ref) + k.k_bracket_um_per_c * d_bracket
                 + bending
                 + k.k_beam_um_per_c * (nodes["beam"] - t_ref))
        if p.heat_rise_c:
            drift = drift + p.heat_k_um_per_c * heated_rise(p, t, self.heat_phase_s)
        if "thermal_lag" in self.effects:
            drift = drift + self.effects["thermal_lag"]["k_um_per_c"] * (nodes["hidden_lag"] - t_ref)
        if "temperature_rate" in self.effects:
            e = self.effects["temperature_rate"]
            drift = drift + e["k_um_per_c_per_s"] * (air - nodes["rate_lag"]) / e["tau_s"]
        if "unmonitored_drift" in self.effects:
            drift = drift + self.effects["unmonitored_drift"]["rate_um_per_h"] * t / 3600.0 + walk
        return drift

    def drift(self, t: np.ndarray) -> dict[str, np.ndarray]:
        """Thermal and other time-only drift of every axis' attained position, µm."""
        t = np.atleast_1d(np.asarray(t, dtype=np.float64))
        air, nodes, _, walk = self.exogenous.at(t)
        return {a: self._drift(a, t, air, nodes, walk) for a in self.axes}

    def static(self, q: Mapping[str, Any], nodes: Mapping[str, Any] | None = None,
               direction: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """Attained positions without drift for commands ``q`` per axis: each stage's own stroke (with the hidden
        effects on it: ``nodes`` and ``direction`` are read only by those) plus what the other stages of a stack
        push into it (crosstalk, non-orthogonality, coupled bending). Floats and arrays both work."""
        c, t_ref = self.cross, self.params.t_ref_c
        full2 = c.full_um * c.full_um
        strokes = {a: self.axis_params[a].geometry(q[a]) for a in self.axes}
        out = {}
        for to in self.axes:
            x = strokes[to]
            if "position_thermal_coupling" in self.effects:
                assert nodes is not None
                x = x * (1.0 + self.effects["position_thermal_coupling"]["kappa_per_c"] * (nodes["stage"] - t_ref))
            if "hysteresis" in self.effects:
                assert direction is not None
                x = x - 0.5 * self.effects["hysteresis"]["h_um"] * direction[to]
            for frm in self.axes:
                if frm != to:
                    x = x + (c.crosstalk(to, frm) + c.tilt(to, frm)) * strokes[frm]
            for i, a in enumerate(self.axes):
                for b in self.axes[i + 1:]:
                    x = x + c.bending(to, a, b) * q[a] * q[b] / full2
            out[to] = x
        return out

    def _positions(self, t: Any, exogenous: tuple[Any, Mapping[str, Any], Any, Any],
                   states: Mapping[str, Mapping[str, Any]], exp: Callable[[Any], Any]) -> dict[str, Any]:
        """Every axis' true position from the exogenous state at ``t`` and each axis' command state (``t``, ``q``,
        ``direction``, ``creep_sum``, ``landing_um``): floats with ``math.exp``, arrays with ``np.exp``."""
        air, nodes, _, walk = exogenous
        static = self.static({a: s["q"] for a, s in states.items()}, nodes,
                             {a: s["direction"] for a, s in states.items()})
        out = {}
        for a, s in states.items():
            x = static[a] + s["landing_um"] + self._drift(a, t, air, nodes, walk)
            if self.creep_c:  # a command at -inf (none yet) has settled: exp(-inf) = 0
                x = x - self.creep_c * s["creep_sum"] * exp(-(t - s["t"]) / self.creep_tau_s)
            out[a] = x
        return out

    # ----- mechanics -----------------------------------------------------------------------------
    def after_command(self, state: StageState, t: float, q: float, landing_um: float) -> StageState:
        """Exact state update of one stage for a new setpoint ``q`` at time ``t``."""
        dq = q - state.q
        direction = state.direction
        if abs(dq) > self.deadband_um:
            direction = 1.0 if dq > 0 else -1.0
        creep_sum = dq
        if self.creep_c and math.isfinite(state.t):
            creep_sum += state.creep_sum * math.exp(-(t - state.t) / self.creep_tau_s)
        return StageState(t=t, q=q, direction=direction, creep_sum=creep_sum, landing_um=landing_um)

    def attained_now(self, t: float, states: Mapping[str, StageState]) -> dict[str, float]:
        """Every axis' true position (µm in its interferometer's frame) at one time, in plain floats."""
        return self._positions(t, self.exogenous.at1(t), {a: vars(s) for a, s in states.items()}, math.exp)

    def command_track(self, cmd_t: np.ndarray, cmd_q: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
        """One stage's state after each of a whole series of commands (sorted by time)."""
        n = len(cmd_t)
        landing = rng.normal(0.0, self.params.landing_sigma_um, n)
        out = {k: np.empty(n) for k in ("t", "q", "direction", "creep_sum", "landing_um")}
        state = StageState()
        for k in range(n):
            state = self.after_command(state, float(cmd_t[k]), float(cmd_q[k]), float(landing[k]))
            for name, value in vars(state).items():
                out[name][k] = value
        return out

    def attained_along(self, t: np.ndarray, tracks: Mapping[str, Mapping[str, np.ndarray]]) -> dict[str, np.ndarray]:
        """True positions at times ``t`` under each axis' command track from :meth:`command_track`."""
        t = np.asarray(t, dtype=np.float64)
        rows = {}
        for axis, track in tracks.items():
            i = np.searchsorted(track["t"], t, side="right") - 1
            before, j = i < 0, np.maximum(i, 0)
            rows[axis] = {name: np.where(before, getattr(StageState, name), col[j]) for name, col in track.items()}
        return self._positions(t, self.exogenous.at(t), rows, np.exp)

    # ----- sensors -------------------------------------------------------------------------------
    def wander(self, axis: str, t: np.ndarray) -> np.ndarray:
        """The slow wander of ``axis``' interferometer beam at times ``t``."""
        return self.beams[axis].at(np.atleast_1d(np.asarray(t, dtype=np.float64)))[2]

    def refraction_um(self, t: np.ndarray) -> np.ndarray:
        """What the air's refractive index adds to every beam's reading (µm): the optical path of
        ``dead_path_um`` changes by L·Δn, and the built-in compensation misses two parts of Δn: the beam's air
        vs its lagging Pt100 (Edlén: −0.93 ppm/K) and a random walk (pressure/humidity it does not follow).
        Neither averages out over a run; the first follows the room, the second is not stationary."""
        p = self.params
        _, nodes, _, _ = self.exogenous.at(t)
        delta_n = DN_DT_PER_C * (nodes["beam"] - nodes["refraction_comp"]) + 1e-6 * self.exogenous.index_at(t)
        result: np.ndarray = p.dead_path_um * delta_n
        return result

    def measure_position(self, axis: str, t: np.ndarray, true_x: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """``axis``' interferometer: truth + its beam's wander + white noise (``noise`` ~ N(0, 1)), quantised."""
        p = self.params
        raw = true_x + self.wander(axis, t) + p.interferometer_noise_um * noise
        if p.dead_path_um:
            raw = raw + self.refraction_um(np.atleast_1d(np.asarray(t, dtype=np.float64)))
        result: np.ndarray = np.round(raw / p.interferometer_resolution_um) * p.interferometer_resolution_um
        return result

    def measure_position1(self, axis: str, t: float, true_x: float, noise: float) -> float:
        wander = self.beams[axis].at1(t)[2]
        p = self.params
        raw = true_x + wander + p.interferometer_noise_um * noise
        if p.dead_path_um:
            raw = raw + float(self.refraction_um(np.array([t]))[0])
        return round(raw / p.interferometer_resolution_um) * p.interferometer_resolution_um

    def measure_temperature1(self, truth: float, noise: float) -> float:
        p = self.params
        return round((truth + p.tc_noise_c * noise) / p.tc_quantum_c) * p.tc_quantum_c

    def measure_temperature(self, channel: str, truth: np.ndarray, noise: np.ndarray) -> np.ndarray:
        """Thermocouple readings: truth + white noise (``noise`` ~ N(0, 1)), quantised to 0.01 °C."""
        p = self.params
        return np.round((truth + p.tc_noise_c * noise) / p.tc_quantum_c) * p.tc_quantum_c


@dataclass(frozen=True)
class CellVariant:
    """A named cell (``[simulation] cell``, ``--cell``): its magnitudes and the effects it always has on."""

    name: str
    params: CellParams
    #: effects always on (a one-axis cell's; a stack keeps no memory of the path, so it has none of them)
    effects: Mapping[str, Mapping[str, float]] = field(default_factory=dict)

    def effects_with(self, chosen: Mapping[str, dict[str, float]], n_axes: int = 1) -> dict[str, dict[str, float]]:
        """This cell's own effects (one axis only) with ``chosen`` on top (its parameters win)."""
        own = {name: dict(values) for name, values in self.effects.items()} if n_axes == 1 else {}
        return {**own, **chosen}


#: The realistic cell's magnitudes: what a lab's cell has and no candidate term reproduces exactly. Each with
#: why (drivers/simulated/README.md, "The realistic cell"); the ideal cell is ``CellParams()``.
REALISTIC_PARAMS = CellParams(
    tc_noise_c=0.02,            # K-type thermocouple + a 16-bit module (ADAM-4018 class): 0.01-0.05 K
    tc_lag_s=20.0,              # a sheathed/glued junction in still air: seconds to tens of seconds
    bend_scale_c=1.0,           # a square within the 0.5 °C of training; 1.8x it 1.5 °C warmer, 0.6x cooler
    bend_lag_s=1200.0,          # the gradient through the bracket lags the surface T2 reads
    heat_rise_c=0.3,            # the amplifier/controller a few cm away: ~0.3 °C on its plate when on
    heat_period_s=5400.0, heat_on_s=2400.0, heat_tau_s=1200.0, heat_k_um_per_c=-0.5,
    dead_path_um=150_000.0,     # 150 mm of beam in air
    refraction_comp_tau_s=1800.0,      # the compensation's Pt100 in its housing lags the beam's air
    index_walk_ppm_per_sqrt_h=0.1,     # what the compensation misses (barometer drift, humidity): 15 nm/√h
)

#: the named cells: ``ideal`` (the model's own form: what it proves is that the fit recovers a cell it can
#: represent) and ``realistic`` (what a lab's cell does that no candidate term reproduces)
CELLS: dict[str, CellVariant] = {
    "ideal": CellVariant("ideal", CellParams()),  # the paper's model form: linear in T1..T4 plus the bracket's square
    "realistic": CellVariant(
        "realistic", REALISTIC_PARAMS,
        # closed loop (the paper's stage: PID on its capacitive sensor): what its loop leaves of the piezo's
        # 10-15 % hysteresis and ~1 %/decade creep is its sensor's: 0.02 % of the stroke, 0.2 % of a step settling
        {"hysteresis": {"h_um": 0.10, "deadband_um": 0.5}, "creep": {"c": 0.002, "tau_s": 15.0}}),
}


def cell_variant(name: str) -> CellVariant:
    """The named cell; an unknown name raises :class:`UnknownNameError` listing the valid ones."""
    try:
        return CELLS[name]
    except KeyError:
        raise UnknownNameError(f"unknown cell {name!r}; valid cells: {', '.join(CELLS)}") from None
